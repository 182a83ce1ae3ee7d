"""Training for the grid we score (issue #32): samples at voxel centres with the voxel values as
targets, importance weights whose weighted value loss estimates the full-grid MSE, the paper's
sampling kept by its presets, decodes clamped to the source's range, the rate control's knobs."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from test_refine import _toy_params

from warpgauss.encoding.driver import resolve_refine
from warpgauss.encoding.refine import PRESETS, RefineConfig, Refiner
from warpgauss.errors import WarpgaussError
from warpgauss.field.analysis import DeviceVolume, normalise


def _field():
    from warpgauss.readers.synthetic import generate

    f = normalise(generate("interface", 20, seed=1))
    occupied = f.values > 0.02
    assert 0.05 < occupied.mean() < 0.8  # strata of very different sizes: the weights matter
    return f


def test_samples_at_voxel_centres_take_the_voxel_values(cpu):
    """At jitter 0 every sample sits on a voxel centre and its target is that voxel's value,
    exactly (no trilinear blur); at the paper's 0.5 the samples leave the centres."""
    f = _field()
    r = Refiner(DeviceVolume(f, cpu), _toy_params(f), RefineConfig(iterations=1, samples=3000, jitter=0.0), 0, 0.3, 4.0)
    r.sample()
    pts = r.points.numpy()[: r.m].astype(np.float64)
    np.testing.assert_array_equal(pts, np.rint(pts))
    ijk = pts.astype(int)
    np.testing.assert_array_equal(r.target.numpy(), f.values[ijk[:, 2], ijk[:, 1], ijk[:, 0]])
    r = Refiner(DeviceVolume(f, cpu), _toy_params(f), RefineConfig(iterations=1, samples=3000, jitter=0.5), 0, 0.3, 4.0)
    r.sample()
    off = np.abs(r.points.numpy()[: r.m] - np.rint(r.points.numpy()[: r.m]))
    assert off.max() <= 0.5 and off.mean() > 0.1


def test_a_loss_record_is_summed_on_the_device_as_numpy_sums_it(cpu):
    """Refiner.losses takes its sums on the device (kernels.analysis.loss_partials, float64
    slices of 64 added in order on the host): the same terms and PSNRs as float64 numpy sums of
    the arrays it read back before (a sample count that is not a multiple of the slice, a
    primitive count either), with one read; a rerun gives the same record bit for bit."""
    f = _field()
    r = Refiner(DeviceVolume(f, cpu), _toy_params(f, 301), RefineConfig(iterations=3, samples=1001, importance=True), 0, 0.3, 4.0)
    r.run()
    r.sample()
    r.forward()
    got = r.losses()
    m = r.m
    pl = r.point_loss.numpy().astype(np.float64).sum(0)
    rl = r.state.reg_loss.numpy().astype(np.float64).sum(0)
    v = r.value.numpy()[:m].astype(np.float64)
    t = r.target.numpy().astype(np.float64)
    om = r.weight.numpy().astype(np.float64)
    assert m == 1001 and r.n == 301 and rl.sum() > 0 and pl[0] > 0
    want = dict(zip(("value", "density", "smooth", "anchor", "aniso", "cap"), (*pl, *rl)))
    for k, x in want.items():
        assert got[k] == pytest.approx(x, rel=1e-12, abs=1e-18), k
    mse = np.sum(om * (v - t) ** 2) / np.sum(om)
    assert got["sample_psnr_db"] == pytest.approx(10 * np.log10(1 / mse), abs=1e-9)
    assert got["grid_psnr_db"] == pytest.approx(10 * np.log10(1 / r.grid_mse_estimate(v, t, om)), abs=1e-9)
    assert r.losses() == got


@pytest.mark.parametrize("uniform_support", [False, True])
def test_importance_weights_make_the_value_loss_the_full_grid_mse(cpu, uniform_support):
    """The weighted mean of any per-voxel quantity over the samples estimates its mean over the
    whole grid (float64 numpy reference), where the unweighted strata mix does not: here the
    squared error of a model that predicts 0 everywhere (the value loss of an empty model)."""
    f = _field()
    truth = float(np.mean(f.values.astype(np.float64) ** 2))  # full-grid MSE of the all-zero model
    cfg = RefineConfig(iterations=1, samples=60_000, jitter=0.0, importance=True, uniform_support=uniform_support, error_share=0.0)
    r = Refiner(DeviceVolume(f, cpu), _toy_params(f, 400), cfg, 0, 0.3, 4.0)
    r.sample()
    w = r.weight.numpy().astype(np.float64)
    t2 = r.target.numpy().astype(np.float64) ** 2
    assert 0.5 < w.mean() < 2.0  # about 1, so the learning rates keep their meaning
    weighted = float(np.sum(w * t2) / np.sum(w))
    plain = float(np.mean(t2))
    assert abs(weighted - truth) < 0.05 * truth, (weighted, truth)
    assert abs(plain - truth) > 0.1 * truth  # the strata alone over-weight the high values
    cfg = dataclasses.replace(cfg, importance=False)
    r = Refiner(DeviceVolume(f, cpu), _toy_params(f, 400), cfg, 0, 0.3, 4.0)
    r.sample()
    np.testing.assert_array_equal(r.weight.numpy(), 1.0)  # the paper's equal weights (nothing masked)


