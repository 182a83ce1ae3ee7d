"""Decode skips bricks no primitive reaches, and gives exactly the values a full evaluation gives."""

from __future__ import annotations

import numpy as np

from warpgauss.field import GaussianField


def _sparse_params(rng, n, shape_xyz):
    p = np.zeros((n, 12), np.float32)
    p[:, :3] = rng.uniform(-3.0, 1.0, (n, 3)) * 0.25 * np.array(shape_xyz) + np.array(shape_xyz) * 0.2  # a corner cluster
    p[:2, :3] = [[-4.0, 10.0, 12.0], [shape_xyz[0] + 2.0, 5.0, 5.0]]  # centres outside the grid
    p[:, 3:6] = rng.uniform(-0.5, 0.7, (n, 3))
    q = rng.normal(size=(n, 4))
    p[:, 6:10] = q / np.linalg.norm(q, axis=1, keepdims=True)
    p[:, 10] = rng.uniform(0.1, 1.0, n)
    p[:, 11] = rng.uniform(0.2, 1.0, n)
    return p


def test_active_decode_equals_full_decode_and_skips_empty_bricks(device):
    rng = np.random.default_rng(4)
    shape = (48, 40, 36)
    gf = GaussianField(_sparse_params(rng, 60, shape), shape, device)
    assert 0.0 < gf.active_fraction < 0.6  # most bricks are empty space
    fast = gf.decode()
    for out_shape in (None, (29, 51, 20)):  # the model grid and a resampled one
        a = gf.decode(out_shape)
        gf._active = (None, 1.0)  # every brick
        b = gf.decode(out_shape)
        gf._active = None
        np.testing.assert_array_equal(a, b)
    assert np.count_nonzero(fast) > 0 and np.count_nonzero(fast == 0) > fast.size // 2


def test_a_primitive_too_large_to_mark_makes_every_brick_active(device):
    rng = np.random.default_rng(5)
    shape = (136, 136, 136)  # 4,913 bricks: more than one primitive may mark one by one
    p = _sparse_params(rng, 10, shape)
    p[0, 3:6] = 5.0  # sigma 148 voxels: its box covers the whole grid many times over
    gf = GaussianField(p, shape, device)
    assert gf.active_bricks() is None and gf.active_fraction == 1.0
    assert np.all(np.isfinite(gf.decode((16, 16, 16))))


def test_blocked_decode_equals_the_row_major_kernel_bit_for_bit(device):
    """Decode runs 8^3 thread blocks (4x4x2 per warp) over slabs whose sides are not multiples of
    8; every voxel must still be written once, with the row-major kernel's exact value."""
    from warpgauss._warp import warp
    from warpgauss.kernels import field as kf

    wp = warp()
    rng = np.random.default_rng(6)
    shape = (27, 13, 21)
    gf = GaussianField(_sparse_params(rng, 80, shape), shape, device)
    gf._active = (None, 1.0)  # no brick skip: the blocked layout alone
    for out_shape in (shape, (9, 30, 5)):
        nx, ny, nz = out_shape
        scale = wp.vec3(*(shape[a] / out_shape[a] for a in range(3)))
        ref = wp.empty((nz, ny, nx), dtype=float, device=device)
        wp.launch(kf.eval_grid_binned, dim=(nz, ny, nx), inputs=[0, scale, gf.prims], outputs=[ref], device=device)
        got = wp.full((nz, ny, nx), np.nan, dtype=float, device=device)
        gf.decode_slab(got, 0, scale)
        expect = ref.numpy()
        assert np.count_nonzero(expect) > expect.size // 4
        np.testing.assert_array_equal(got.numpy(), expect)
