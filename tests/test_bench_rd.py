"""Plumbing of benchmarks/rate_distortion/bench_rd.py and plot_rd.py on a 16^3 field (seconds on the CPU).

SZ3 (pysz), ZFP (zfpy) and matplotlib are in the ``bench`` extra only: without them the script
skips those codecs and the parts of this test that need them are skipped.
"""

from __future__ import annotations

import importlib.util
import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest

BENCH = Path(__file__).resolve().parents[1] / "benchmarks" / "rate_distortion"


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
        [
            "--size",
            "16",
            "--fields",
            "vortex",
            "--real",
            "none",
            "--budgets",
            "60",
            "--iterations",
            "3",
            "--min-ratio",
            "1",
            "--device",
            "cpu",
            "--out",
            str(out),
        ]
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
    from warpgauss.readers.synthetic import generate

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


def _fake_sz3(calls):
    """A codec whose ratio is a monotone staircase power law in the bound (like SZ3's)."""

    def run(data, eb):
        calls.append(eb)
        ratio = 5.0 * (eb / 1e-4) ** 0.45 * (1.0 + 0.01 * math.sin(40 * math.log(eb)))
        return int(round(4e6 / ratio)), data, 0.0, 0.0

    return run


@pytest.mark.parametrize("target", [3.0, 40.0, 200.0])
def test_sz3_search_reaches_the_target_ratio_and_uses_the_curve(target):
    bench = _load("bench_rd")
    calls = []
    eb, nbytes, _, _, _, steps, ok = bench.sz3_matched(None, 4e6, target, 1.0, 0.02, run=_fake_sz3(calls))
    assert ok and abs(4e6 / nbytes / target - 1) <= 0.02 and steps == len(calls)
    # seeded with a curve that brackets the target, it needs fewer runs than from scratch
    fake = _fake_sz3([])
    curve = [(e, 4e6 / fake(None, e)[0]) for e in (1e-6, 1e-5, 1e-4, 1e-3, 1e-2, 1e-1, 1.0)]
    seeded = []
    *_, steps2, ok2 = bench.sz3_matched(None, 4e6, target, 1.0, 0.02, seen=curve, run=_fake_sz3(seeded))
    assert ok2 and steps2 == len(seeded) <= min(steps, 3) and steps <= 12


def test_sz3_search_stops_when_the_target_is_out_of_reach():
    bench = _load("bench_rd")
    calls = []
    *_, ok = bench.sz3_matched(None, 4e6, 1e9, 1.0, 0.02, run=_fake_sz3(calls))
    assert not ok and len(calls) < 40 and max(calls) == pytest.approx(2.0)


def test_codec_workers_and_volume_dir(tmp_path):
    """--volume-dir writes the fields once and maps them; --workers gives the rows of the in-process run."""
    pytest.importorskip("zfpy")
    bench = _load("bench_rd")
    common = [
        "--size",
        "16",
        "--fields",
        "vortex",
        "--real",
        "none",
        "--budgets",
        "60",
        "--iterations",
        "0",
        "--min-ratio",
        "1",
        "--codecs",
        "zfp",
        "--zfp-rates",
        "1,4",
        "--zfp-tols",
        "0.01",
        "--device",
        "cpu",
    ]
    gen = bench.main(common + ["--volume-dir", str(tmp_path / "vol"), "--generate-only", "--out", str(tmp_path / "g.json")])
    npy = tmp_path / "vol" / "vortex_16.npy"
    assert set(gen["generated"]) == {"vortex"} and npy.is_file()
    from warpgauss.readers.synthetic import generate

    np.testing.assert_array_equal(np.load(npy), generate("vortex", 16, seed=0))
    a = bench.main(common + ["--out", str(tmp_path / "a.json")])
    b = bench.main(common + ["--volume-dir", str(tmp_path / "vol"), "--workers", "2", "--out", str(tmp_path / "b.json")])

    def rows(res):
        return sorted((r["codec"], r["param"], r["bytes"], round(r["psnr_db"], 9)) for r in res["volumes"]["vortex 16^3"]["rows"])

    assert rows(a) == rows(b)
    assert {r[0] for r in rows(a)} == {"wg-full", "wg-compact", "zfp-rate", "zfp-acc", "zfp-rate-matched"}


def test_resume_keeps_measured_rows_and_runs_only_what_is_missing(tmp_path):
    pytest.importorskip("zfpy")
    bench = _load("bench_rd")
    common = [
        "--size",
        "16",
        "--fields",
        "vortex",
        "--real",
        "none",
        "--budgets",
        "60",
        "--iterations",
        "0",
        "--min-ratio",
        "1",
        "--codecs",
        "zfp",
        "--zfp-tols",
        "0.01",
        "--device",
        "cpu",
    ]
    a = bench.main(common + ["--zfp-rates", "1", "--out", str(tmp_path / "a.json")])
    first = a["volumes"]["vortex 16^3"]["rows"]
    b = bench.main(common + ["--zfp-rates", "1,4", "--resume", str(tmp_path / "a.json"), "--out", str(tmp_path / "b.json")])
    rows = b["volumes"]["vortex 16^3"]["rows"]
    assert rows[: len(first)] == first  # kept as measured, warpgauss rows included
    new = rows[len(first) :]
    assert [(r["codec"], r["rate_bits_per_value"]) for r in new] == [("zfp-rate", 4.0)]  # only the missing setting
    assert b["resumed_from"] == str(tmp_path / "a.json") and b["complete"] and b["previous_run"]["date"] == a["date"]
    # the key identifies a planned task and the row it gave
    keys = {bench.task_key(r) for r in first if not r["codec"].startswith("wg")}
    assert bench.task_key({"kind": "zfp-rate", "rate": 1.0}) in keys and bench.task_key(new[0]) not in keys
