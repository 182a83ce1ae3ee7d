"""Refinement (S2): closed-form gradients against float64 finite differences, Adam, determinism."""

from __future__ import annotations

import math

import numpy as np
import pytest
from conftest import assert_matches_atomic_scatter, random_quaternions
from reference import loss_ref

from warpgauss.encoding.refine import LossWeights, RefineConfig, Refiner, self_test, stratum_counts
from warpgauss.field.analysis import DeviceVolume, normalise

SHAPE = (10, 10, 10)
SCALE_MIN, SCALE_CAP = 0.9, 2.0  # tight bounds so that the cap term acts in the test scene


def _scene(seed=0, n=12, m=200):
    rng = np.random.default_rng(seed)
    z, y, x = np.meshgrid(*(np.arange(10.0),) * 3, indexing="ij")
    vol = 0.5 + 0.4 * np.sin(0.6 * x + 0.3) * np.cos(0.5 * y) * np.sin(0.4 * z + 1.0)
    vol[:, :, :2] = 0.0  # an empty slab: value_empty and the rho floor matter there
    raw = np.zeros((n, 12))
    raw[:, :3] = rng.uniform(1.5, 8.5, (n, 3))
    raw[:, 3:6] = rng.uniform(-0.2, 0.8, (n, 3))
    raw[:3, 3] += 1.3  # beyond 3:1 for the anisotropy term
    raw[:, 6:10] = random_quaternions(rng, n) * rng.uniform(0.5, 2.0, (n, 1))  # unnormalised
    raw[:, 10] = rng.uniform(0.0, 1.0, n)
    raw[:, 11] = rng.uniform(-2.5, 1.5, n)
    points = rng.uniform(-0.5, 9.5, (m, 3))
    partners = points + rng.normal(size=(m, 3)) * 0.6
    return vol.astype(np.float32), raw.astype(np.float32), points.astype(np.float32), partners.astype(np.float32), rng


def _trilinear(vol, p):
    nz, ny, nx = vol.shape
    x, y, z = (np.clip(p[:, a], 0, s - 1) for a, s in zip(range(3), (nx, ny, nz)))
    i0, j0, k0 = (np.minimum(np.floor(c).astype(int), s - 1) for c, s in ((x, nx), (y, ny), (z, nz)))
    i1, j1, k1 = np.minimum(i0 + 1, nx - 1), np.minimum(j0 + 1, ny - 1), np.minimum(k0 + 1, nz - 1)
    tx, ty, tz = x - i0, y - j0, z - k0
    v = vol.astype(np.float64)
    c00 = v[k0, j0, i0] * (1 - tx) + v[k0, j0, i1] * tx
    c01 = v[k0, j1, i0] * (1 - tx) + v[k0, j1, i1] * tx
    c10 = v[k1, j0, i0] * (1 - tx) + v[k1, j0, i1] * tx
    c11 = v[k1, j1, i0] * (1 - tx) + v[k1, j1, i1] * tx
    return (c00 * (1 - ty) + c01 * ty) * (1 - tz) + (c10 * (1 - ty) + c11 * ty) * tz


TERMS = {
    "value": {},
    "value_empty": {"value_empty": 0.5},
    "density": {"density": 0.3},
    "smooth": {"smooth": 0.4},
    "anchor": {"anchor": 0.7},
    "aniso": {"aniso": 2.0},
    "cap": {"cap": 1.5},
    "all": {"value_empty": 0.5, "density": 0.3, "smooth": 0.4, "anchor": 0.7, "aniso": 2.0, "cap": 1.5},
}


