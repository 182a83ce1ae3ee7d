"""The truncation-aware binned evaluator against the dense Warp kernel and a float64 numpy reference."""

from __future__ import annotations

import math

import numpy as np
import pytest
from conftest import random_params
from reference.field_ref import field as field_ref

from warpgauss.field.gaussians import GaussianField, grid_points, plan_bins


def _points(rng, shape, m):
    return rng.uniform(-0.5, np.asarray(shape) - 0.5, size=(m, 3)).astype(np.float32)


def test_binned_matches_dense_and_float64_on_mixed_rotated_anisotropic(device):
    rng = np.random.default_rng(1)
    shape = (24, 20, 16)
    # three size classes (sub-voxel, a few voxels, large) so that several bin levels are used
    params = np.concatenate(
        [
            random_params(rng, 60, shape, (-1.5, -0.8), aniso=3.0),
            random_params(rng, 60, shape, (0.0, 0.7), aniso=3.0),
            random_params(rng, 10, shape, (1.5, 2.0), aniso=3.0),
        ]
    )
    f = GaussianField(params, shape, device=device)
    assert len(f.plan.sizes) >= 3
    pts = _points(rng, shape, 3000)
    v, d, c = f.evaluate_full(pts)
    vd, dd, cd = f.evaluate_dense(pts)
    vr, dr, cr = field_ref(params, pts)
    np.testing.assert_array_equal(c, cd)  # the same pairs pass the cut
    np.testing.assert_allclose(d, dd, rtol=2e-6, atol=1e-6)
    np.testing.assert_allclose(v, vd, rtol=2e-6, atol=1e-6)
    np.testing.assert_allclose(d, dr, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(v, vr, rtol=1e-5, atol=1e-5)
    # pairs differ from float64 only where m sits on the 5-sigma shell within round-off
    assert np.abs(c - cr).max() <= 1 and (c != cr).mean() < 0.01
    assert c.sum() > 0 and (d > 0.05).mean() > 0.3  # the test exercises dense coverage, not empty space


def test_single_gaussian_negative_coordinates_and_outside_grid(device):
    p = np.zeros((1, 12), np.float32)
    p[0, :3] = (-2.0, 0.5, 3.0)  # centre outside the grid on x
    p[0, 3:6] = np.log([1.0, 2.0, 0.5])
    p[0, 6:10] = (0.0, 0.0, np.sin(0.4), np.cos(0.4))
    p[0, 10], p[0, 11] = 0.7, 0.9
    shape = (8, 8, 8)
    f = GaussianField(p, shape, device=device)
    pts = np.array([[-2.0, 0.5, 3.0], [-0.5, 0.5, 3.0], [1.0, 1.0, 3.2], [7.5, 7.5, 7.5], [-6.0, 0.5, 3.0]], np.float32)
    v, d, c = f.evaluate_full(pts)
    vr, dr, cr = field_ref(p, pts)
    np.testing.assert_allclose(d, dr, rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(v, vr, rtol=1e-5, atol=1e-7)
    np.testing.assert_array_equal(c, cr)
    assert d[0] == pytest.approx(0.9, rel=1e-6) and v[0] == pytest.approx(0.7, rel=1e-6)
    assert c[3] == 0 and v[3] == 0.0  # far corner: empty cell, value 0 under the density floor


def test_decode_equals_point_evaluation_and_resampling(device):
    rng = np.random.default_rng(2)
    shape = (12, 10, 9)
    params = random_params(rng, 80, shape, (0.0, 1.0), aniso=2.0)
    f = GaussianField(params, shape, device=device)
    grid = f.decode()
    assert grid.shape == (9, 10, 12)
    np.testing.assert_array_equal(grid.ravel(), f.evaluate(grid_points(shape)))
    # a grid of twice the resolution: voxel (i) centre sits at (i + 0.5) / 2 - 0.5 model voxels
    fine = f.decode((24, 20, 18))
    pts = (grid_points((24, 20, 18)) + 0.5) * 0.5 - 0.5
    np.testing.assert_allclose(fine.ravel(), f.evaluate(pts), rtol=1e-6, atol=1e-7)


def test_bin_plan_levels_cover_every_radius():
    r = np.array([0.3, 0.9, 1.5, 3.9, 4.0, 17.0, 100.0])
    plan = plan_bins(r, (64, 64, 64))
    sizes = np.array(plan.sizes)
    assert np.all(np.diff(sizes) > 0) and sizes[-1] > 1e30  # ascending, global last
    for x in r:  # every radius has a level at least as large
        assert sizes[sizes >= x].size > 0
    assert plan.total_cells == sum(a * b * c for a, b, c in plan.dims)


def test_huge_and_degenerate_primitives_stay_finite(device):
    p = np.zeros((3, 12), np.float32)
    p[:, :3] = 4.0
    p[0, 3:6] = 50.0  # scale far beyond the grid: clamped exponent, global level
    p[1, 3:6] = -50.0  # vanishing scale: clamped, contributes only at its centre
    p[2, 6:10] = 0.0  # zero quaternion: identity rotation
    p[:, 10], p[:, 11] = 0.5, 0.5
    f = GaussianField(p, (8, 8, 8), device=device)
    v = f.decode()
    assert np.all(np.isfinite(v))


def test_bin_plan_is_stable_while_radii_drift_within_their_octaves():
    """Refinement re-plans every 100 iterations; a plan that changes with every small drift of the
    smallest radius would re-allocate the tables and re-capture the iteration graph each time."""
    rng = np.random.default_rng(0)
    r = rng.uniform(2.1, 30.0, 5000)
    a = plan_bins(r, (96, 80, 64))
    b = plan_bins(r * rng.uniform(0.97, 1.03, r.size).clip(2.05 / r, 31.0 / r), (96, 80, 64))
    assert a == b
    assert math.log2(a.sizes[0]).is_integer()  # levels start at a power of two


def test_device_plan_equals_the_numpy_plan(device):
    """plan_bins_on_device finds the least radius and the occupied classes on the device and must
    give plan_bins' plan: spread radii, exact powers of two, radii below MIN_CELL, non-finite
    radii (ignored), a huge one (coarsened levels), and none finite at all."""
    from warpgauss.core.warp import warp
    from warpgauss.field.gaussians import plan_bins_on_device

    wp = warp()
    rng = np.random.default_rng(3)
    cases = [
        rng.uniform(0.3, 40.0, 2000),
        np.array([1.0, 2.0, 4.0, 8.0, 8.0, 16.0, 3.0]),
        np.concatenate([rng.uniform(0.01, 0.9, 50), [np.nan, np.inf, -np.inf, 5.5]]),
        np.array([2.5, 1.0e9, 7.0]),
        np.array([np.nan, np.inf]),
        2.0 ** rng.integers(-3, 9, 300) * rng.choice([1.0, 1.0 - 1e-7, 1.0 + 1e-7], 300),
    ]
    for shape in ((64, 64, 64), (300, 20, 9)):
        for r in cases:
            r = r.astype(np.float32)
            got = plan_bins_on_device(wp.array(r, dtype=float, device=device), shape)
            assert got == plan_bins(r, shape), (r[:8], shape)