def test_the_samples_estimate_the_decoded_models_full_grid_mse(cpu):
    """Where the support leaves empty space (bubbles: a few per cent occupied), the weighted
    squared errors over the samples times D, plus V^2 over the voxels no sample can reach (where
    the decode writes 0), over the grid, estimate the full-grid MSE of the decoded, clamped model
    (float64 numpy reference from the decode); sample_psnr_db alone is the MSE over the reach."""
    from warpgauss.core.profiling import StageRecorder
    from warpgauss.encoding.allocate import AllocationConfig, allocate
    from warpgauss.field.gaussians import GaussianField
    from warpgauss.readers.synthetic import generate

    vol = generate("bubbles", 40, seed=2).astype(np.float32)
    vol += np.float32(0.01 * (vol.max() - vol.min())) * np.random.default_rng(0).random(
        vol.shape, dtype=np.float32
    )  # a floor of small values
    f = normalise(vol)
    dv = DeviceVolume(f, cpu)
    params, _ = allocate(dv, 300, 0, AllocationConfig(), StageRecorder())
    r = Refiner(dv, params, RefineConfig(iterations=1, samples=80_000), 0, 0.3, 6.0)
    r.sample()
    r.forward()
    unreached = r.sampler.unreached_error()
    assert unreached is not None and unreached > 0 and r.sampler.reach() < f.values.size  # empty space beyond the support
    estimate = r.grid_mse_estimate(
        r.value.numpy()[: r.m].astype(np.float64), r.target.numpy().astype(np.float64), r.weight.numpy().astype(np.float64)
    )
    gf = GaussianField(r.model_params(), f.values.shape[::-1], cpu)
    model = gf.evaluate(np.argwhere(np.ones_like(f.values, bool))[:, ::-1].astype(np.float32)).astype(np.float64)
    exact = float(np.mean((np.clip(model, 0.0, 1.0) - f.values.reshape(-1).astype(np.float64)) ** 2))
    assert estimate == pytest.approx(exact, rel=0.1), (estimate, exact)
    counts = r.sampler.support_marks[2].numpy()
    near = np.repeat(np.repeat(np.repeat(counts > 0, 4, 0), 4, 1), 4, 2)[: f.values.shape[0], : f.values.shape[1], : f.values.shape[2]]
    far = ~near & (f.values <= 0.02)
    assert unreached == pytest.approx(float(np.sum(f.values[far].astype(np.float64) ** 2)), rel=1e-5, abs=1e-12)
    losses = r.losses()
    assert losses["grid_psnr_db"] == pytest.approx(10 * np.log10(1 / estimate), abs=1e-6)


def test_the_end_estimate_averages_draws_without_changing_the_model(cpu):
    """Refiner.end_estimate scores the current model on several draws (forward passes only): its
    grid estimate is close to the decoded model's full-grid PSNR (float64 reference from the
    decode), and the parameters, the iteration and the steps after it are what they would have
    been without it (bit for bit); the driver reports it."""
    import warpgauss
    from warpgauss.core.profiling import StageRecorder
    from warpgauss.encoding.allocate import AllocationConfig, allocate
    from warpgauss.field.gaussians import GaussianField
    from warpgauss.readers.synthetic import generate

    f = normalise(generate("bubbles", 32, seed=3).astype(np.float32))
    dv = DeviceVolume(f, cpu)
    params, _ = allocate(dv, 200, 0, AllocationConfig(), StageRecorder())
    r, twin = (Refiner(dv, params, RefineConfig(iterations=40, samples=2048), 0, 0.3, 6.0) for _ in range(2))
    assert r.end_estimate() == {}  # nothing trained yet
    for _ in range(20):
        r.step()
        twin.step()
    before = r.model_params().copy()
    end = r.end_estimate(draws=16)
    assert (end["draws"], end["samples"]) == (16, 16 * r.m)
    assert r.iteration == 20 and np.array_equal(r.model_params(), before)
    gf = GaussianField(before, f.values.shape[::-1], cpu)
    model = gf.evaluate(np.argwhere(np.ones_like(f.values, bool))[:, ::-1].astype(np.float32)).astype(np.float64)
    exact = 10 * np.log10(1 / float(np.mean((np.clip(model, 0.0, 1.0) - f.values.reshape(-1).astype(np.float64)) ** 2)))
    assert end["grid_psnr_db"] == pytest.approx(exact, abs=0.5), (end, exact)
    for _ in range(20):
        r.step()
        twin.step()
    assert np.array_equal(r.model_params(), twin.model_params())  # the draws left no trace
    rep = warpgauss.encode(f.values, budget=60, iterations=20, samples=512, device=cpu, evaluate=False).report
    assert rep["refinement"]["end_estimate"]["draws"] > 1 and np.isfinite(rep["refinement"]["end_estimate"]["grid_psnr_db"])


def test_presets_keep_the_papers_sampling():
    """--preset paper trains as the paper does: jittered samples, trilinear targets, equal weights;
    the library default, and --preset fast (its 300-iteration form), sample voxel centres with
    importance weights and half the samples where the error is."""
    cfg = resolve_refine(None, "paper", None, None)
    assert (cfg.jitter, cfg.importance, cfg.error_share, cfg.auto_samples) == (0.5, False, 0.0, False)
    assert {k: getattr(cfg, k) for k in PRESETS["paper"] if k != "weights"} == {k: v for k, v in PRESETS["paper"].items() if k != "weights"}
    assert (cfg.weights.smooth, cfg.weights.smooth_final) == (0.01, 0.0001)  # the paper's smoothness term, annealed
    assert RefineConfig().weights.smooth == 0.0  # the default has none: no partner points
    mine = resolve_refine(RefineConfig(weights=dataclasses.replace(RefineConfig().weights, density=0.5)), "paper", None, None)
    assert mine.weights.density == 0.5 and mine.weights.smooth == 0.01  # the preset sets only the smoothness
    fast, default = resolve_refine(None, "fast", None, None), RefineConfig()
    assert fast.iterations == 300 and default.iterations == 1500
    assert fast == dataclasses.replace(default, iterations=300, lr_decay=0.3)  # a short run decays its rate less
    assert (default.jitter, default.importance) == (0.0, True)
    with pytest.raises(Exception, match="jitter must be in"):
        RefineConfig(jitter=2.0).validate()