@pytest.mark.parametrize("split", [False, True], ids=["point-major", "split-cells"])
@pytest.mark.parametrize("term", sorted(TERMS))
def test_gradients_match_float64_finite_differences(term, device, split):
    vol, raw, points, partners, rng = _scene(seed=len(term))
    lam = {"value_empty": 0.0, "density": 0.0, "smooth": 0.0, "anchor": 0.0, "aniso": 0.0, "cap": 0.0}
    lam.update(TERMS[term])
    # keep samples away from the 5-sigma shell, where the hard cut is not differentiable
    m_pts = loss_ref.mahalanobis(raw.astype(np.float64), points.astype(np.float64))
    m_par = loss_ref.mahalanobis(raw.astype(np.float64), partners.astype(np.float64))
    keep = (np.abs(m_pts - 25).min(1) > 0.5) & (np.abs(m_par - 25).min(1) > 0.5)
    points, partners = points[keep], partners[keep]
    m = points.shape[0]
    assert m > 100
    target = _trilinear(vol, points).astype(np.float32)
    occupied = target > 0.02
    weight = (rng.uniform(size=m) > 0.1).astype(np.float32)
    assert 0 < occupied.sum() < m

    f = normalise(vol, value_range=(0.0, 1.0))
    dv = DeviceVolume(f, device)
    w = LossWeights(
        value_empty=lam["value_empty"],
        density=lam["density"],
        smooth=lam["smooth"],
        smooth_final=lam["smooth"],
        anchor=lam["anchor"],
        aniso=lam["aniso"],
        cap=lam["cap"],
    )
    model = raw.copy()
    model[:, 11] = 1 / (1 + np.exp(-raw[:, 11].astype(np.float64)))
    cfg = RefineConfig(samples=m, weights=w, split_cells=split)
    r = Refiner(dv, model, cfg, seed=0, scale_min=SCALE_MIN, scale_cap=SCALE_CAP)
    r.set_raw(raw)  # keep the unnormalised quaternions and exact logits of the scene
    r.points.assign(np.concatenate([points, partners]))
    r.target.assign(target)
    r.weight.assign(weight)
    r.occupied.assign(occupied.astype(np.float32))
    r.forward_backward()
    grad = r.gradient().astype(np.float64)
    np.testing.assert_array_equal(r.pairs.numpy(), r.back_pairs.numpy())  # same pairs both passes

    lam_ref = dict(lam, log_cap=math.log(SCALE_CAP), log_min=math.log(SCALE_MIN), log_aniso=math.log(3.0))
    args = (
        points.astype(np.float64),
        partners.astype(np.float64),
        target.astype(np.float64),
        weight.astype(np.float64),
        occupied,
        _trilinear(vol, raw[:, :3].astype(np.float64)),
        lam_ref,
    )
    raw64 = raw.astype(np.float64)
    fd = loss_ref.numeric_gradient(raw64, *args, h=1e-6)
    terms = loss_ref.loss_terms(raw64, *args)
    for name in TERMS[term]:  # the term under test is really active
        key = "value" if name == "value_empty" else name
        assert terms[key] > 1e-8, (key, terms)
    # tolerance: float32 kernels against float64 differences, relative to the largest entry
    scale = np.abs(fd).max()
    err = np.abs(grad - fd) / scale
    assert err.max() < 2e-4, (term, err.max(), np.unravel_index(err.argmax(), err.shape))
    # each parameter kind carries gradient in this scene
    for cols in (slice(0, 3), slice(3, 6), slice(6, 10), slice(10, 11), slice(11, 12)):
        assert np.abs(fd[:, cols]).max() > 1e-4 * scale or term in ("aniso", "cap", "anchor")


def test_cached_anchor_targets_are_the_volume_at_the_centres(device, monkeypatch):
    """With the volume in host memory the anchor term's V(mu) is read at every
    update.ANCHOR_REBINS-th re-bin, carried with its primitive through the others and held
    between (update.ANCHOR_CACHE): fresh, the cached targets equal a float64 trilinear reference and the
    anchor loss and gradient are those read from the volume, bit for bit; held while the centres
    move, they stay the values of the centres at the re-bin."""
    from warpgauss.encoding.refine import update

    vol, raw, _, _, _ = _scene(seed=4)
    dv = DeviceVolume(normalise(vol, value_range=(0.0, 1.0)), device)
    model = raw.copy()
    model[:, 11] = 1 / (1 + np.exp(-raw[:, 11].astype(np.float64)))
    cfg = RefineConfig(samples=64, weights=LossWeights(anchor=0.7, aniso=0.0, cap=0.0))
    grads = {}
    for mode in ("never", "always"):
        monkeypatch.setattr(update, "ANCHOR_CACHE", mode)
        r = Refiner(dv, model, cfg, seed=0, scale_min=SCALE_MIN, scale_cap=SCALE_CAP)
        r.set_raw(raw)
        grads[mode] = r.gradient(), r.state.reg_loss.numpy()[:, 0].copy()
        assert r.updater.cached == (mode == "always")
    np.testing.assert_array_equal(grads["always"][0], grads["never"][0])
    np.testing.assert_array_equal(grads["always"][1], grads["never"][1])
    assert grads["always"][1].min() > 0  # the anchor term acts on every slot
    ids = r.state.ids.numpy()
    centres = raw[ids, :3].astype(np.float64)
    np.testing.assert_allclose(r.updater.anchors.numpy(), _trilinear(vol, centres), rtol=1e-6, atol=1e-7)
    moved = raw.copy()
    moved[:, :3] += 0.3
    r.state.raw.assign(moved[ids])  # the centres move without a re-bin: the targets are held
    np.testing.assert_allclose(r.updater.anchors.numpy(), _trilinear(vol, centres), rtol=1e-6, atol=1e-7)
    r.gradient()
    np.testing.assert_array_equal(r.state.reg_loss.numpy()[:, 0], grads["never"][1])  # a unchanged, targets held
    held = np.empty((len(ids), 3))
    held[ids] = centres  # each primitive's centre at the read
    r.rebin()  # carried with their primitives into the new slot order (update.ANCHOR_REBINS)
    assert update.ANCHOR_REBINS > 1
    np.testing.assert_allclose(r.updater.anchors.numpy(), _trilinear(vol, held[r.state.ids.numpy()]), rtol=1e-6, atol=1e-7)
    monkeypatch.setattr(update, "ANCHOR_REBINS", 1)
    r.rebin()  # read at every ANCHOR_REBINS-th re-bin
    ids = r.state.ids.numpy()
    np.testing.assert_allclose(r.updater.anchors.numpy(), _trilinear(vol, moved[ids, :3].astype(np.float64)), rtol=1e-6, atol=1e-7)
    # a resumed run reads them at its slots' centres (restore sets the slots without a re-bin)
    arrays, scalars = r.state_arrays()
    resumed = Refiner(dv, model, cfg, seed=0, scale_min=SCALE_MIN, scale_cap=SCALE_CAP)
    resumed.restore(arrays, scalars)
    centres = resumed.state.raw.numpy().reshape(-1, 12)[:, :3].astype(np.float64)
    np.testing.assert_allclose(resumed.updater.anchors.numpy(), _trilinear(vol, centres), rtol=1e-6, atol=1e-7)


