"""Motion compensation of a warm start (issue #21): the Lucas-Kanade step against a float64 numpy
reference, a known shift recovered, and a warm start that follows the motion scoring above one
that does not."""

from __future__ import annotations

import numpy as np
import pytest

import warpgauss
from warpgauss.core.warp import warp
from warpgauss.readers.synthetic import generate, generate_series


def _sample(f: np.ndarray, p) -> float:
    """Trilinear at p = (x, y, z), edges held (as kernels/motion.py ``sample``)."""
    nz, ny, nx = f.shape
    x, y, z = (min(max(float(p[a]), 0.0), float(n - 1)) for a, n in zip(range(3), (nx, ny, nz)))
    i0, j0, k0 = min(int(x), max(nx - 2, 0)), min(int(y), max(ny - 2, 0)), min(int(z), max(nz - 2, 0))
    i1, j1, k1 = min(i0 + 1, nx - 1), min(j0 + 1, ny - 1), min(k0 + 1, nz - 1)
    fx, fy, fz = x - i0, y - j0, z - k0

    def lerp(a, b, t):
        return a + t * (b - a)

    c00 = lerp(f[k0, j0, i0], f[k0, j0, i1], fx)
    c01 = lerp(f[k0, j1, i0], f[k0, j1, i1], fx)
    c10 = lerp(f[k1, j0, i0], f[k1, j0, i1], fx)
    c11 = lerp(f[k1, j1, i0], f[k1, j1, i1], fx)
    return lerp(lerp(c00, c01, fy), lerp(c10, c11, fy), fz)


def test_one_lucas_kanade_step_matches_a_float64_reference():
    from warpgauss.kernels import motion as km

    wp = warp()
    rng = np.random.default_rng(3)
    ref = rng.random((8, 8, 8))
    cur = np.roll(ref, 1, axis=2) + 0.01 * rng.random((8, 8, 8))
    block, lam = 4, 1e-6
    start = rng.normal(0.0, 0.3, (2, 2, 2, 3))
    out = wp.empty((2, 2, 2), dtype=wp.vec3, device="cpu")
    conf = wp.empty((2, 2, 2), dtype=float, device="cpu")
    wp.launch(
        km.lk_step,
        dim=(2, 2, 2),
        inputs=[
            wp.array(ref.astype(np.float32), device="cpu"),
            wp.array(cur.astype(np.float32), device="cpu"),
            wp.array(start.astype(np.float32), dtype=wp.vec3, device="cpu"),
            block,
            lam,
        ],
        outputs=[out, conf],
        device="cpu",
    )
    got, got_conf = out.numpy(), conf.numpy()
    e = np.eye(3)
    for bk, bj, bi in np.ndindex(2, 2, 2):
        d = start[bk, bj, bi]
        a, b = np.zeros((3, 3)), np.zeros(3)
        for k, j, i in np.ndindex(block, block, block):
            x = np.array([bi * block + i, bj * block + j, bk * block + k], float)
            p = x + d
            g = np.array([0.5 * (_sample(cur, p + e[c]) - _sample(cur, p - e[c])) for c in range(3)])
            a += np.outer(g, g)
            b += g * (ref[int(x[2]), int(x[1]), int(x[0])] - _sample(cur, p))
        tr = np.trace(a)
        step = np.linalg.solve(a + np.eye(3) * (lam + 1e-3 * tr), b)
        n = np.linalg.norm(step)
        if n > 2.0:
            step *= 2.0 / n
        np.testing.assert_allclose(got[bk, bj, bi], d + step, rtol=2e-3, atol=2e-4)
        assert got_conf[bk, bj, bi] == pytest.approx(tr, rel=1e-4)


