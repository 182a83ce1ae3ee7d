"""Stage P validation, budget arithmetic, and the analytic allocation S1b-S1e."""

from __future__ import annotations

import numpy as np
import pytest

from warpgauss.core.profiling import StageRecorder
from warpgauss.encoding.allocate import AllocationConfig, allocate, draw_seeds
from warpgauss.errors import WarpgaussError
from warpgauss.field.analysis import (
    DeviceVolume,
    budget_from_ratio,
    check_budget,
    normalise,
    seed_limit,
    split_budget,
    structure_stats,
)


def _blobs(n=24, seed=0, plateau=True):
    """A sparse field: a few soft blobs, one with a flat (constant) core, zero background."""
    rng = np.random.default_rng(seed)
    z, y, x = np.meshgrid(*(np.arange(n, dtype=np.float64),) * 3, indexing="ij")
    v = np.zeros((n, n, n))
    for _ in range(4):
        c = rng.uniform(4, n - 4, 3)
        r2 = (x - c[0]) ** 2 + (y - c[1]) ** 2 + (z - c[2]) ** 2
        v += np.exp(-r2 / rng.uniform(4, 9))
    if plateau:
        v = np.minimum(v, 0.7)  # flat tops: occupied voxels with zero gradient
    return v.astype(np.float32)