def test_adam_step_equals_numpy_reference(device):
    from warpgauss.core.warp import warp
    from warpgauss.kernels import field as kf
    from warpgauss.kernels import optim as ko

    wp = warp()
    rng = np.random.default_rng(3)
    n = 7
    p = rng.normal(size=(n, 12)).astype(np.float32)
    p[:, 6:10] /= np.linalg.norm(p[:, 6:10], axis=1, keepdims=True)
    lr = np.array([0.1] * 3 + [0.02] * 3 + [0.03] * 4 + [0.05, 0.07], np.float32)
    b1, b2, eps, lo, hi = 0.9, 0.999, 1e-8, -1.0, 1.0
    params = wp.array(p, dtype=kf.vec12, device=device)
    m1 = wp.zeros(n, dtype=kf.vec12, device=device)
    m2 = wp.zeros(n, dtype=kf.vec12, device=device)
    skipped = wp.zeros(1, dtype=int, device=device)
    ref_p, ref_m, ref_v = p.astype(np.float64), np.zeros((n, 12)), np.zeros((n, 12))
    for t in range(1, 4):
        g = rng.normal(size=(n, 12)).astype(np.float32)
        g[2, 5] = np.nan if t == 2 else g[2, 5]  # a non-finite gradient: primitive 2 skips step 2
        if t == 3:
            g[4] = 0.0  # primitive 4 untouched in step 3: sparse Adam leaves it and its moments
        wp.launch(
            ko.adam_step,
            dim=n,
            inputs=[
                params,
                wp.array(g, dtype=kf.vec12, device=device),
                m1,
                m2,
                kf.vec12(*lr),
                1.0,
                b1,
                b2,
                eps,
                1 - b1**t,
                1 - b2**t,
                lo,
                hi,
            ],
            outputs=[skipped],
            device=device,
        )
        ok = np.all(np.isfinite(g), axis=1) & np.any(g != 0, axis=1)
        gm = np.where(ok[:, None], g, 0.0)
        new_m = b1 * ref_m + (1 - b1) * gm
        new_v = b2 * ref_v + (1 - b2) * gm * gm
        new_p = ref_p - lr * (new_m / (1 - b1**t)) / (np.sqrt(new_v / (1 - b2**t)) + eps)
        new_p[:, 6:10] /= np.linalg.norm(new_p[:, 6:10], axis=1, keepdims=True)
        new_p[:, 3:6] = np.clip(new_p[:, 3:6], lo, hi)
        new_p[:, 11] = np.clip(new_p[:, 11], -12, 12)
        ref_p = np.where(ok[:, None], new_p, ref_p)
        ref_m = np.where(ok[:, None], new_m, ref_m)
        ref_v = np.where(ok[:, None], new_v, ref_v)
        np.testing.assert_allclose(params.numpy().reshape(n, 12), ref_p, rtol=2e-5, atol=2e-6)
    assert int(skipped.numpy()[0]) == 1


def test_strata_shares_and_reassignment():
    assert stratum_counts(3072, 10, 10) == (1075, 1229, 768)  # 35 / 40 / 25
    h, mid, u = stratum_counts(1000, 0, 5)  # no high voxels: their share goes to the others
    assert h == 0 and mid + u == 1000 and mid == round(1000 * 0.40 / 0.65)
    assert stratum_counts(1000, 0, 0) == (0, 0, 1000)


def _toy(device, seed=0, iterations=120, split_cells=None):
    from warpgauss.core.profiling import StageRecorder
    from warpgauss.encoding.allocate import AllocationConfig, allocate
    from warpgauss.readers.synthetic import generate

    f = normalise(generate("vortex", 24, seed=1))
    dv = DeviceVolume(f, device)
    cfg = AllocationConfig()
    params, _ = allocate(dv, 300, seed, cfg, StageRecorder())
    rc = RefineConfig(iterations=iterations, samples=1024, split_cells=split_cells)
    return Refiner(dv, params, rc, seed, cfg.scale_min, cfg.resolved_cap(f.shape_xyz)), f, params


