"""`warpgauss stats`: values equal an independent numpy computation (SPEC section 5)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from test_allocate import _blobs, _stats_numpy
from typer.testing import CliRunner

from warpgauss.cli.main import app
from warpgauss.encoding.driver.sizing import CODED_BPP_MEASURED
from warpgauss.readers import write_volume


def test_stats_json_equals_numpy(tmp_path, cpu):
    v = _blobs(40, seed=6)
    path = write_volume(tmp_path / "blobs_40x40x40_float32.raw", v.astype(np.float32))
    res = CliRunner().invoke(app, ["stats", str(path), "--device", "cpu", "--json", "--budgets", "100,1000,100000000"])
    assert res.exit_code == 0, res.output
    got = json.loads(res.stdout)
    ref = _stats_numpy(v)
    assert got["occupancy"] == pytest.approx(ref["occupancy"], abs=1e-12)
    assert got["grad_top10"] == pytest.approx(ref["grad_top10"], rel=1e-5)
    assert got["s1"] == pytest.approx(ref["s1"], rel=1e-5)
    assert got["s16"] == pytest.approx(ref["s16"], rel=1e-5)
    assert got["s1_s16"] == pytest.approx(ref["s1"] / ref["s16"], rel=1e-5)
    # seed limit from the occupied voxels and those of them with a non-zero gradient
    w = v.astype(np.float64)
    w = (w - w.min()) / (w.max() - w.min())
    occ = w > 0.02
    g = np.sqrt(sum(np.gradient(w, axis=a) ** 2 for a in range(3)))
    e, o = int((occ & (g > 0)).sum()), int(occ.sum())
    assert got["n_max"] == math.floor(min(e / 0.55, o / 0.45))
    # the table: feasible budgets and N_max, exact sizes (one 4 KiB header block)
    ns = [b["n"] for b in got["budgets"]]
    assert ns == [100, 1000, got["n_max"]]
    for b in got["budgets"]:
        assert b["bytes"] == 48 * b["n"] + 4096 and b["compact_bytes"] == 12 * b["n"] + 4096
        lo, hi = b["coded_bytes_estimate"]  # the default format, as the range measured on real models
        least, most = CODED_BPP_MEASURED  # B a Gaussian, one coded header (smaller than the 4 KiB block)
        head = lo - least * b["n"]
        assert 0 < head < 4096 and hi - most * b["n"] == pytest.approx(head, abs=1)
        assert b["coded_compression_ratio_estimate"] == pytest.approx([got["source_bytes"] / hi, got["source_bytes"] / lo])
        assert b["compression_ratio"] == pytest.approx(v.size * 4 / b["bytes"])
    assert got["reading"]


def test_stats_readings_tell_the_example_fields_apart(cpu):
    from warpgauss.encoding.driver import load_field
    from warpgauss.encoding.stats import field_stats

    read = {}
    for name in ("bubbles", "interface", "turbulence"):
        f, _ = load_field(None, example=name, example_size=64)
        read[name] = field_stats(f, "cpu")["reading"]
    assert read["bubbles"].startswith("sparse")
    assert "interface-concentrated" in read["interface"]
    assert "turbulence-like" in read["turbulence"]


def test_stats_refuses_bad_budgets():
    res = CliRunner().invoke(app, ["stats", "--example", "vortex", "--size", "16", "--budgets", "0,5"])
    assert res.exit_code == 2 and "--budgets must be" in res.output


def _strict(text: str):
    """json.loads that refuses NaN and Infinity, as jq and other parsers do."""

    def refuse(c):
        raise ValueError(f"non-standard JSON constant {c}")

    return json.loads(text, parse_constant=refuse)


def test_undefined_s1_s16_is_null_in_stats_and_the_encode_report(tmp_path, cpu):
    """A 12^3 grid has no voxel pairs 16 apart: S(1)/S(16) is undefined and written as null, so
    `stats --json` and the report file stay standard JSON."""
    res = CliRunner().invoke(app, ["stats", "--example", "vortex", "--size", "12", "--device", "cpu", "--json"])
    assert res.exit_code == 0, res.output
    got = _strict(res.stdout)
    assert got["s1_s16"] is None and got["s1"] > 0 and got["s16"] == 0
    assert "no structure at 16 voxels" in got["reading"]
    text = CliRunner().invoke(app, ["stats", "--example", "vortex", "--size", "12", "--device", "cpu"])
    assert text.exit_code == 0 and "S(1)/S(16) n/a" in text.stdout
    out = tmp_path / "m.wgs"
    enc = CliRunner().invoke(
        app, ["encode", "--example", "vortex", "--size", "12", "--budget", "20", "--iterations", "2", "-o", str(out), "--device", "cpu"]
    )
    assert enc.exit_code == 0, enc.output
    rep = _strict((tmp_path / "m.wgs.report.json").read_text())
    assert rep["structure"]["s1_s16"] is None


def test_the_default_ladder_leaves_out_files_larger_than_the_source(cpu):
    """A 48^3 float32 volume (442,368 bytes) was offered 200,000 Gaussians (issue #57 item 7): the
    default ladder keeps the budgets whose coded file stays below the source, at the top of the
    measured range, and names the ones it leaves out."""
    res = CliRunner().invoke(app, ["stats", "--example", "vortex", "--size", "48", "--device", "cpu", "--json"])
    assert res.exit_code == 0, res.output
    got = json.loads(res.stdout)
    source = 48**3 * 4
    assert got["source_bytes"] == source
    kept = [b["n"] for b in got["budgets"]]
    out = [r["n"] for r in got["left_out"]]
    assert kept == [2_000, 20_000] and out == [200_000, got["n_max"]] and got["left_out"][-1]["is_n_max"]
    for b in got["budgets"]:
        assert b["coded_bytes_estimate"][1] <= source
    most = CODED_BPP_MEASURED[1]
    assert all(most * n > source - 4096 for n in out)  # each left out because its file could pass the source
    # the 20,000 row is kept for its coded file, yet its full-precision file is larger than the source
    row = got["budgets"][1]
    assert row["larger_than_source"] == ["full"] and row["bytes"] > source > row["compact_bytes"]


def test_budgets_given_are_all_tabulated_in_80_columns_each_ratio_below_1_marked(monkeypatch, cpu):
    from warpgauss.cli import stats as stats_cli

    monkeypatch.setattr(stats_cli.out_console, "width", 80)
    args = ["stats", "--example", "vortex", "--size", "48", "--device", "cpu", "--budgets", "100,2000,20000,200000"]
    got = json.loads(CliRunner().invoke(app, [*args, "--json"]).stdout)
    assert [b["n"] for b in got["budgets"]] == [100, 2_000, 20_000, 200_000, got["n_max"]] and got["left_out"] == []
    for b in got["budgets"]:
        sizes = {"coded": b["coded_bytes_estimate"][1], "compact": b["compact_bytes"], "full": b["bytes"]}
        assert b["larger_than_source"] == [k for k, v in sizes.items() if v > got["source_bytes"]]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 0, res.output
    lines = res.stdout.splitlines()
    assert all(len(line) <= 80 for line in lines) and "…" not in res.stdout, res.stdout
    rows = {line.split()[0]: line.split() for line in lines if line.split() and line.split()[0].rstrip("*").replace(",", "").isdigit()}
    assert list(rows) == ["100", "2,000", "20,000", "200,000", f"{got['n_max']:,}*"], res.stdout  # one line a budget
    for b, cells in zip(got["budgets"], rows.values()):
        assert len(cells) == 10  # N, coded range and unit, ratio, compact and unit, ratio, full and unit, ratio
        marks = [cells[i].endswith("!") for i in (3, 6, 9)]
        assert marks == [k in b["larger_than_source"] for k in ("coded", "compact", "full")], cells
    assert "! a file larger than the 432 KiB source" in res.stdout
