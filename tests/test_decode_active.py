"""Decode skips bricks no primitive reaches, and gives exactly the values a full evaluation gives."""

from __future__ import annotations

import numpy as np
import pytest

from warpgauss.field.gaussians import GaussianField


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


@pytest.mark.parametrize("path", ["brick lists", "halved slabs", "cell walk"])
def test_decode_equals_the_row_major_kernel_bit_for_bit(device, path, monkeypatch):
    """Decode lists the primitives of each 8^3 brick (a slab whose lists would not fit in halves
    along z, and one a brick high whose lists still would not by the cell walk in 8^3 thread
    blocks) over slabs whose sides are not multiples of 8; every voxel must still be written once,
    with the row-major kernel's exact value, also on resampled grids and with primitives centred
    outside the grid."""
    from warpgauss.core.warp import warp
    from warpgauss.field import gaussians as wf
    from warpgauss.kernels import field as kf

    wp = warp()
    if path == "cell walk":
        monkeypatch.setattr(wf, "MAX_BRICK_LIST", 0)
    halves = []
    if path == "halved slabs":  # the larger slabs' lists hold more entries than this
        monkeypatch.setattr(wf, "MAX_BRICK_LIST", 100)
        plain = GaussianField.decode_slab

        def counted(self, out, z0, scale, offset=None):
            halves.append(out.shape[0])
            plain(self, out, z0, scale, offset)

        monkeypatch.setattr(GaussianField, "decode_slab", counted)
    rng = np.random.default_rng(6)
    shape = (27, 13, 21)
    p = _sparse_params(rng, 80, shape)
    p[2, 3:6] = 2.5  # sigma 12 voxels: a level of its own
    gf = GaussianField(p, shape, device)
    gf._active = (None, 1.0)  # no brick skip in the cell walk: its blocked layout alone
    for out_shape in (shape, (9, 30, 5), (40, 17, 33)):
        nx, ny, nz = out_shape
        scale = wp.vec3(*(shape[a] / out_shape[a] for a in range(3)))
        ref = wp.empty((nz, ny, nx), dtype=float, device=device)
        wp.launch(kf.eval_grid_binned, dim=(nz, ny, nx), inputs=[0, scale, gf.prims], outputs=[ref], device=device)
        for z0 in (0, 3):  # a slab that starts at slice 0, and one further in
            got = wp.full((nz - z0, ny, nx), np.nan, dtype=float, device=device)
            gf.decode_slab(got, z0, scale)
            expect = ref.numpy()[z0:]
            assert np.count_nonzero(expect) > expect.size // 4
            np.testing.assert_array_equal(got.numpy(), expect)
    if path == "halved slabs":
        assert len(halves) > 6 and 8 in halves and 13 in halves, halves  # the 21-slice slab halved: 8 + 13


def test_slabs_after_a_halved_one_start_at_the_height_that_fitted(device, monkeypatch):
    """Once a slab's lists have had to be halved, the decode's later slabs of the same sampling are
    cut to the height that fitted before they are listed (one listing each piece, not a wasted one
    of the whole slab): the same values as a decode whose lists always fit."""
    from warpgauss.field import gaussians as wf

    rng = np.random.default_rng(9)
    shape = (20, 18, 64)
    p = _sparse_params(rng, 60, shape)
    p[:, 2] = rng.uniform(0.0, shape[2], 60)  # spread along z: every slab has lists
    whole = GaussianField(p, shape, device).decode()
    monkeypatch.setattr(wf, "DECODE_SLAB_VOXELS", 20 * 18 * 16)  # four slabs of 16 slices
    monkeypatch.setattr(wf, "MAX_BRICK_LIST", 40)
    gf = GaussianField(p, shape, device)
    np.testing.assert_array_equal(gf.decode(), whole)
    assert gf._fit_height, "no slab was halved: the case does not test the rule"

    class Forgets(dict):  # the decode without the rule: every slab listed whole first
        def __setitem__(self, key, value):
            pass

    plain = GaussianField(p, shape, device)
    plain._fit_height = Forgets()
    np.testing.assert_array_equal(plain.decode(), whole)
    assert gf.decode_listings < plain.decode_listings, (gf.decode_listings, plain.decode_listings)


def test_brick_lists_hold_exactly_the_primitives_whose_box_meets_the_brick(device):
    """The list of a brick is the binned-order subsequence of primitives whose 5-sigma box meets
    the brick's voxel centres (against a float64 numpy check; boxes touching only within the
    rounding margin may be listed too)."""
    from warpgauss.core.warp import warp
    from warpgauss.kernels import decode as kd

    wp = warp()
    rng = np.random.default_rng(8)
    shape = (30, 20, 17)
    gf = GaussianField(_sparse_params(rng, 50, shape), shape, device)
    nx, ny, nz = shape
    e = int(kd.BRICK_EDGE)
    bricks = wp.vec3i(-(-nx // e), -(-ny // e), -(-nz // e))
    nb = int(np.prod(bricks))
    counts = wp.zeros(nb, dtype=int, device=device)
    ends = wp.zeros(nb, dtype=int, device=device)
    items = wp.zeros(1, dtype=int, device=device)
    common = [0, wp.vec3(1.0, 1.0, 1.0), wp.vec3(0.0, 0.0, 0.0), wp.vec3i(nx, ny, nz), bricks, gf.prims]
    wp.launch(kd.list_bricks, dim=nb, inputs=[*common, 0, ends, counts, items], device=device)
    c = counts.numpy()
    ends = wp.array(np.cumsum(c).astype(np.int32), dtype=int, device=device)
    items = wp.full(int(c.sum()), -1, dtype=int, device=device)
    wp.launch(kd.list_bricks, dim=nb, inputs=[*common, 1, ends, counts, items], device=device)
    lists = np.split(items.numpy(), np.cumsum(c)[:-1])
    mu = gf.prims.mu.numpy().astype(np.float64)
    ext = gf.prims.ext.numpy().astype(np.float64)
    listed_somewhere = 0
    for b, got in enumerate(lists):
        bx, by, bz = b % bricks[0], (b // bricks[0]) % bricks[1], b // (bricks[0] * bricks[1])
        lo = np.array([bx, by, bz], np.float64) * e
        hi = np.minimum(lo + e, shape) - 1
        meets = np.all((mu - ext <= hi + 1e-3) & (mu + ext >= lo - 1e-3), axis=1)
        surely = np.all((mu - ext < hi - 1e-3) & (mu + ext > lo + 1e-3), axis=1)
        assert np.all(np.diff(got) > 0)  # binned order, no repeats
        assert set(np.flatnonzero(surely)) <= set(got) <= set(np.flatnonzero(meets))
        listed_somewhere += len(got)
    assert 0 < listed_somewhere < nb * gf.n // 2  # the lists cull