def test_loss_decreases_and_psnr_improves_on_a_toy_problem(device):
    from warpgauss.field.evaluate import evaluate_field
    from warpgauss.field.gaussians import GaussianField

    r, f, params = _toy(device)
    hist = r.run(log_every=10)
    total = np.array([h["total"] for h in hist])
    assert total[-3:].mean() < 0.6 * total[:3].mean()
    assert np.mean(np.diff(total) < 0) >= 0.6  # mostly monotone under sample noise
    before = evaluate_field(GaussianField(params, f.shape_xyz, device), f)["psnr_db"]
    after = evaluate_field(GaussianField(r.model_params(), f.shape_xyz, device), f)["psnr_db"]
    assert after > before + 3.0
    out = r.model_params()
    assert out.shape == params.shape and np.all(np.isfinite(out))
    np.testing.assert_allclose(np.linalg.norm(out[:, 6:10], axis=1), 1.0, atol=1e-5)
    assert np.all((out[:, 11] > 0) & (out[:, 11] < 1))


def test_same_seed_gives_a_bit_identical_refined_model(device):
    """Same seed, same device => same model, on CUDA too: the forward sums its partials in a
    fixed order and the pair pass is primitive-major (no float atomics anywhere in a step)."""
    a, _, _ = _toy(device, iterations=30)
    b, _, _ = _toy(device, iterations=30)
    a.run(log_every=30)
    b.run(log_every=30)
    assert a.model_params().tobytes() == b.model_params().tobytes()
    c, _, _ = _toy(device, seed=1, iterations=30)
    c.run(log_every=30)
    assert not np.array_equal(a.model_params(), c.model_params())


@pytest.mark.parametrize("split", [False, True], ids=["point-major", "split-cells"])
def test_self_test_passes_and_compares_both_paths(device, split):
    r, _, _ = _toy(device, iterations=1)
    r.split = split
    res = self_test(r)
    assert res["passed"] and res["pairs_equal"] and res["gradient_max_rel_diff"] < 1e-4


@pytest.mark.parametrize("split", [False, True], ids=["point-major", "split-cells"])
def test_primitive_major_pair_pass_equals_the_atomic_point_scatter(device, split):
    """The balanced chunk pass visits the same pairs as the point-major atomic scatter and sums
    the same gradients (in another order: float32 rounding only)."""
    r, _, _ = _toy(device, iterations=1)
    r.split = not split
    r.sample()
    r.forward_backward()  # buffers made for the other forward pass first: switching must re-make them
    r.split = split
    r.forward_backward()
    mine = [a.numpy().copy() for a in r.pair_grads]
    pairs = r.back_pairs.numpy().copy()
    np.testing.assert_array_equal(pairs, r.pairs.numpy())
    assert pairs.sum() > 10 * r.m  # a real workload: every point touches primitives
    assert_matches_atomic_scatter(r, mine, pairs)


def test_a_primitive_outgrowing_the_levels_triggers_a_replan(cpu):
    """Between re-plans a grown primitive would land in the global level, where one thread of
    the pair pass would visit every point: the re-bin re-plans instead."""
    r, _, _ = _toy(cpu, iterations=1)
    top = r.plan.sizes[-2]
    raw = r.raw.numpy()
    raw[0, 3:6] = np.log(top)  # 5 sigma = 5x the largest planned cell
    r.raw.assign(raw)
    r.rebin(replan=False)
    assert r.binner.global_members() == 0
    assert r.plan.sizes[-2] > top
    r.sample()
    r.forward_backward()
    np.testing.assert_array_equal(r.pairs.numpy(), r.back_pairs.numpy())


def test_split_and_point_major_paths_agree(cpu):
    a, _, _ = _toy(cpu, iterations=1)
    b, _, _ = _toy(cpu, iterations=1)
    b.split = True
    for r in (a, b):
        r.sample()
        r.forward_backward()
    np.testing.assert_allclose(a.value.numpy(), b.value.numpy(), rtol=1e-5, atol=1e-6)
    np.testing.assert_array_equal(a.pairs.numpy(), b.pairs.numpy())
    np.testing.assert_array_equal(a.back_pairs.numpy(), b.back_pairs.numpy())
    ga, gb = a.gradient(), b.gradient()
    np.testing.assert_allclose(ga, gb, rtol=1e-3, atol=1e-4 * np.abs(ga).max())


def _vortex64_gain(iterations: int) -> tuple[float, float]:
    import warpgauss
    from warpgauss.readers.synthetic import generate

    m = warpgauss.encode(generate("vortex", 64), budget=4000, iterations=iterations, device="cpu", seed=0)
    ev = m.report["evaluation"]
    return ev["analytic"]["psnr_db"], ev["final"]["psnr_db"]


def test_refinement_gains_5_db_on_vortex_64_with_4000(cpu):
    before, after = _vortex64_gain(100)  # about 25 s on one core
    assert after >= before + 5.0, (before, after)


@pytest.mark.slow
def test_refinement_gains_on_vortex_64_with_4000_paper_configuration(cpu):
    before, after = _vortex64_gain(1500)  # about 6 minutes on one core
    assert after >= before + 5.0, (before, after)


class _FakeClock:
    """Advances by a fixed step per reading (the refiner reads once per iteration)."""

    def __init__(self, steps):
        self.steps = list(steps)
        self.t = 0.0
        self.readings = []

    def __call__(self):
        self.t += self.steps.pop(0) if len(self.steps) > 1 else self.steps[0]
        self.readings.append(self.t)
        return self.t


