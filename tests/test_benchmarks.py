"""The run-time-against-error benchmark (benchmarks/refine/bench_tradeoff.py) and its plot, on a tiny CPU case."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[1] / "benchmarks" / "refine"
BUDGET = 0.5  # seconds of the time-budgeted run
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def _load(name: str):
    """Import a script from benchmarks/ (not a package) by path."""
    spec = importlib.util.spec_from_file_location(f"_bench_{name}", BENCH / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _cpu_or_skip() -> str:
    from warpgauss.core.warp import warp

    if "cpu" not in {str(d) for d in warp().get_devices()}:
        pytest.skip("this Warp build has no CPU device")
    return "cpu"


@pytest.fixture(scope="module")
def tradeoff(tmp_path_factory) -> tuple[Path, dict]:
    dev = _cpu_or_skip()
    out = tmp_path_factory.mktemp("tradeoff") / "tradeoff.json"
    argv = ["--fields", "vortex", "--sizes", "16", "--budgets", "60", "--presets", "fast", "--iterations-override", "20",
            "--time-budgets", str(BUDGET), "--device", dev, "--out", str(out)]  # fmt: skip
    _load("bench_tradeoff").main(argv)
    return out, json.loads(out.read_text())


def test_tradeoff_rows_baseline_and_budget(tradeoff):
    out, data = tradeoff
    for key in ("benchmark", "device", "device_name", "warp_version", "date", "command", "rows"):
        assert key in data
    assert data["device"] == "cpu" and data["complete"] and data["skipped"] == []
    assert "--time-budgets" in data["command"]
    assert [p.name for p in out.parent.iterdir()] == [out.name]  # no temporary file left behind
    rows = data["rows"]
    assert [r["run"] for r in rows] == ["paper", "fast", f"T={BUDGET:g}s"]  # the baseline runs first though not asked for
    assert all((r["field"], r["size"], r["n"]) == ("vortex", 16, 60) for r in rows)
    assert data["volumes"][0]["field"] == "vortex" and data["volumes"][0]["generate_seconds"] >= 0
    paper, fast, timed = rows
    assert paper["iterations"] == fast["iterations"] == 20 and paper["samples"] == 3072
    assert paper["delta_final_db_vs_paper"] == 0.0 and paper["refine_time_ratio_vs_paper"] == 1.0
    assert fast["delta_final_db_vs_paper"] == pytest.approx(fast["psnr_final_db"] - paper["psnr_final_db"])
    assert timed["delta_final_db_vs_paper"] == pytest.approx(timed["psnr_final_db"] - paper["psnr_final_db"])
    for r in rows:
        assert r["psnr_final_db"] > r["psnr_analytic_db"]
        assert 0 < r["refine_loop_seconds"] <= r["refine_seconds"] <= r["encode_seconds"]
        assert r["encode_seconds"] == pytest.approx(sum(v for k, v in r["stages"].items() if k != "P"))
    assert timed["kind"] == "time_budget" and timed["time_budget"] == BUDGET and timed["preset"] == "paper"
    assert timed["iterations"] >= 5  # at least the timing probe
    assert timed["within_budget"]
    assert timed["self_test_seconds"] + timed["refine_loop_seconds"] <= BUDGET
    assert timed["refine_seconds"] <= BUDGET + 0.1  # + the refiner's set-up, which the budget does not cover


def test_tradeoff_max_seconds_and_refusal(tmp_path):
    dev = _cpu_or_skip()
    bench = _load("bench_tradeoff")
    out = tmp_path / "stopped.json"
    bench.main(["--fields", "vortex", "--sizes", "8", "--budgets", "20", "--presets", "fast", "--time-budgets", "1",
                "--device", dev, "--max-seconds", "0", "--out", str(out)])  # fmt: skip
    data = json.loads(out.read_text())
    assert data["rows"] == [] and not data["complete"]
    assert [s["run"] for s in data["skipped"]] == ["paper", "fast", "T=1s"]
    out = tmp_path / "refused.json"
    bench.main(["--fields", "vortex", "--sizes", "8", "--budgets", "100000", "--presets", "fast", "--time-budgets", "",
                "--device", dev, "--out", str(out)])  # fmt: skip
    data = json.loads(out.read_text())
    assert len(data["rows"]) == 1 and "seed limit" in data["rows"][0]["refused"]
    assert [s["run"] for s in data["skipped"]] == ["fast"]


def test_plot_tradeoff(tradeoff, tmp_path, capsys):
    pytest.importorskip("matplotlib")
    out, _ = tradeoff
    png = tmp_path / "tradeoff.png"
    _load("plot_tradeoff").main([str(out), "--out", str(png)])
    assert png.read_bytes()[:8] == PNG_SIGNATURE
    table = capsys.readouterr().out
    assert "| vortex | 16^3 | 60 | paper |" in table and "baseline" in table
