"""Plumbing of benchmarks/bench_rd.py and plot_rd.py on a 16^3 field (seconds on the CPU).

SZ3 (pysz), ZFP (zfpy) and matplotlib are in the ``bench`` extra only: without them the script
skips those codecs and the parts of this test that need them are skipped.
"""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

import numpy as np
import pytest

BENCH = Path(__file__).resolve().parents[1] / "benchmarks"


def _load(name):
    spec = importlib.util.spec_from_file_location(name, BENCH / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    bench = _load("bench_rd")
    out = tmp_path_factory.mktemp("rd") / "rd.json"
    res = bench.main(
        ["--size", "16", "--fields", "vortex", "--real", "none", "--budgets", "60", "--iterations", "3", "--min-ratio", "1",
         "--device", "cpu", "--out", str(out)]
    )
    return bench, out, res


def test_json_written_and_complete(run):
    bench, out, res = run
    on_disk = json.loads(out.read_text())
    assert on_disk["complete"] is True
    assert on_disk["device"] == "cpu" and on_disk["warp_version"] and on_disk["date"]
    entry = on_disk["volumes"]["vortex 16^3"]
    codecs = {r["codec"] for r in entry["rows"]}
    assert {"wg-full", "wg-compact"} <= codecs
    full = next(r for r in entry["rows"] if r["codec"] == "wg-full")
    comp = next(r for r in entry["rows"] if r["codec"] == "wg-compact")
    assert full["n"] == 60 and full["bytes"] > comp["bytes"]
    assert full["ratio"] == pytest.approx(entry["source_bytes"] / full["bytes"])
    assert comp["ratio"] == pytest.approx(entry["source_bytes"] / comp["bytes"])
    assert 5 < full["psnr_db"] < 80 and abs(full["psnr_db"] - comp["psnr_db"]) < 1.0
    assert full["encode_s"] > 0 and full["decode_s"] > 0


def test_psnr_matches_warpgauss_full_grid_evaluation(run):
    """The benchmark's PSNR equals warpgauss's own full-grid PSNR for the same model."""
    bench, _, _ = run
    import warpgauss
    from warpgauss.synthetic import generate

    vol = generate("vortex", 16, seed=0)
    m = warpgauss.encode(vol, budget=60, iterations=0, device="cpu", evaluate=False)
    truth = bench.Truth(vol, float(vol.min()), float(vol.max()), None)
    ours = truth.psnr(m.decode(device="cpu"))
    theirs = warpgauss.psnr(m, vol, full=True, device="cpu")
    assert ours == pytest.approx(theirs, abs=1e-3)


def test_truth_excludes_masked_voxels():
    bench = _load("bench_rd")
    raw = np.zeros((4, 4, 4), np.float32)
    raw[0, 0, 0] = 1.0
    valid = np.ones_like(raw, bool)
    valid[1] = False
    t = bench.Truth(raw, 0.0, 2.0, valid)
    recon = raw.copy()
    recon[1] = 100.0  # errors only where masked
    assert t.psnr(recon) == pytest.approx(200.0)


def test_reference_codecs(run):
    pytest.importorskip("pysz")
    pytest.importorskip("zfpy")
    _, out, _ = run
    entry = json.loads(out.read_text())["volumes"]["vortex 16^3"]
    codecs = {r["codec"] for r in entry["rows"]}
    assert {"sz3", "sz3-matched", "zfp-rate", "zfp-acc", "zfp-rate-matched"} <= codecs
    full = next(r for r in entry["rows"] if r["codec"] == "wg-full")
    sz = next(r for r in entry["rows"] if r["codec"] == "sz3-matched")
    if sz["matched_to"]["within_tol"]:
        assert sz["ratio"] == pytest.approx(full["ratio"], rel=0.02)


def test_plot_and_table(run, tmp_path):
    pytest.importorskip("matplotlib")
    _, out, _ = run
    plot = _load("plot_rd")
    png = tmp_path / "rd.png"
    md = tmp_path / "rd.md"
    plot.main([str(out), "-o", str(png), "--table", str(md)])
    assert png.stat().st_size > 1000
    assert "vortex 16^3" in md.read_text()