def _valid(params):
    assert np.all(np.isfinite(params))
    np.testing.assert_allclose(np.linalg.norm(params[:, 6:10], axis=1), 1.0, atol=1e-5)
    assert np.all((params[:, 11] > 0) & (params[:, 11] < 1))


def test_time_budget_sizes_the_schedule_and_ends_in_time(cpu):
    r, _, _ = _toy(cpu, iterations=1000)
    clock = _FakeClock([0.01])
    r.run(deadline=0.31, clock=clock, log_every=5)
    # probe: readings at 0.02 (before the first step) .. 0.07 (after 5 steps) -> 10 ms per
    # iteration; 0.9 x (0.31 - 0.07) / 0.01 = 21.6 more iterations are planned
    assert r.budget["planned_iterations"] in (5 + 21, 5 + 22)
    assert r.iteration == r.cfg.iterations == r.budget["planned_iterations"]
    assert not r.budget["stopped_early"]
    assert clock.readings[-1] <= 0.31
    _valid(r.model_params())


def test_time_budget_stops_early_when_steps_slow_down(cpu):
    r, _, _ = _toy(cpu, iterations=1000)
    clock = _FakeClock([0.01] * 7 + [0.05])  # iterations become 5x slower after the probe
    r.run(deadline=0.31, clock=clock, log_every=5)
    assert r.budget["stopped_early"] and r.iteration < r.budget["planned_iterations"]
    assert clock.readings[-1] <= 0.31  # no step was started that would end past the deadline
    _valid(r.model_params())


def test_learning_rate_scales_with_contact_density(cpu):
    from warpgauss.core.profiling import StageRecorder
    from warpgauss.encoding.allocate import AllocationConfig, allocate
    from warpgauss.readers.synthetic import generate

    f = normalise(generate("vortex", 24, seed=1))
    dv = DeviceVolume(f, cpu)
    cfg = AllocationConfig()
    params, _ = allocate(dv, 300, 0, cfg, StageRecorder())
    scales = {}
    for samples in (4, 1024):
        r = Refiner(dv, params, RefineConfig(iterations=5, samples=samples), 0, cfg.scale_min, cfg.resolved_cap(f.shape_xyz))
        r.step()
        expected = r.pairs.numpy()[:samples].sum() / 300
        assert r.contacts == pytest.approx(expected)
        assert r.touch_scale == pytest.approx(min(1.0, math.sqrt(expected / 12.0)))
        scales[samples] = r.touch_scale
    assert scales[4] < 0.5 and scales[1024] == 1.0


def test_bins_stay_exact_between_rebins_and_far_moves_are_deferred(cpu):
    """Slots are re-sorted only every rebin_every iterations; evaluation must stay exact meanwhile."""
    from warpgauss.field.gaussians import GaussianField

    r, f, _ = _toy(cpu, iterations=60)
    r.cfg = RefineConfig(iterations=60, samples=1024, lr=0.08, rebin_every=10_000, replan_every=10_000)
    r.write_schedule()
    for _ in range(60):
        r.step()
    assert r.rebins == 1  # only the initial binning
    assert r.deferred_steps() > 0  # a high rate pushes some primitives out of their cell's reach
    r.sample()
    r.forward_backward()
    k = r.n_points  # the points the pass evaluates (the samples; their partners with a smoothness term)
    pts = r.points.numpy()[:k]
    vd, dd, cd = GaussianField(r.model_params(), f.shape_xyz, cpu).evaluate_dense(pts)
    np.testing.assert_array_equal(r.pairs.numpy()[:k], cd)
    np.testing.assert_allclose(r.value.numpy()[:k], vd, atol=2e-5)
    np.testing.assert_allclose(r.density.numpy()[:k], dd, rtol=2e-5, atol=1e-6)
    moved = r.model_params()
    r.rebin()
    np.testing.assert_array_equal(r.model_params(), moved)  # re-sorting changes no primitive


def test_stratum_index_enumerates_each_stratum_exactly_once(device):
    """The brick index maps rank r to the r-th stratum voxel: every voxel once, none outside."""
    import warp as wp

    from warpgauss.kernels import sampling as ks

    rng = np.random.default_rng(5)
    vol = rng.uniform(0, 1, (9, 7, 11)).astype(np.float32)  # not a multiple of the brick edge
    vol[rng.uniform(size=vol.shape) < 0.3] = 0.0  # empty voxels belong to no stratum
    mask = rng.uniform(size=vol.shape) > 0.1
    f = normalise(np.where(mask, vol, np.nan), value_range=(0.0, 1.0))
    r = Refiner(DeviceVolume(f, device), _toy_params(f), RefineConfig(iterations=1, samples=16), 0, 0.3, 4.0)

    @wp.kernel
    def enumerate_stratum(
        bits: wp.array(dtype=wp.uint64),
        cum: wp.array(dtype=wp.int64),
        ny: int,
        nx: int,
        out: wp.array(dtype=int),
    ):
        t = wp.tid()
        v = ks.stratum_voxel(bits, cum, ny, nx, wp.int64(t))
        out[t] = (v[0] * ny + v[1]) * nx + v[2]

    v = f.values
    usable = f.mask if f.mask is not None else np.ones(v.shape, bool)
    smp = r.sampler
    for stratum, cum, bits, count in ((0, r.high, smp.high_bits, r.n_high), (1, r.mid, smp.mid_bits, r.n_mid)):
        want = usable & ((v > 0.4) if stratum == 0 else ((v > 0.02) & (v <= 0.4)))
        assert count == int(want.sum()) > 0
        out = wp.zeros(count, dtype=int, device=device)
        wp.launch(enumerate_stratum, dim=count, inputs=[bits, cum, v.shape[1], v.shape[2], out], device=device)
        got = np.sort(out.numpy())
        np.testing.assert_array_equal(got, np.flatnonzero(want.ravel()))