def test_decoded_values_stay_within_the_source_range(cpu):
    """A Gaussian that overshoots (a value far above the field's maximum) and one below its
    minimum: the decode, the full-grid evaluation and the sampled one all clamp to [min, max] and
    count the voxels clamped."""
    import warpgauss
    from warpgauss.field.evaluate import evaluate_field

    vol = np.zeros((12, 12, 12), np.float32)
    vol[4:8, 4:8, 4:8] = 250.0
    vol[0, 0, 0] = -10.0
    model = warpgauss.encode(vol, budget=20, iterations=0, device=cpu, evaluate=False)
    p = model.params.copy()
    p[0, :3] = (6.0, 6.0, 6.0)
    p[0, 3:6] = np.log(1.5)
    p[0, 10] = 3.0  # normalised value 3: three times the maximum
    p[1, :3] = (2.0, 9.0, 9.0)
    p[1, 3:6] = np.log(1.5)
    p[1, 10] = -2.0
    m = warpgauss.Model(p, model.header)
    info: dict = {}
    dec = m.decode(device=cpu, info=info)
    assert dec.min() >= -10.0 and dec.max() <= 250.0
    assert info["clamped_voxels"] > 0 and (dec == 250.0).any() and (dec == -10.0).any()
    f = normalise(vol)
    full = evaluate_field(m.field(cpu), f, full=True)
    assert full["clamped_voxels"] > 0
    raw = m.field(cpu).evaluate(np.argwhere(np.ones_like(vol, bool))[:, ::-1].astype(np.float32))
    ref = np.clip(raw, 0.0, 1.0).astype(np.float64) - f.values.reshape(-1).astype(np.float64)
    assert full["mse"] == pytest.approx(float(np.mean(ref**2)), rel=1e-5)


def test_fit_bytes_prunes_within_its_share_and_reports_the_rows_kept():
    """Up to ``prune_share`` excess the least important primitives go and no depth changes; the
    rows kept are reported in order; beyond it bits are dropped first."""
    from test_wgs import realistic_params

    from warpgauss.format import coded, ratefit

    p = realistic_params(np.random.default_rng(9), 3000)
    full = len(coded.encode_coded(p)[0])
    small, bits, info = ratefit.fit_bytes(p, int(full * 0.8), prune_share=0.5)
    assert info["steps"] == [] and bits == coded.CODED_BITS and info["pruned"] > 0
    kept = info["kept"]
    assert len(kept) == 3000 - info["pruned"] and np.all(np.diff(kept) > 0)
    dropped = np.setdiff1d(np.arange(3000), kept)
    imp = ratefit.importance(p)
    assert imp[dropped].max() <= imp[kept].min()  # the least important went
    # importance is the primitive's share of the blend (weight x sigma volume), not its value
    assert np.allclose(imp, np.abs(p[:, 11]) * np.exp(p[:, 3:6].astype(np.float64).sum(1)), rtol=1e-6)
    _, bits, info = ratefit.fit_bytes(p, int(full * 0.8), prune_share=0.03)
    assert any(s.endswith("-1") for s in info["steps"])


def test_fit_bytes_with_a_score_keeps_the_fit_that_scores_best(monkeypatch):
    """Where the first fit drops bits, a scored fit also tries the larger prune shares and keeps
    the best-scoring one, every candidate within the budget and reported."""
    from test_wgs import realistic_params

    from warpgauss.format import coded, ratefit

    p = realistic_params(np.random.default_rng(9), 3000)
    budget = int(
        len(coded.encode_coded(p)[0]) * 0.7
    )  # where the first fit prunes no more than bits alone (at 0.8 with layout 2 it prunes 77, bits alone none)
    plain = ratefit.fit_bytes(p, budget)
    assert any(s.endswith("-1") for s in plain[2]["steps"]) and "choice" not in plain[2]

    def rows(stored, bits):  # prefers the fewest pruned: the first fit (bits dropped)
        return float(len(stored))

    def depth(stored, bits):  # prefers the most bits kept: pruning alone
        return float(sum(bits.values()))

    kept_rows = ratefit.fit_bytes(p, budget, score=rows)
    kept_bits = ratefit.fit_bytes(p, budget, score=depth)
    # the first fit on a thread beside the alternatives (CHOICE_CONCURRENT) or before them: the same fits
    for score in (rows, depth):
        monkeypatch.setattr(ratefit, "CHOICE_CONCURRENT", False)
        serial = ratefit.fit_bytes(p, budget, score=score)
        monkeypatch.setattr(ratefit, "CHOICE_CONCURRENT", True)
        together = ratefit.fit_bytes(p, budget, score=score)
        np.testing.assert_array_equal(serial[0], together[0])
        np.testing.assert_array_equal(serial[2].pop("kept"), together[2].pop("kept"))
        assert serial[1:] == together[1:]
    for _, _, info in (kept_rows, kept_bits):
        assert info["bytes"] <= budget and len(info["choice"]) >= 2
        assert [c["prune_share"] for c in info["choice"]] == list(ratefit.CHOICE_SHARES[: len(info["choice"])])
    assert kept_rows[2]["chosen"] == 0 and kept_rows[2]["pruned"] == plain[2]["pruned"]
    np.testing.assert_array_equal(kept_rows[0], plain[0])
    last = kept_bits[2]["choice"][kept_bits[2]["chosen"]]
    assert kept_bits[2]["chosen"] > 0 and last["pruned"] > plain[2]["pruned"]
    assert sum(kept_bits[1].values()) > sum(plain[1].values())
    # where the first fit drops bits and prunes the rest of the excess, bits alone (share 0) are
    # tried too: a score that counts the rows kept picks that fit, nothing pruned, within the budget
    full = len(coded.encode_coded(p)[0])
    for scale in np.linspace(0.70, 0.97, 28):
        first = ratefit.fit_bytes(p, int(full * scale))[2]
        if first["pruned"] > 0 and any(s.endswith("-1") for s in first["steps"]):
            break
    else:
        raise AssertionError("no budget where the first fit both drops bits and prunes")
    _, _, info = ratefit.fit_bytes(p, int(full * scale), score=rows)
    assert info["choice"][1]["prune_share"] == 0.0 and info["chosen"] == 1
    assert info["pruned"] == 0 and info["bytes"] <= int(full * scale)


