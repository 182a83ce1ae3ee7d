"""Skipping what a field does not need: target PSNR, plateau, the self-test once per device."""

from __future__ import annotations

import numpy as np
import pytest

import warpgauss
from warpgauss.encoding import refine

KW = {"example": "vortex", "example_size": 24, "budget": 300, "samples": 256, "device": "cpu", "seed": 1}


def _skipped(m) -> set:
    return {s["what"] for s in m.report["skipped"]}


def test_target_reached_by_the_analytic_model_skips_refinement(cpu):
    analytic = warpgauss.encode(**KW, iterations=0)
    m = warpgauss.encode(**KW, iterations=500, target_psnr=analytic.report["psnr_db"] - 1.0)
    assert "S2 refinement" in _skipped(m) and m.report["refinement"]["stop"]["iterations_skipped"] == 500
    assert m.params.tobytes() == analytic.params.tobytes()
    assert "S2" not in [s["stage"] for s in m.report["stages"]]


def test_target_stops_refinement_once_reached(cpu):
    # float32: the validation checks see the model as stored (a coded model moves once more at export)
    full = warpgauss.encode(**KW, iterations=600, format="full")
    analytic_db = full.report["evaluation"]["analytic"]["psnr_db"]
    target = analytic_db + 0.5 * (full.report["psnr_db"] - analytic_db)  # reached well before the end
    m = warpgauss.encode(**KW, iterations=600, target_psnr=target, format="full")
    stop = m.report["refinement"]["stop"]
    assert stop["at_iteration"] < 600 and stop["at_iteration"] % 100 == 0
    assert stop["checks"][-1]["psnr_db"] >= target  # stopped at the first check that reached it
    assert all(c["psnr_db"] < target for c in stop["checks"][:-1])
    # the validation set is the whole 24^3 grid here, so the check is the reported PSNR
    assert m.report["psnr_db"] == pytest.approx(stop["checks"][-1]["psnr_db"], abs=1e-4)
    assert m.report["psnr_db"] >= target
    assert stop["seconds_saved_estimate"] > 0 and any("target PSNR" in s["why"] for s in m.report["skipped"])


def test_plateau_stops_when_the_gain_over_the_window_is_small(cpu):
    m = warpgauss.encode(**KW, iterations=1000, plateau_db=50.0)  # any gain is "small"
    stop = m.report["refinement"]["stop"]
    assert stop["reason"].startswith("plateau") and stop["at_iteration"] == 400  # first check with 300 behind it
    assert [c["iteration"] for c in stop["checks"]] == [100, 200, 300, 400]
    assert np.all(np.isfinite(m.params))


def test_self_test_runs_once_per_process_and_device(cpu, monkeypatch):
    monkeypatch.setattr(refine, "SELF_TESTS", {})
    import warpgauss.encoding.driver  # noqa: F401  (the driver imports the dict at call time)

    a = warpgauss.encode(**KW, iterations=5)
    b = warpgauss.encode(**KW, iterations=5)
    assert a.report["refinement"]["self_test"]["passed"] and not a.report["refinement"]["self_test"].get("reused")
    assert b.report["refinement"]["self_test"]["reused"] and "self-test" in _skipped(b)
    assert a.params.tobytes() == b.params.tobytes()


def test_bad_stop_options_are_refused():
    with pytest.raises(warpgauss.WarpgaussError, match="--target-psnr must be a positive"):
        warpgauss.encode(**KW, target_psnr=-3)


def test_the_uniform_stratum_restriction_is_logged_only_when_it_applies():
    import warpgauss
    from warpgauss.encoding.refine import LossWeights, RefineConfig
    from warpgauss.readers.synthetic import generate

    vol = generate("interface", 24)
    for value_empty, logged in ((0.0, True), (1.0, False)):
        cfg = RefineConfig(iterations=5, samples=256, weights=LossWeights(value_empty=value_empty))
        m = warpgauss.encode(vol, budget=300, refine=cfg, device="cpu", seed=0)
        hits = [s for s in m.report["skipped"] if s["what"] == "uniform samples in empty space"]
        assert bool(hits) == logged
        if logged:
            assert 0.0 < hits[0]["uniform_samples_moved_share"] < 1.0


def test_the_support_restriction_of_the_uniform_stratum_is_logged_when_it_applies():
    """Default loss (empty samples carry a loss): on a sparse field the uniform stratum skips the
    grid no Gaussian reaches and the report says how much; switched off, nothing is logged."""
    from warpgauss.encoding.refine import RefineConfig
    from warpgauss.readers.synthetic import generate

    vol = generate("bubbles", 48, seed=2)
    for on in (True, False):
        m = warpgauss.encode(
            vol, budget=600, refine=RefineConfig(iterations=3, samples=256, uniform_support=on), device="cpu", evaluate=False
        )
        hits = [s for s in m.report["skipped"] if s["what"] == "uniform samples outside the model's support"]
        share = m.report["refinement"]["uniform_support_share"]
        if on:
            assert len(hits) == 1 and 0.0 < share < 1.0
            assert 0.0 < hits[0]["share_skipped_at_start"] < 1.0
        else:
            assert not hits and share is None


def test_empty_bricks_of_the_full_grid_evaluation_are_logged_and_exact(cpu):
    """Bubbles are sparse: the full-grid evaluation skips the bricks no Gaussian reaches, says so,
    and its PSNR equals a plain numpy PSNR of an unskipped decode (the skipped voxels are exact)."""
    from warpgauss.readers.synthetic import generate

    vol = generate("bubbles", 48, seed=2)
    m = warpgauss.encode(vol, budget=150, iterations=3, samples=128, device="cpu", full_eval=True)
    entry = next(s for s in m.report["skipped"] if s["what"].startswith("empty 8^3 bricks"))
    share = m.field("cpu").active_fraction
    assert 0.0 < share < 1.0 and entry["share_skipped"] == pytest.approx(1.0 - share)
    assert entry["seconds_saved_estimate"] >= 0.0
    assert m.report["evaluation"]["final"]["bricks_evaluated_share"] == pytest.approx(share)
    # the model evaluated at every voxel centre, without the brick skip
    nz, ny, nx = vol.shape
    z, y, x = np.meshgrid(np.arange(nz), np.arange(ny), np.arange(nx), indexing="ij")
    pts = np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1).astype(np.float32)
    every = m.field("cpu").evaluate(pts).astype(np.float64)
    mse = np.mean((every - vol.reshape(-1).astype(np.float64)) ** 2)
    assert m.report["psnr_db"] == pytest.approx(10 * np.log10(1 / mse), abs=1e-3)
    info = {}
    m.decode(device="cpu", normalised=True, info=info)
    assert info["bricks_evaluated_share"] == pytest.approx(share)
    # a dense field reaches every brick: nothing is skipped and nothing is logged
    d = warpgauss.encode(**KW, iterations=3, full_eval=True)
    assert d.report["evaluation"]["final"]["bricks_evaluated_share"] == 1.0
    assert not any(s["what"].startswith("empty 8^3 bricks") for s in d.report["skipped"])