@pytest.mark.parametrize("value_empty", [0.0, 1.0])
def test_uniform_samples_avoid_empty_space_only_when_it_carries_no_loss(cpu, value_empty):
    """With no value loss on empty samples the uniform stratum is drawn among occupied voxels;
    with one it still covers the whole grid (empty space then has a loss to fit)."""
    from warpgauss.readers.synthetic import generate

    f = normalise(generate("interface", 24, seed=1))
    occupied = f.values > 0.02
    assert 0.05 < occupied.mean() < 0.8
    w = LossWeights(value_empty=value_empty)
    cfg = RefineConfig(iterations=1, samples=4000, weights=w, uniform_support=False, error_share=0.0)  # support: the next test
    r = Refiner(DeviceVolume(f, cpu), _toy_params(f), cfg, 0, 0.3, 4.0)
    assert r.uniform_occupied == (value_empty == 0.0)
    r.sample()
    m_high, m_mid, m_uni = r.strata
    assert m_uni > 500
    pts = r.points.numpy()[m_high + m_mid : r.m]
    ijk = np.clip(np.rint(pts).astype(int), 0, np.array(f.shape_xyz) - 1)
    on = occupied[ijk[:, 2], ijk[:, 1], ijk[:, 0]]
    if value_empty == 0.0:
        assert on.all()
    else:
        assert 0.5 * (1 - occupied.mean()) < 1 - on.mean() < 1.5 * (1 - occupied.mean())