def test_silenced_primitives_stay_out_and_come_last(cpu):
    """Refiner.silence: the primitives taken out get weight exactly 0 and are never stepped again
    (their weight stays 0 over later steps and re-bins); the rest keep their parameters and order
    as the first ``n_live`` rows of the model; a checkpoint carries the count."""
    from warpgauss.core.profiling import StageRecorder
    from warpgauss.encoding.allocate import AllocationConfig, allocate
    from warpgauss.readers.synthetic import generate

    f = normalise(generate("bubbles", 24, seed=1))
    dv = DeviceVolume(f, cpu)
    p, _ = allocate(dv, 200, 0, AllocationConfig(), StageRecorder())
    r = Refiner(dv, p, RefineConfig(iterations=40, samples=512, rebin_every=5), 0, 0.3, 4.0)
    for _ in range(10):
        r.step()
    before = r.model_params()
    gone = np.arange(0, 200, 7)
    r.silence(gone)
    kept = np.setdiff1d(np.arange(200), gone)
    after = r.model_params()
    assert r.n_live == len(kept)
    np.testing.assert_array_equal(after[: r.n_live], before[kept])
    assert (after[r.n_live :, 11] == 0.0).all()
    frozen = after[r.n_live :].copy()
    for _ in range(12):  # across two re-bins
        r.step()
    later = r.model_params()
    np.testing.assert_array_equal(later[r.n_live :], frozen)
    assert not np.array_equal(later[: r.n_live], after[: r.n_live])  # the rest trains on
    assert r.state_arrays()[1]["n_train"] == len(kept)
    # taken out again (the late re-plan): indices among those still in; the earlier stay out
    again = np.arange(3, r.n_live, 11)
    still = np.setdiff1d(np.arange(r.n_live), again)
    r.silence(again)
    now = r.model_params()
    assert r.n_live == len(still) and r.silenced == 200 - len(still)
    np.testing.assert_array_equal(now[: r.n_live], later[still])
    assert (now[r.n_live :, 11] == 0.0).all()
    with pytest.raises(WarpgaussError, match="those still in"):
        r.silence(np.array([r.n_live]))
    assert r.state_arrays()[1]["silenced"] == r.silenced


def test_a_coded_budget_re_plans_n_for_the_depths_its_accuracy_needs(tmp_path, cpu):
    """--ratio R: at a quarter of the iterations the model is coded at the depths of its expected
    accuracy; where that would not fit, the least important Gaussians are taken out and the file
    holds the rest. The file fits its budget, the report says what was done, and the same seed
    gives the same file."""
    import warpgauss
    from warpgauss.readers.synthetic import generate

    vol = generate("vortex", 24, seed=0)
    kw = dict(ratio=20, iterations=120, samples=1024, device=cpu, self_test=False, seed=1)
    a = warpgauss.encode(vol, **kw, output=tmp_path / "a.wgs")
    warpgauss.encode(vol, **kw, output=tmp_path / "b.wgs")
    assert (tmp_path / "a.wgs").read_bytes() == (tmp_path / "b.wgs").read_bytes()
    bud = a.report["budget"]
    rp = bud["coded_replan"]
    assert rp["iteration"] == 30 and rp["n_before"] == bud["coded_sizing"]["n"]
    assert rp["n_after"] < rp["n_before"]  # a smooth field outgrows the pilot's depths
    assert a.n <= rp["n_after"] and a.n >= 0.95 * rp["n_after"]
    assert (a.params[:, 11] > 0).all()  # nothing taken out reaches the file
    size = (tmp_path / "a.wgs").stat().st_size
    assert 0.95 * bud["requested_bytes"] <= size <= bud["requested_bytes"]
    assert "taken out" in bud["coded_choice"]


