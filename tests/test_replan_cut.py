"""The re-plan's cut (issue #53): which primitives a coded budget takes out half-way through
refinement, by weight x sigma volume or by what leaving each out changes at its centre."""

from __future__ import annotations

import numpy as np
import pytest

from warpgauss.format.ratefit import LEFT_OUT_HOLE, importance, importance_left_out


def _blob(mu, log_s, a, w):
    """One model row: centre, log-sigmas, the identity turn, value, weight."""
    return np.array([*mu, *log_s, 1.0, 0.0, 0.0, 0.0, a, w], np.float32)


def test_left_out_importance_is_the_change_at_each_centre(cpu):
    """The ranking equals its float64 definition on the model's own dense evaluation at the
    centres, and among equal weights and sizes a primitive that says what its neighbours say
    ranks below one that differs from them (which weight x sigma volume cannot tell apart)."""
    from warpgauss.field.gaussians import GaussianField

    rng = np.random.default_rng(4)
    rows = [_blob(rng.uniform(4, 20, 3), rng.uniform(0.3, 1.2, 3), rng.uniform(0.1, 0.9), rng.uniform(0.2, 1.0)) for _ in range(40)]
    rows += [_blob((12, 12, 12), (0.8,) * 3, 0.5, 0.6), _blob((12.5, 12, 12), (0.8,) * 3, 0.5, 0.6)]  # twins: each redundant
    rows += [_blob((12, 13, 12), (0.8,) * 3, 0.95, 0.6)]  # beside them, a different value
    p = np.stack(rows)
    value, density, _ = GaussianField(p, (24, 24, 24), device=cpu).evaluate_dense(p[:, 0:3])
    got = importance_left_out(p, value, density)
    q = p.astype(np.float64)
    w = np.abs(q[:, 11])
    ref = w * np.exp(q[:, 3:6].sum(1)) * (np.abs(q[:, 10] - value) + LEFT_OUT_HOLE) / np.maximum(density - w, 1e-3 * np.median(density))
    np.testing.assert_allclose(got, ref, rtol=1e-12)
    assert got[-1] > got[-2] and got[-1] > got[-3]  # the odd one out is kept longer than the twins
    assert importance(p)[-1] == pytest.approx(importance(p)[-2])  # the weight ranking cannot tell them apart


def test_a_left_out_cut_takes_out_as_many_others_and_the_file_fits(tmp_path, cpu, monkeypatch):
    """replan.CUT_ORDER "left-out" (the default) against "weight": the same re-plan (iteration, depths, how many go), other
    primitives taken out, the same file for the same seed, within its byte budget; an unknown
    order is refused by name."""
    import warpgauss
    from warpgauss.encoding.driver import replan
    from warpgauss.readers.synthetic import generate

    vol = generate("vortex", 24, seed=0)
    kw = dict(ratio=20, iterations=120, samples=1024, device=cpu, self_test=False, seed=1)
    monkeypatch.setattr(replan, "CUT_ORDER", "weight")
    by_weight = warpgauss.encode(vol, **kw)
    monkeypatch.setattr(replan, "CUT_ORDER", "left-out")
    a = warpgauss.encode(vol, **kw, output=tmp_path / "a.wgs")
    warpgauss.encode(vol, **kw, output=tmp_path / "b.wgs")
    assert (tmp_path / "a.wgs").read_bytes() == (tmp_path / "b.wgs").read_bytes()
    rp, rw = a.report["budget"]["coded_replan"], by_weight.report["budget"]["coded_replan"]
    for k in ("iteration", "n_before", "n_after", "bits", "expected_psnr_db"):
        assert rp[k] == rw[k], k
    assert rp["n_after"] < rp["n_before"]
    assert not np.array_equal(a.params, by_weight.params)  # other primitives went
    assert (tmp_path / "a.wgs").stat().st_size <= a.report["budget"]["requested_bytes"]
    monkeypatch.setattr(replan, "CUT_ORDER", "value")
    with pytest.raises(ValueError, match="CUT_ORDER"):
        warpgauss.encode(vol, **kw)


def test_the_training_state_reads_the_model_at_any_points(cpu):
    """PairPasses.values_at: the value and density of the refiner's state at points inside and
    outside the volume equal the stored model's dense evaluation there (float32 rounding), the
    centres included, and reading them changes no iteration buffer."""
    from test_pair_pass import _refiner

    from warpgauss.field.gaussians import GaussianField

    r = _refiner(cpu, n=200, samples=512)
    r.step()
    before = r.passes.value.numpy().copy()
    p = r.model_params()
    rng = np.random.default_rng(2)
    pts = np.concatenate([p[:, 0:3], rng.uniform(-2.0, 26.0, (300, 3))]).astype(np.float32)
    value, density = r.passes.values_at(pts)
    ref_v, ref_d, _ = GaussianField(p, r.passes.shape_xyz, device=cpu).evaluate_dense(pts)
    np.testing.assert_allclose(density, ref_d, rtol=2e-4, atol=1e-6)
    np.testing.assert_allclose(value, ref_v, rtol=2e-4, atol=2e-5)
    assert (density[: len(p)] > 0).all()
    np.testing.assert_array_equal(r.passes.value.numpy(), before)