def test_uniform_samples_cover_the_model_support_and_nothing_else(device):
    """With a value loss on empty samples the uniform stratum is drawn over the 4^3 bricks the
    primitives' 5-sigma boxes (+2 voxels) reach: right after a re-bin every point any primitive
    contributes to is inside, 9 steps later (the last before the next re-bin) all but a sliver,
    and every uniform sample is inside."""
    from warpgauss.core.profiling import StageRecorder
    from warpgauss.encoding.allocate import AllocationConfig, allocate
    from warpgauss.field.gaussians import GaussianField
    from warpgauss.readers.synthetic import generate

    f = normalise(generate("bubbles", 40, seed=3))
    dv = DeviceVolume(f, device)
    params, _ = allocate(dv, 800, 0, AllocationConfig(), StageRecorder())
    r = Refiner(dv, params, RefineConfig(iterations=20, samples=4000, rebin_every=10, error_share=0.0), 0, 0.3, 4.0)
    assert r.uniform_support and not r.uniform_occupied
    nz, ny, nx = f.values.shape
    rng = np.random.default_rng(0)
    for steps in (0, 9):  # right after the re-bin, and 9 steps later (the last before the next one)
        for _ in range(steps):
            r.step()
        marks, everything, _ = r.sampler.marks
        assert int(everything.numpy()[0]) == 0
        sup = np.repeat(np.repeat(np.repeat(marks.numpy() != 0, 4, 0), 4, 1), 4, 2)[:nz, :ny, :nx]
        assert int(r.sampler.support.numpy()[-1]) == int(sup.sum()) and r.support_share() == pytest.approx(sup.mean())
        assert 0.0 < sup.mean() < 0.75  # a sparse field: a good part of the grid is skipped
        # points jittered within +-0.5 of every voxel centre, where the model reaches
        z, y, x = np.nonzero(np.ones((nz, ny, nx), bool))
        vox = np.stack([x, y, z], 1)
        pts = (vox + rng.uniform(-0.5, 0.5, vox.shape)).astype(np.float32)
        _, _, pairs = GaussianField(r.model_params(), f.shape_xyz, device=device).evaluate_full(pts)
        reached = pairs > 0
        inside = sup[z[reached], y[reached], x[reached]]
        assert reached.any() and (inside.all() if steps == 0 else inside.mean() > 0.999)
        r.sample()
        m_high, m_mid, m_uni = r.strata
        uni = r.points.numpy()[m_high + m_mid : r.m]
        ijk = np.clip(np.rint(uni).astype(int), 0, np.array(f.shape_xyz) - 1)
        assert m_uni > 500 and sup[ijk[:, 2], ijk[:, 1], ijk[:, 0]].all()
        # and the draw covers the support: about uniformly over its bricks
        assert len({tuple(b) for b in ijk // 4}) > 0.5 * min(m_uni, (marks.numpy() != 0).sum())


def test_without_smoothness_the_partners_are_not_evaluated(device):
    """Partners serve only the smoothness term: with its weight 0 an iteration evaluates the
    samples alone, and the gradient equals evaluating the partners too (to float32 rounding: the
    partners, which carry no gradient, still change how the pair pass splits its chunks)."""
    from warpgauss.core.profiling import StageRecorder
    from warpgauss.encoding.allocate import AllocationConfig, allocate
    from warpgauss.readers.synthetic import generate

    f = normalise(generate("vortex", 24, seed=1))
    dv = DeviceVolume(f, device)
    params, _ = allocate(dv, 300, 0, AllocationConfig(), StageRecorder())
    cfg = RefineConfig(iterations=1, samples=1024, weights=LossWeights(smooth=0.0, smooth_final=0.0))
    grads = []
    for partners in (False, True):
        r = Refiner(dv, params, cfg, 0, 0.3, 4.0)
        assert not r.partners and r.n_points == r.m
        r.partners = partners
        r.sample()
        r.forward_backward()
        if not partners:
            assert r.pairs.numpy()[: r.m].sum() > 0 and not r.pairs.numpy()[r.m :].any()
        grads.append(r.gradient())
    np.testing.assert_allclose(grads[0], grads[1], rtol=0, atol=1e-5 * np.abs(grads[1]).max())


def _toy_params(f, n=20):
    rng = np.random.default_rng(0)
    p = np.zeros((n, 12), np.float32)
    p[:, :3] = rng.uniform(0, 1, (n, 3)) * (np.array(f.shape_xyz) - 1)
    p[:, 3:6] = 0.3
    p[:, 9] = 1.0
    p[:, 10] = 0.5
    p[:, 11] = 0.5
    return p


def test_time_budget_spends_spare_time_on_samples(cpu):
    """Cost = 1 ms + 10 us per sample: the budget keeps >= 30 iterations and raises the samples."""
    from warpgauss.core.profiling import StageRecorder
    from warpgauss.encoding.allocate import AllocationConfig, allocate
    from warpgauss.readers.synthetic import generate

    f = normalise(generate("vortex", 24, seed=1))
    dv = DeviceVolume(f, cpu)
    cfg = AllocationConfig()
    params, _ = allocate(dv, 300, 0, cfg, StageRecorder())
    rc = RefineConfig(iterations=100_000, samples=64, budget_min_iterations=30)
    r = Refiner(dv, params, rc, 0, cfg.scale_min, cfg.resolved_cap(f.shape_xyz))
    t = [0.0]

    def clock():  # one reading per iteration, advancing by the cost of the current sample count
        t[0] += 0.001 + 1e-5 * r.m
        return t[0]

    r.run(deadline=0.5, clock=clock, log_every=1000)
    b = r.budget
    assert b["cost_model_ms"]["fixed"] == pytest.approx(1.0, rel=1e-6)
    assert b["cost_model_ms"]["per_1000_samples"] == pytest.approx(10.0, rel=1e-6)
    # 16 x 64 samples leave >= 30 iterations, 32 x 64 would not
    assert r.m == b["samples"] == 1024
    assert 30 <= b["planned_iterations"] == r.iteration == r.cfg.iterations < 60
    assert t[0] <= 0.5 and not b["stopped_early"]
    _valid(r.model_params())
    # with the choice off, the samples stay and the iterations grow instead
    rc2 = RefineConfig(iterations=100_000, samples=64, budget_min_iterations=30, budget_samples=False)
    r = Refiner(dv, params, rc2, 0, cfg.scale_min, cfg.resolved_cap(f.shape_xyz))
    t[0] = 0.0
    r.run(deadline=0.5, clock=clock, log_every=1000)
    assert r.m == 64 and r.iteration > 200


def test_support_marks_count_the_boxes_reaching_each_brick(device):
    """mark_support's corner counts plus the three prefix sums give every 4^3 brick the number of
    widened 5-sigma boxes reaching it (numpy brute force), for boxes inside, across the edge of,
    outside and far larger than the grid."""
    from warpgauss.core.warp import warp
    from warpgauss.kernels import support as ksup

    wp = warp()
    rng = np.random.default_rng(11)
    nb = (5, 7, 6)  # bricks along z, y, x
    n = 40
    mu = rng.uniform(-8.0, 34.0, (n, 3)).astype(np.float32)
    ext = rng.uniform(0.2, 9.0, (n, 3)).astype(np.float32)
    ext[0] = 1.0e6  # covers everything
    mu[1] = [-30.0, 10.0, 10.0]  # wholly left of the grid: clamps to the first bricks along x
    marks = wp.zeros(nb, dtype=int, device=device)
    everything = wp.zeros(1, dtype=int, device=device)
    wp.launch(
        ksup.mark_support,
        dim=n,
        inputs=[wp.array(mu, dtype=wp.vec3, device=device), wp.array(ext, dtype=wp.vec3, device=device)],
        outputs=[marks, everything],
        device=device,
    )
    for axis, lines in ((0, (nb[1], nb[2])), (2, (nb[0], nb[1])), (1, (nb[0], nb[2]))):  # any order
        wp.launch(ksup.prefix_sum_axis, dim=lines, inputs=[marks, axis], device=device)
    expect = np.zeros(nb, np.int64)
    size = np.array(nb[::-1])  # x, y, z
    for c, e in zip(mu.astype(np.float64), ext.astype(np.float64)):
        h = e + float(ksup.SUPPORT_MARGIN)
        lo = np.clip(np.floor(np.ceil(c - h - 0.5) / 4), 0, size - 1).astype(int)
        hi = np.clip(np.floor(np.floor(c + h + 0.5) / 4), 0, size - 1).astype(int)
        expect[lo[2] : hi[2] + 1, lo[1] : hi[1] + 1, lo[0] : hi[0] + 1] += 1
    assert int(everything.numpy()[0]) == 0
    np.testing.assert_array_equal(marks.numpy(), expect)
    assert expect.min() >= 1 and expect.max() > 2  # the huge box everywhere, overlaps elsewhere


def test_the_forward_pass_is_chosen_by_the_points_an_iteration(cpu):
    """split_cells None: split on CUDA up to SPLIT_MAX_POINTS points (measured faster there),
    point-major above and on the CPU; True or False is kept whatever the sample count."""
    from warpgauss.encoding.refine.passes import SPLIT_DENSE_POINTS, SPLIT_DENSE_PRIMITIVES, SPLIT_MAX_POINTS, picks_split

    assert picks_split(True, SPLIT_MAX_POINTS) and not picks_split(True, SPLIT_MAX_POINTS + 1)
    assert picks_split(True, SPLIT_MAX_POINTS + 1, SPLIT_DENSE_PRIMITIVES)  # a dense model keeps it longer
    assert not picks_split(True, SPLIT_DENSE_POINTS, SPLIT_DENSE_PRIMITIVES)
    assert not picks_split(False, 16, SPLIT_DENSE_PRIMITIVES)
    assert not picks_split(True, SPLIT_MAX_POINTS + 1, SPLIT_DENSE_PRIMITIVES, dense_rule=False)  # beside other bricks
    assert picks_split(True, SPLIT_MAX_POINTS, SPLIT_DENSE_PRIMITIVES, dense_rule=False)
    auto, _, _ = _toy(cpu, iterations=1)
    assert auto.cfg.split_cells is None and not auto.split
    forced, _, _ = _toy(cpu, iterations=1, split_cells=True)
    forced.set_samples(SPLIT_MAX_POINTS + 1)  # above the automatic limit
    assert forced.split and forced.n_points > SPLIT_MAX_POINTS
    assert auto.forward_pass == "point-major: the CPU"
    assert forced.forward_pass == "split: split_cells=True"


def test_a_time_budget_is_the_whole_encodes(cpu, monkeypatch):
    """--time-budget counts from the call, not from refinement: the refinement's deadline leaves
    what the stages before it spent and a reserve for the fit, evaluation and writing, and the
    fit to the bytes keeps its first result (no scored choice) on a budget."""
    import time

    import warpgauss
    from warpgauss.encoding.driver import run
    from warpgauss.readers.synthetic import generate

    seen = {}
    real = run.EncodeRun.budget_deadline

    def spy(self, now, compile_s, eval_s=0.0):
        seen["now"], seen["deadline"] = now, real(self, now, compile_s, eval_s)
        return seen["deadline"]

    monkeypatch.setattr(run.EncodeRun, "budget_deadline", spy)
    t0 = time.perf_counter()
    m = warpgauss.encode(generate("vortex", 32, seed=0), ratio=4, time_budget=6.0, device="cpu", samples=256, self_test=False)
    note = m.report["refinement"]["time_budget"]["call"]
    assert note["seconds"] == 6.0
    assert 0.0 < note["spent_before_refinement_s"] < seen["now"] - t0 + 1e-6  # the stages before refinement count
    assert note["reserved_after_s"] >= run.TAIL_SHARE * 6.0
    # the reserve holds the final model's evaluation, measured on the analytic model before refinement
    assert note["reserved_evaluation_s"] > 0 and any(s["stage"] == "EVa" for s in m.report["stages"])
    assert note["reserved_after_s"] == pytest.approx(run.TAIL_SHARE * 6.0 + note["reserved_coding_s"] + note["reserved_evaluation_s"])
    assert note["reserved_coding_s"] >= run.TAIL_CODINGS * m.report["budget"]["coded_sizing"]["coding_seconds"] > 0
    assert m.report["evaluation"]["analytic"]["psnr_db"] > 0  # measured once, before refinement
    budget_end = seen["now"] - note["spent_before_refinement_s"] + 6.0
    assert seen["deadline"] == pytest.approx(budget_end - note["reserved_after_s"], abs=1e-6)
    assert m.report["refinement"]["time_budget"]["seconds"] <= 6.0 - note["spent_before_refinement_s"] - note["reserved_after_s"] + 1e-3
    assert any(s["what"] == "coded fit choice" for s in m.report["skipped"])