def test_the_late_re_plan_takes_out_more_where_the_model_will_need_more_bits(tmp_path, cpu, monkeypatch):
    """The late re-plan (off by default, measured to lose): half-way from the re-plan to the end
    the model is expected to gain what it gained since; where that asks for more bits than the
    re-plan planned for, the least important primitives still in are taken out so that it fits at
    those depths. Forced here by a large extrapolation: the file still fits its budget, the report
    says what was done, the same seed gives the same file; at 1.0 this small run keeps its
    re-plan's bits and every primitive, and off there is no late look at all."""
    import warpgauss
    from warpgauss.encoding.driver import replan
    from warpgauss.format.ratefit import bits_for_psnr
    from warpgauss.readers.synthetic import generate

    vol = generate("vortex", 24, seed=0)
    kw = dict(ratio=20, iterations=120, samples=1024, device=cpu, self_test=False, seed=3)
    assert "late" not in warpgauss.encode(vol, **kw).report["budget"]["coded_replan"]
    monkeypatch.setattr(replan, "REPLAN_LATE", True)
    plain = warpgauss.encode(vol, **kw).report["budget"]["coded_replan"]
    assert plain["late"]["iteration"] == (120 + 30) // 2 and plain["late"]["n_after"] == plain["late"]["n_before"] == plain["n_after"]
    monkeypatch.setattr(replan, "REPLAN_LATE_EXTRAPOLATE", 12.0)
    a = warpgauss.encode(vol, **kw, output=tmp_path / "a.wgs")
    warpgauss.encode(vol, **kw, output=tmp_path / "b.wgs")
    assert (tmp_path / "a.wgs").read_bytes() == (tmp_path / "b.wgs").read_bytes()
    bud = a.report["budget"]
    rp, late = bud["coded_replan"], bud["coded_replan"]["late"]
    assert late["n_before"] == rp["n_after"] and late["n_after"] < late["n_before"]
    assert late["n_after"] >= (1 - replan.REPLAN_MAX_CUT) * late["n_before"]
    assert late["bits_added"] > rp["bits_added"] and late["bits_added"] == bits_for_psnr(late["planned_psnr_db"])[1]
    assert a.n <= late["n_after"] and (a.params[:, 11] > 0).all()
    size = (tmp_path / "a.wgs").stat().st_size
    assert 0.95 * bud["requested_bytes"] <= size <= bud["requested_bytes"]
    assert "more were taken out" in bud["coded_choice"]


def test_the_measured_alternatives_still_run(tmp_path, cpu, monkeypatch):
    """The rate-control variants benchmarks/accuracy/sweep.py measured against the defaults (off
    by default): pruning up to half the excess with a refit of the rest, and coding at the
    sizing's depths. Each still fits its budget and says what it did."""
    import warpgauss
    from warpgauss.encoding.driver import replan, sizing
    from warpgauss.format import ratefit
    from warpgauss.readers.synthetic import generate

    vol = generate("vortex", 24, seed=0)
    kw = dict(ratio=20, iterations=40, samples=512, device=cpu, self_test=False, seed=1)
    monkeypatch.setattr(ratefit, "PRUNE_SHARE", 0.5)
    monkeypatch.setattr(replan, "REFIT_SHARE", 0.5)
    monkeypatch.setattr(replan, "REPLAN_AT", 0.0)  # no re-plan: the export has the excess to prune
    m = warpgauss.encode(vol, **kw, output=tmp_path / "refit.wgs")
    fit = m.report["budget"]["coded_fit"]
    assert fit["refit"]["iterations"] == 30 and fit["pruned"] > 0 and fit["refit"]["first_fit"]["pruned"] > 0
    assert (tmp_path / "refit.wgs").stat().st_size <= m.report["budget"]["requested_bytes"]
    monkeypatch.setattr(replan, "REFIT_SHARE", 0.0)
    monkeypatch.setattr(replan, "REFINED_BITS", "sizing")
    monkeypatch.setattr(sizing, "CODED_REFINE_GAIN_DB", 30.0)  # sized for finer grids than the default
    m = warpgauss.encode(vol, **kw, output=tmp_path / "sizing.wgs")
    bud = m.report["budget"]
    assert bud["coded_sizing"]["bits_added"] > 0
    assert bud["coded_bits_from_accuracy"] is None  # the depths N was sized for
    bits = dict(bud["coded_sizing"]["bits"])
    for step in bud["coded_fit"]["steps"]:  # the rate control started from them
        bits[step[:-2]] += 1 if step.endswith("+1") else -1
    assert bits == bud["coded_fit"]["bits"]
    assert (tmp_path / "sizing.wgs").stat().st_size <= m.report["budget"]["requested_bytes"]


def test_a_scored_fit_spends_bits_where_they_are_worth_most(monkeypatch):
    """With ratefit.MEASURE_BIT_WORTH (off by default: measured, it does not pay) and a score,
    fit_bytes measures each attribute's bit (one more, one fewer, projected and scored) and drops
    the bits that lose least per byte first, adds those that gain most first; a score that sees
    no difference drops the fixed orders' bits (and adds them in ties, the fewest grown first)."""
    from test_wgs import realistic_params

    from warpgauss.format import coded, ratefit

    assert ratefit.MEASURE_BIT_WORTH is False
    monkeypatch.setattr(ratefit, "MEASURE_BIT_WORTH", True)

    p = realistic_params(np.random.default_rng(4), 2000)
    bits = dict(coded.CODED_BITS)
    full = len(coded.encode_coded(p, bits)[0])
    care = {"mu": 100.0, "log_s": 1.0, "q": 1.0, "a": 1.0, "w": 1.0}

    def mu_matters(stored, b):  # a PSNR-like score: noise power falls 4x a bit, mu's 100x the rest's
        return -10 * np.log10(sum(care[k] * 4.0 ** -b[k] for k in b))

    def blind(stored, b):
        return 0.0

    roomy = ratefit.fit_bytes(p, int(full * 1.2), bits, score=mu_matters)
    assert roomy[2]["steps"][0] == "mu+1" and ratefit.fit_bytes(p, int(full * 1.2), bits)[2]["steps"][0] == "q+1"
    worth = roomy[2]["bit_worth"]
    assert max(worth, key=lambda k: worth[k]["gain"]) == "mu" and min(worth, key=lambda k: worth[k]["loss"]) != "mu"
    tight = ratefit.fit_bytes(p, int(full * 0.8), bits, score=mu_matters)
    assert tight[2]["bytes"] <= int(full * 0.8) and "mu-1" not in tight[2]["choice"][0]["steps"]
    for budget in (int(full * 1.2), int(full * 0.8)):
        fixed, same = ratefit.fit_at_share(p, budget, bits), ratefit.fit_bytes(p, budget, bits, score=blind)
        first = same[2]["choice"][0]["steps"] if budget < full else same[2]["steps"]  # tight: the choice's first fit
        drops = [s for s in fixed[2]["steps"] if s.endswith("-1")]
        assert [s for s in first if s.endswith("-1")] == drops and any(s.endswith("-1" if budget < full else "+1") for s in first)
        assert same[2]["bytes"] <= budget
        if budget > full:  # adding bits in ties re-sorts after each (the fewest grown first): here the same
            assert first == fixed[2]["steps"]