def _voxel_coords(idx, shape_zyx):
    nz, ny, nx = shape_zyx
    return np.stack([idx % nx, (idx // nx) % ny, idx // (nx * ny)], axis=1)


def test_seed_limit_follows_the_spec_and_every_budget_under_it_fits():
    for eligible in range(0, 60, 7):
        for occupied in range(eligible, 90, 11):
            n_max = seed_limit(eligible, occupied)
            assert n_max == int(np.floor(min(eligible / 0.55, occupied / 0.45) + 1e-9))
            for n in range(0, n_max + 1):
                nd, nc = split_budget(n)
                assert nd + nc == n and nd <= eligible and nc <= occupied


def test_ratio_gives_spec_budget():
    # N = floor((S_src / R - H) / 48)
    assert budget_from_ratio(1_048_576, 20.0, 4096) == (1_048_576 // 20 - 4096) // 48
    assert budget_from_ratio(16_777_216, 100.0, 4096, 12) == int((16_777_216 / 100 - 4096) // 12)
    with pytest.raises(WarpgaussError, match="largest possible ratio"):
        budget_from_ratio(10_000, 1000.0, 4096)


@pytest.mark.parametrize("masked", [False, True])
def test_numpy_candidate_counts_match_the_kernels(device, masked):
    from warpgauss.core.warp import warp
    from warpgauss.kernels import analysis as ka

    wp = warp()
    v = _blobs(20, seed=3)
    v[:, :, 7] = v[:, :, 5]  # equal neighbours across a column: zero central difference there
    if masked:
        v[2:5, 3:9, 1:4] = np.nan  # a masked block next to structure
    f = normalise(v)
    assert (f.mask is not None) == masked
    if masked:
        assert f.n_valid == v.size - 3 * 6 * 3
    dv = DeviceVolume(f, device)
    for mode, expected in ((0, f.eligible), (1, f.occupied)):
        hist = wp.zeros(ka.KEY_BINS, dtype=wp.int64, device=device)
        count = wp.zeros(1, dtype=wp.int64, device=device)
        wp.launch(
            ka.seed_key_histogram,
            dim=dv.values.shape,
            inputs=[dv.values, dv.mask, dv.has_mask, mode, 7],
            outputs=[hist, count],
            device=device,
        )
        assert int(count.numpy()[0]) == expected == int(hist.numpy().sum())
    assert 0 < f.eligible < f.occupied  # the plateau makes some occupied voxels ineligible


def test_draws_are_distinct_eligible_and_deterministic(device):
    f = normalise(_blobs(24, seed=1))
    dv = DeviceVolume(f, device)
    vals = f.values.reshape(-1)
    for mode, pool in ((0, f.eligible), (1, f.occupied)):
        for k in (1, 17, pool // 2, pool):
            idx = draw_seeds(dv, k, mode, stream=11).numpy()
            assert idx.size == k and np.unique(idx).size == k
            assert np.all(vals[idx] > 0.02)
            again = draw_seeds(dv, k, mode, stream=11).numpy()
            np.testing.assert_array_equal(idx, again)
    other = draw_seeds(dv, 50, 1, stream=12).numpy()
    assert not np.array_equal(np.sort(other), np.sort(draw_seeds(dv, 50, 1, stream=11).numpy()))


def test_detail_draw_follows_gradient_magnitude(device):
    # two slabs with linear ramps of gradient 1:4: detail seeds land in proportion to |grad V|
    # (weighted without replacement; drawing 10 % of the pool keeps shares close to the weights)
    n = 32
    v = np.zeros((n, n, n), np.float32)
    ramp = np.arange(n, dtype=np.float32)
    v[:, :, :] = 0.5
    v[:, : n // 2, :] += 0.001 * ramp[None, None, :]
    v[:, n // 2 :, :] += 0.004 * ramp[None, None, :]
    f = normalise(v)
    dv = DeviceVolume(f, device)
    idx = draw_seeds(dv, f.eligible // 10, 0, stream=5).numpy()
    y = (idx // n) % n
    share_steep = np.mean(y >= n // 2)
    g = np.sqrt(sum(np.gradient(f.values.astype(np.float64), axis=a) ** 2 for a in range(3)))
    expected = g[:, n // 2 :, :].sum() / g.sum()  # first-order inclusion share of the steep half
    assert 0.6 < expected < 0.9
    assert share_steep == pytest.approx(expected, abs=0.03)


def test_allocation_exact_budget_scales_anisotropy_and_determinism(device):
    f = normalise(_blobs(24, seed=2))
    n_max = seed_limit(f.eligible, f.occupied)
    dv = DeviceVolume(f, device)
    cfg = AllocationConfig()
    cap = cfg.resolved_cap(f.shape_xyz)
    for n in (1, 2, 3, 50, 333, n_max):
        params, facts = allocate(dv, n, seed=4, config=cfg, timer=StageRecorder())
        assert params.shape == (n, 12) and np.all(np.isfinite(params))
        s = np.exp(params[:, 3:6].astype(np.float64))
        assert np.all(s <= cap * (1 + 1e-6)) and np.all(s >= cfg.scale_min * (1 - 1e-6))
        assert np.all(s.max(1) / s.min(1) <= cfg.max_aniso * (1 + 1e-5))
        np.testing.assert_allclose(np.linalg.norm(params[:, 6:10], axis=1), 1.0, atol=1e-5)
        assert np.all(params[:, 11] == np.float32(cfg.init_weight))
        assert facts["detail_seeds"] + facts["coverage_seeds"] == n
        # centres stay within half a voxel of distinct voxels in each draw
        nd = facts["detail_seeds"]
        for part in (params[:nd], params[nd:]):
            vox = np.round(part[:, :3]).astype(np.int64)
            assert np.all(np.abs(part[:, :3] - vox) <= 0.5 + 1e-6)
            assert np.unique(vox, axis=0).shape[0] == part.shape[0]
    a, _ = allocate(dv, 200, seed=9, config=cfg, timer=StageRecorder())
    b, _ = allocate(dv, 200, seed=9, config=cfg, timer=StageRecorder())
    c, _ = allocate(dv, 200, seed=10, config=cfg, timer=StageRecorder())
    assert a.tobytes() == b.tobytes()  # same seed, same device: bit-identical
    assert not np.array_equal(a, c)
    with pytest.raises(WarpgaussError, match=f"N_max = {n_max}"):
        check_budget(f, n_max + 1, 4096)
    with pytest.raises(WarpgaussError, match="at least 1"):
        check_budget(f, 0, 4096)


def test_principal_axis_lies_in_a_planar_interface(device):
    n = 32
    normal = np.array([0.3, 0.5, 0.81])
    normal /= np.linalg.norm(normal)
    z, y, x = np.meshgrid(*(np.arange(n, dtype=np.float64),) * 3, indexing="ij")
    d = x * normal[0] + y * normal[1] + z * normal[2] - normal.sum() * n / 2
    v = (0.5 * (1 + np.tanh(d / 2.0))).astype(np.float32)
    f = normalise(v)
    dv = DeviceVolume(f, device)
    cfg = AllocationConfig(scale_cap=8.0)  # room to elongate on this small grid
    params, _ = allocate(dv, 400, seed=0, config=cfg, timer=StageRecorder())
    from reference.field_ref import quat_to_matrix

    R = quat_to_matrix(params[:, 6:10])
    mu = params[:, :3].astype(np.float64)
    near = np.abs(mu @ normal - normal.sum() * n / 2) < 4  # gradient-bearing seeds
    assert near.sum() > 100
    tangent = R[near][:, :, 0]
    assert np.max(np.abs(tangent @ normal)) < 0.05  # principal axis within ~3 degrees of the plane
    third = R[near][:, :, 2]
    assert np.min(np.abs(third @ normal)) > 0.99  # the short axis is the normal
    s = np.exp(params[near][:, 3:6])
    assert np.mean(s[:, 0] > 1.5 * s[:, 2]) > 0.5  # elongated along the interface


def test_masked_voxels_are_never_seeded_nor_counted(device):
    v = _blobs(20, seed=5, plateau=False)
    fill = -999.0
    v[:, :, :10] = fill  # half the volume is "land"
    f = normalise(v, fill_value=fill)
    assert f.vmin >= 0.0 and f.n_valid == v.size // 2
    dv = DeviceVolume(f, device)
    params, _ = allocate(dv, min(300, seed_limit(f.eligible, f.occupied)), seed=1, config=AllocationConfig(), timer=StageRecorder())
    assert np.all(np.round(params[:, 0]) >= 10)


def test_bad_volumes_are_refused():
    with pytest.raises(WarpgaussError, match="constant"):
        normalise(np.full((8, 8, 8), 3.0, np.float32))
    with pytest.raises(WarpgaussError, match="no finite value"):
        normalise(np.full((8, 8, 8), np.nan, np.float32))
    with pytest.raises(WarpgaussError, match="2D"):
        normalise(np.zeros((8, 8), np.float32))


def _stats_numpy(v: np.ndarray, lag: int = 16) -> dict:
    """Independent float64 computation of SPEC section 5 (no mask)."""
    v = v.astype(np.float64)
    v = (v - v.min()) / (v.max() - v.min())
    occ = v > 0.02
    g = np.zeros(v.shape)
    for ax in range(3):
        g += np.gradient(v, axis=ax) ** 2  # central inside, one-sided at the border: as the kernel
    g = np.sqrt(g)[occ]
    top = np.sort(g)[::-1][: int(np.ceil(0.1 * g.size))]

    def s(l):
        tot, cnt = 0.0, 0
        for ax in range(3):
            a = np.moveaxis(v, ax, 0)
            o = np.moveaxis(occ, ax, 0)[: a.shape[0] - l]
            d = np.abs(a[l:] - a[:-l])[o]
            tot, cnt = tot + d.sum(), cnt + d.size
        return tot / cnt

    return {"occupancy": occ.mean(), "grad_top10": top.sum() / g.sum(), "s1": s(1), "s16": s(lag)}


def test_structure_statistics_match_numpy(device):
    v = _blobs(40, seed=6)
    f = normalise(v)
    st = structure_stats(DeviceVolume(f, device))
    ref = _stats_numpy(v)
    assert not st["sampled"]
    assert st["occupancy"] == pytest.approx(ref["occupancy"], abs=1e-12)
    assert st["grad_top10"] == pytest.approx(ref["grad_top10"], rel=1e-5)
    assert st["s1"] == pytest.approx(ref["s1"], rel=1e-5)
    assert st["s16"] == pytest.approx(ref["s16"], rel=1e-5)
    assert st["s1_s16"] == pytest.approx(ref["s1"] / ref["s16"], rel=1e-5)


def test_every_feasible_budget_yields_exactly_n(device):
    v = np.zeros((6, 7, 8), np.float32)
    v[1:5, 2:6, 2:7] = np.linspace(0.1, 1.0, 4 * 4 * 5).reshape(4, 4, 5)
    v[2, 3, 3:5] = 0.5  # a flat pair: occupied with zero gradient on x
    f = normalise(v)
    n_max = seed_limit(f.eligible, f.occupied)
    assert 50 < n_max < 200
    dv = DeviceVolume(f, device)
    for n in range(1, n_max + 1):
        params, facts = allocate(dv, n, seed=n, config=AllocationConfig(), timer=StageRecorder())
        assert params.shape == (n, 12) and np.all(np.isfinite(params))
    with pytest.raises(WarpgaussError, match="N_max"):
        check_budget(f, n_max + 1, 4096)
