"""Budget ladders: one read and analysis, and each model equal to its own single encode."""

from __future__ import annotations

import json

import pytest
from typer.testing import CliRunner

import warpgauss
from warpgauss.cli.main import app
from warpgauss.errors import WarpgaussError

KW = {"example": "vortex", "example_size": 24, "iterations": 30, "samples": 256, "device": "cpu", "seed": 2}


def test_ladder_models_equal_single_encodes_and_share_the_analysis(tmp_path, cpu):
    models = warpgauss.encode_ladder(budgets=[400, 100], output_pattern=str(tmp_path / "m.n{n}.wgs"), **KW)
    assert [m.n for m in models] == [100, 400]
    for m in models:
        single = warpgauss.encode(budget=m.n, **KW)
        assert m.params.tobytes() == single.params.tobytes()  # same seed, same device
        assert m.report["psnr_db"] == pytest.approx(single.report["psnr_db"], abs=1e-9)
        assert warpgauss.Model.load(tmp_path / f"m.n{m.n}.wgs").params.tobytes() == m.params.tobytes()
    stages = [[s["stage"] for s in m.report["stages"]] for m in models]
    assert "P" in stages[0] and "S1a" in stages[0]
    assert "P" not in stages[1] and "S1a" not in stages[1]  # reused, and said so
    assert {s["what"] for s in models[1].report["skipped"]} >= {"P", "S1a"}
    assert models[1].report["ladder"] == {"budgets": [100, 400], "position": 1, "shared": ["P", "S1a"]}
    assert models[1].report["psnr_db"] > models[0].report["psnr_db"]


def test_ladder_refuses_an_infeasible_top_budget_before_encoding(tmp_path, cpu):
    with pytest.raises(WarpgaussError, match="exceeds the seed limit"):
        warpgauss.encode_ladder(budgets=[10, 10**8], output_pattern=str(tmp_path / "x.n{n}.wgs"), **KW)
    assert not list(tmp_path.iterdir())


def test_ladder_cli_prints_psnr_per_budget(tmp_path, cpu):
    out = tmp_path / "v.wgs"
    args = [
        "encode",
        "--example",
        "vortex",
        "--size",
        "24",
        "--ladder",
        "100,300",
        "--iterations",
        "20",
        "--samples",
        "256",
        "--device",
        "cpu",
        "-o",
        str(out),
        "--json",
    ]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 0, res.output
    rows = json.loads(res.stdout)["ladder"]
    assert [r["n"] for r in rows] == [100, 300]
    for r in rows:
        assert (tmp_path / f"v.n{r['n']}.wgs").is_file() and (tmp_path / f"v.n{r['n']}.wgs.report.json").is_file()
        assert r["psnr_db"] > r["psnr_analytic_db"]
    res = CliRunner().invoke(app, [*args[:-1], "--budget", "5"])
    assert res.exit_code == 2 and "does not combine" in res.output


def test_ladder_cli_keeps_target_psnr_and_plateau(tmp_path, cpu):
    """--ladder passes --target-psnr and --plateau on (they were dropped: the header said None)."""
    from warpgauss import Model

    out = tmp_path / "v.wgs"
    args = [
        "encode",
        "--example",
        "vortex",
        "--size",
        "16",
        "--ladder",
        "40,80",
        "--iterations",
        "10",
        "--samples",
        "128",
        "--target-psnr",
        "99",
        "--plateau",
        "0.25",
        "--device",
        "cpu",
        "-o",
        str(out),
        "--json",
    ]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 0, res.output
    for n in (40, 80):
        refinement = Model.load(tmp_path / f"v.n{n}.wgs").header["encoding"]["refinement"]
        assert refinement["target_psnr"] == 99.0 and refinement["plateau_db"] == 0.25
    res = CliRunner().invoke(app, [*args[:-3], "--target-psnr=-1", "-o", str(tmp_path / "w.wgs"), "--json"])
    assert res.exit_code == 2 and "--target-psnr must be a positive number of dB" in res.output


# what a ladder does not take from warpgauss.encode, and why (a new encode option must be added to
# encode_ladder or here, so that no path drops it silently, as --target-psnr once was)
NOT_FOR_LADDERS = {
    "budget": "the ladder gives the budgets",
    "ratio": "the ladder gives the budgets",
    "file_bytes": "the ladder gives the budgets",
    "output": "output_pattern names one file per budget",
    "analytic_output": "one analytic model per budget is not written",
    "checkpoint": "ladders do not resume",
    "checkpoint_every": "ladders do not resume",
    "resume": "ladders do not resume",
    "time_budget": "a time budget is one encode's",
    "bricks": "a ladder encodes the whole volume",
    "halo": "a ladder encodes the whole volume",
    "client": "a ladder encodes the whole volume",
    "max_error": "a bounded residual is one encode's (the CLI refuses --ladder with --max-error)",
    "max_error_rel": "a bounded residual is one encode's",
    "residual_psnr": "a bounded residual is one encode's",
    "max_device_memory": "a ladder encodes the whole volume",
    "max_host_memory": "a ladder encodes the whole volume",
    "read_by_bricks": "a ladder encodes the whole volume",
    "volume_on_host": "a ladder's rungs share one device volume (not kept on the host yet)",
    "devices": "a ladder's rungs refine on one device (the CLI refuses --ladder with --devices)",
    "on_bricks": "a ladder encodes the whole volume",
    "on_stats": "the statistics are shared by the ladder",
    "warm_start": "warm starts belong to series",
    "motion": "warm starts belong to series",
    "session": "an Encoder's state",
    "progress": "a ladder's rungs show their progress through on_progress",
}


def test_every_encode_option_reaches_a_ladder_or_says_why_not():
    import inspect

    encode = set(inspect.signature(warpgauss.encode).parameters)
    ladder = set(inspect.signature(warpgauss.encode_ladder).parameters)
    assert encode - ladder == set(NOT_FOR_LADDERS), sorted((encode - ladder) ^ set(NOT_FOR_LADDERS))
    assert ladder - encode == {"budgets", "output_pattern"}