def test_a_re_plan_holds_bits_back_rather_than_take_out_too_many(tmp_path, cpu, monkeypatch):
    """replan.REPLAN_MAX_CUT: where the depths of the expected accuracy would take out more than
    that share of the Gaussians, the re-plan codes one bit fewer on every attribute at a time
    (down to the default depths) instead; the report says so and the file still fits."""
    import warpgauss
    from warpgauss.encoding.driver import replan
    from warpgauss.readers.synthetic import generate

    vol = generate("vortex", 24, seed=0)
    kw = dict(ratio=8, iterations=120, samples=1024, device=cpu, self_test=False, seed=3)
    free = warpgauss.encode(vol, **kw).report["budget"]["coded_replan"]
    assert free["bits_added"] > 0 and free["n_after"] < free["n_before"]
    assert free["planned_psnr_db"] == free["expected_psnr_db"]
    monkeypatch.setattr(replan, "REPLAN_MAX_CUT", 0.0)  # no cut is small enough: back to the default depths
    m = warpgauss.encode(vol, **kw, output=tmp_path / "held.wgs")
    bud = m.report["budget"]
    held = bud["coded_replan"]
    assert held["bits_added"] == 0 and held["planned_psnr_db"] < held["expected_psnr_db"] == free["expected_psnr_db"]
    assert held["n_after"] >= free["n_after"]
    assert "planned for" in bud["coded_choice"]
    # replan.REFINED_HELD_START: the fit started from the re-plan's depths where the accuracy's are higher
    note = bud["coded_bits_from_accuracy"]
    start = {k: min(v, held["bits"][k]) for k, v in note["bits"].items()}
    assert note.get("held_by_replan", note["bits"]) == start
    if start != note["bits"]:
        assert "started from the re-plan's depths" in bud["coded_choice"]
        assert not any(s.endswith("-1") for s in bud["coded_fit"]["steps"][:1]) or bud["coded_fit"]["first_bytes"] > bud["requested_bytes"]
    assert (tmp_path / "held.wgs").stat().st_size <= bud["requested_bytes"]


def test_the_re_plans_codings_at_once_decide_as_one_after_the_other(cpu, monkeypatch):
    """replan.REPLAN_WORKERS: the re-plan's fewer-bit codings on threads, several at a time, pick
    the same depths and take out the same Gaussians as one coding after the other (the same model
    bit for bit), where the first depths are enough, where none but the default's is, and where
    the walk stops between them."""
    import warpgauss
    from warpgauss.encoding.driver import replan
    from warpgauss.readers.synthetic import generate

    vol = generate("vortex", 24, seed=0)
    kw = dict(ratio=8, iterations=120, samples=1024, device=cpu, self_test=False, seed=3)
    seen = set()
    for cut in (replan.REPLAN_MAX_CUT, 0.0, 0.2):
        monkeypatch.setattr(replan, "REPLAN_MAX_CUT", cut)
        models = []
        for workers in (1, 3):
            monkeypatch.setattr(replan, "REPLAN_WORKERS", workers)
            models.append(warpgauss.encode(vol, **kw))
        one, three = ({k: v for k, v in m.report["budget"]["coded_replan"].items() if k != "seconds"} for m in models)
        assert one == three
        np.testing.assert_array_equal(np.asarray(models[0].params), np.asarray(models[1].params))
        seen.add(one["bits_added"])
    assert len(seen) >= 2  # the cases differ in the depths they stop at


def _error_field_refiner(cpu, **cfg):
    f = _field()
    base = dict(iterations=1, samples=60_000, jitter=0.0, importance=True, uniform_support=False, error_share=0.5)
    return f, Refiner(DeviceVolume(f, cpu), _toy_params(f, 400), RefineConfig(**{**base, **cfg}), 0, 0.3, 4.0)


def _random_errors(smp, seed: int, share: float) -> np.ndarray:
    """Random error sums (2^-32 fixed point) on ``share`` of the sampler's bricks, folded in: the sums."""
    rng = np.random.default_rng(seed)
    acc = rng.integers(0, 2**36, size=smp.bricks, dtype=np.int64) * (rng.random(smp.bricks) < share)
    smp.err_acc.assign(acc)
    smp.refresh_errors()
    return acc


def _brick_voxels(shape, bricks) -> np.ndarray:
    """Voxels of each 4^3 brick inside a grid of ``shape`` (z, y, x)."""
    (nz, ny, nx), (bz, by, bx) = shape, bricks
    return np.einsum("k,j,i->kji", *(np.minimum(4, n - 4 * np.arange(b)) for n, b in ((nz, bz), (ny, by), (nx, bx))))