def test_a_known_shift_is_recovered():
    from warpgauss.encoding.motion import BLOCK, compensate, estimate_motion
    from warpgauss.field.analysis import DeviceVolume, normalise

    wp = warp()
    v = generate("bubbles", 32)
    moved = np.roll(v, (1, -2), axis=(1, 2))  # y + 1, x - 2 voxels
    a = wp.array(v, device="cpu")
    b = wp.array(moved, device="cpu")
    disp = estimate_motion(a, b).numpy()
    # where there is structure (not at the wrapped faces), the blocks found (-2, +1, 0)
    inner = disp[2:-2, 2:-2, 2:-2].reshape(-1, 3)
    np.testing.assert_allclose(np.median(inner, axis=0), [-2.0, 1.0, 0.0], atol=0.15)
    m0 = warpgauss.encode(v, budget=300, iterations=40, samples=512, device="cpu", self_test=False, format="full")
    f = normalise(moved)
    p, facts = compensate(m0.params, DeviceVolume(f, "cpu"))
    assert facts["block"] == BLOCK and 1.5 < facts["mean_move_voxels"] < 3.0
    shift = np.median(p[:, :3] - m0.params[:, :3], axis=0)
    np.testing.assert_allclose(shift, [-2.0, 1.0, 0.0], atol=0.2)


def test_a_warm_start_follows_the_motion():
    kw = dict(budget=400, iterations=30, samples=512, device="cpu", self_test=False, format="full")
    v0, v1 = generate_series("bubbles", 28, 2, turn_degrees=10.0)
    m0 = warpgauss.encode(v0, **kw)
    follow = warpgauss.encode(v1, warm_start=m0, **kw)
    stay = warpgauss.encode(v1, warm_start=m0, motion=False, **kw)
    again = warpgauss.encode(v1, warm_start=m0, **kw)
    np.testing.assert_array_equal(follow.params, again.params)  # same seed, same device: same model
    start_follow = follow.report["evaluation"]["analytic"]["psnr_db"]
    start_stay = stay.report["evaluation"]["analytic"]["psnr_db"]
    assert start_follow > start_stay + 3.0
    assert follow.report["psnr_db"] > stay.report["psnr_db"]
    assert follow.report["allocation"]["motion"]["passes"] >= 1
    assert any(s["what"] == "S1m motion compensation" for s in stay.report["skipped"])


def test_a_primitive_the_motion_carries_out_of_the_grid_stays():
    """shift_centres moves a centre by the displacement at it, unless that leaves the grid: then
    the primitive stays where it was, unturned, and is counted (moved = -1)."""
    from warpgauss.core.warp import warp
    from warpgauss.kernels import motion as km

    wp = warp()
    p0 = np.zeros((3, 12), np.float32)
    p0[:, 3:6] = 1.0  # unit scales
    p0[:, 9] = 1.0  # identity rotation (x, y, z, w)
    p0[:, 10:12] = 0.5
    p0[:, 0:3] = [[5.0, 5.0, 5.0], [14.8, 5.0, 5.0], [0.2, 5.0, 5.0]]
    disp = np.zeros((8, 8, 8, 3), np.float32)
    disp[..., 0] = 1.0  # everything moves one voxel along +x
    p = wp.array(p0, dtype=float, device="cpu")
    moved = wp.empty(3, dtype=float, device="cpu")
    d = wp.array(disp, dtype=wp.vec3, device="cpu")
    wp.launch(km.shift_centres, dim=3, inputs=[p, d, 2, wp.vec3(16.0, 16.0, 16.0), 1], outputs=[moved], device="cpu")
    out = p.numpy()
    np.testing.assert_allclose(out[0, :3], [6.0, 5.0, 5.0])
    np.testing.assert_array_equal(out[1], p0[1])  # 15.8 > 15.5: it would leave the grid, so it stays
    np.testing.assert_allclose(out[2, :3], [1.2, 5.0, 5.0])
    np.testing.assert_allclose(moved.numpy(), [1.0, -1.0, 1.0])
    np.testing.assert_array_equal(out[:, 6:], p0[:, 6:])  # a uniform shift turns nothing