def test_the_error_sums_are_the_samples_weighted_squared_errors(cpu):
    """Sampler.record_errors adds each sample's weight x squared error (point_grads' value term
    x M) to its 4^3 brick in 2^-32 fixed point: equal to a numpy reference bit for bit (integer
    sums do not depend on the order), and folded into the running sums at a re-bin."""
    f, r = _error_field_refiner(cpu)
    r.sample()
    r.forward()
    smp = r.sampler
    smp.record_errors(r.passes.point_loss)
    loss = r.passes.point_loss.numpy()[:, 0].astype(np.float32)
    e = loss * np.float32(r.m)
    fixed = (e.astype(np.float64) * 2.0**32).astype(np.int64)
    ijk = np.rint(r.points.numpy()[: r.m]).astype(int) // 4
    want = np.zeros(smp.bricks, np.int64)
    np.add.at(want, (ijk[:, 2], ijk[:, 1], ijk[:, 0]), np.where(e > 0, fixed, 0))
    np.testing.assert_array_equal(smp.err_acc.numpy(), want)
    assert want.sum() > 0
    smp.refresh_errors()
    np.testing.assert_allclose(smp.err_sum.numpy(), want.astype(np.float64) / 2.0**32, rtol=1e-6)
    assert not smp.err_acc.numpy().any()


def test_the_error_stratum_follows_its_quota_and_keeps_the_loss_the_full_grid_mse(cpu):
    """With error_share 0.5: the quota of each brick is cap x sqrt(sum x voxels) over the largest
    (numpy float32 reference, exactly), the error stratum's samples fall in the bricks in
    proportion to it, every sample's weight is 1 / (D q(v)) with the stratum's probability in
    q(v) (float64 reference), and the weighted mean of a per-voxel quantity still estimates its
    full-grid mean."""
    f, r = _error_field_refiner(cpu)
    smp = r.sampler
    acc = _random_errors(smp, 5, 0.6)
    bz, by, bx = smp.bricks
    nb = _brick_voxels(f.values.shape, smp.bricks).astype(np.float32)
    s = np.float32(0.7) * np.float32(0) + acc.astype(np.float32) / np.float32(2.0**32)
    score = np.sqrt(s * nb)
    quota = (np.float32(smp.err_cap) * (score / score.max())).astype(np.int64)
    np.testing.assert_array_equal(smp.err_quota.numpy(), quota)
    r.sample()
    m, m_err = r.m, smp.m_err
    m_high, m_mid, m_uni = r.strata
    assert m_err == 30_000 and m_high + m_mid + m_uni + m_err == m
    pts = np.rint(r.points.numpy()[:m]).astype(int)
    b = (pts[:, 2] // 4 * by + pts[:, 1] // 4) * bx + pts[:, 0] // 4
    hist = np.bincount(b[m - m_err :], minlength=bz * by * bx) / m_err
    p = quota.reshape(-1) / quota.sum()
    assert 0.5 * np.abs(hist - p).sum() < 0.05  # total variation
    assert hist[p == 0].sum() == 0
    # the weights: float64 reference of 1 / (D q(v))
    v = f.values.astype(np.float64)
    high, mid = v > 0.4, (v > 0.02) & (v <= 0.4)
    n_high, n_mid, n_all = int(high.sum()), int(mid.sum()), v.size
    k, j, i = pts[:, 2], pts[:, 1], pts[:, 0]
    q = np.where(high[k, j, i], m_high / (m * n_high), 0.0) + np.where(mid[k, j, i], m_mid / (m * n_mid), 0.0)
    q += m_err / m * quota.reshape(-1)[b] / (quota.sum() * nb.reshape(-1)[b])
    q += m_uni / (m * n_all)
    want = 1.0 / (max(n_all, n_high + n_mid) * q)
    np.testing.assert_allclose(r.weight.numpy(), want, rtol=1e-5)
    w = r.weight.numpy().astype(np.float64)
    t2 = r.target.numpy().astype(np.float64) ** 2
    truth = float(np.mean(v**2))
    assert abs(float(np.sum(w * t2) / np.sum(w)) - truth) < 0.05 * truth


def test_with_the_error_stratum_the_same_seed_gives_the_same_model(cpu):
    """Same seed, same device => same model with samples following the error (integer sums, an
    order-free max, integer prefix sums): two runs across three re-bins agree bit for bit, and
    the stratum changes the model (it is not a no-op)."""
    from warpgauss.core.profiling import StageRecorder
    from warpgauss.encoding.allocate import AllocationConfig, allocate
    from warpgauss.readers.synthetic import generate

    f = normalise(generate("interface", 24, seed=2))
    dv = DeviceVolume(f, cpu)
    params, _ = allocate(dv, 300, 0, AllocationConfig(), StageRecorder())
    out = []
    for share in (0.5, 0.5, 0.0):
        r = Refiner(dv, params, RefineConfig(iterations=30, samples=2048, error_share=share), 7, 0.3, 4.0)
        for _ in range(30):
            r.step()
        out.append(r.model_params())
    assert int(r.sampler.err_cum.numpy()[-1]) == 0  # off: the placeholder index
    np.testing.assert_array_equal(out[0], out[1])
    assert not np.array_equal(out[0], out[2])


def test_the_error_stratum_is_not_drawn_where_its_map_sees_too_few_samples(cpu):
    """Below draw.ERROR_MIN_SAMPLES_A_CELL samples a 4^3 cell over the map's memory (rebin_every x
    samples / (1 - error_decay) / cells) nothing is drawn from the error stratum: the model equals
    error_share 0's bit for bit and the report says so; at the threshold it is drawn."""
    from warpgauss.core.profiling import StageRecorder
    from warpgauss.encoding.allocate import AllocationConfig, allocate
    from warpgauss.encoding.refine import draw
    from warpgauss.readers.synthetic import generate

    f = normalise(generate("interface", 64, seed=2))
    cells = 16**3
    dv = DeviceVolume(f, cpu)
    params, _ = allocate(dv, 200, 0, AllocationConfig(), StageRecorder())
    sparse = math.ceil(draw.ERROR_MIN_SAMPLES_A_CELL * cells * 0.3 / 10) - 1  # the most samples below the threshold
    out = []
    for share, m in ((0.5, sparse), (0.0, sparse), (0.5, sparse + 1)):
        r = Refiner(dv, params, RefineConfig(iterations=25, samples=m, error_share=share), 3, 0.3, 4.0)
        for _ in range(25):
            r.step()
        out.append((r.model_params(), r.sampler.error_report()))
    (p_sparse, rep), (p_off, _), (p_dense, rep_dense) = out
    assert rep["share"] == 0.5 and rep["share_drawn"] == 0.0
    assert rep["samples_a_cell"] == pytest.approx(10 * sparse / 0.3 / cells) and rep["samples_a_cell"] < draw.ERROR_MIN_SAMPLES_A_CELL
    np.testing.assert_array_equal(p_sparse, p_off)
    assert rep_dense["samples_a_cell"] >= draw.ERROR_MIN_SAMPLES_A_CELL
    assert rep_dense["share_drawn"] == pytest.approx(round((sparse + 1) * 0.5) / (sparse + 1))


def test_pooled_quota_scores_blocks_of_cells(cpu, monkeypatch):
    """draw.ERROR_POOL: where the cells see too few samples the quota scores blocks of f^3 cells,
    each cell getting its block's sqrt(sum x voxels) by its share of the block's voxels (numpy
    float64 reference; the blocks at the grid's edge are partial), and the weights still make the
    loss estimate the full-grid mean."""
    from warpgauss.encoding.refine import draw

    monkeypatch.setattr(draw, "ERROR_POOL", True)
    monkeypatch.setattr(draw, "ERROR_POOL_SAMPLES_A_CELL", 1e9)  # the largest blocks
    f, r = _error_field_refiner(cpu)
    smp = r.sampler
    assert smp.error_pool == draw.ERROR_MAX_POOL == 8 and smp.error_report()["cell_edge"] == 32
    acc = _random_errors(smp, 3, 0.3)
    bz, by, bx = smp.bricks
    fp = smp.error_pool
    e = acc.astype(np.float64) / 2.0**32
    vox = _brick_voxels(f.values.shape, smp.bricks).astype(np.float64)
    pad = [(0, -(-n // fp) * fp - n) for n in (bz, by, bx)]
    blocks = lambda a: np.pad(a, pad).reshape(-(-bz // fp), fp, -(-by // fp), fp, -(-bx // fp), fp).sum(axis=(1, 3, 5))  # noqa: E731
    eb, vb = blocks(e), blocks(vox)
    up = lambda a: np.repeat(np.repeat(np.repeat(a, fp, 0), fp, 1), fp, 2)[:bz, :by, :bx]  # noqa: E731
    score = np.sqrt(up(eb) * up(vb)) * vox / up(vb)
    want = np.floor(smp.err_cap * score / score.max())
    got = smp.err_quota.numpy()
    assert np.abs(got - want).max() <= 1 and np.mean(got == want) > 0.99  # float32 against float64 at the floor
    assert got.sum() > 0
    r.sample()
    w = r.weight.numpy().astype(np.float64)
    t2 = r.target.numpy().astype(np.float64) ** 2
    truth = float(np.mean(f.values.astype(np.float64) ** 2))
    assert abs(float(np.sum(w * t2) / np.sum(w)) - truth) < 0.05 * truth


def test_an_encode_reports_the_error_stratum_and_pools_sparse_cells_on_request(monkeypatch):
    """The report's refinement.error_stratum: at 0.098 samples a 4^3 cell (64^3, 12 samples) the
    stratum is left out by default, and with draw.ERROR_POOL drawn from blocks of 4^3 cells (edge
    16: 6.25 samples a block)."""
    import warpgauss
    from warpgauss.encoding.refine import draw
    from warpgauss.readers.synthetic import generate

    vol = generate("interface", 64, seed=1)
    kw = dict(budget=200, iterations=10, samples=12, format="full", device="cpu", self_test=False)
    off = warpgauss.encode(vol, **kw).report["refinement"]["error_stratum"]
    monkeypatch.setattr(draw, "ERROR_POOL", True)
    pooled = warpgauss.encode(vol, **kw).report["refinement"]["error_stratum"]
    assert off["samples_a_cell"] == pytest.approx(10 * 12 / 0.3 / 16**3)
    assert off["share_drawn"] == 0.0 and off["cell_edge"] == 4
    assert pooled["share_drawn"] == pytest.approx(0.5) and pooled["cell_edge"] == 16


def test_error_share_is_validated():
    from warpgauss.errors import WarpgaussError

    for bad in (-0.1, 1.0, float("nan")):
        with pytest.raises(WarpgaussError, match="error_share"):
            RefineConfig(error_share=bad).validate()
    with pytest.raises(WarpgaussError, match="error_decay"):
        RefineConfig(error_decay=1.5).validate()
