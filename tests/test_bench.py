"""`warpgauss bench kernels` on the CPU: a tiny configuration, its JSON, and its refusals."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from typer.testing import CliRunner

from warpgauss.cli.main import app
from warpgauss.encoding.bench import source_commit

ROOT = Path(__file__).resolve().parents[1]


def test_bench_kernels_writes_rows_for_every_n_and_sample_count(tmp_path, cpu):
    out = tmp_path / "kernels.json"
    args = ["bench", "kernels", "--device", "cpu", "--size", "16", "--n", "40,120", "--samples", "64,256"]
    res = CliRunner().invoke(app, [*args, "--repeat", "1", "--dense-max-n", "200", "--json-out", str(out)])
    assert res.exit_code == 0, res.output
    r = json.loads(out.read_text())
    assert r["device"] == "cpu" and r["warp_version"] and r["date"]
    assert r["commit"] == source_commit(ROOT) and r["warpgauss_version"]  # the run's commit ($WARPGAUSS_COMMIT or git)
    assert [(x["n"], x["samples"]) for x in r["rows"]] == [(40, 64), (40, 256), (120, 64), (120, 256)]
    for row in r["rows"]:
        assert row["pairs_per_point"] > 1.0  # the synthetic primitives overlap every sample
        assert row["forward_ms"] > 0 and row["backward_ms"] > 0 and row["iteration_ms"] > 0
    # the dense evaluator ran (smallest sample count) and found the same pairs (asserted inside)
    assert [x["samples"] for x in r["rows"] if "dense_forward_ms" in x] == [64, 64]
    assert [e["n"] for e in r["per_n"]] == [40, 120] and all(e["decode_ms"] > 0 for e in r["per_n"])
    assert all(e["decode_slab_equal_to_rowmajor"] for e in r["per_n"])  # the row-major values clamped as the decode's
    assert "| N | samples |" in res.output


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--n", "abc"], "--n must be a comma-separated list"),
        (["--samples", "0"], "--samples must be"),
        (["--repeat", "0"], "--repeat must be"),
    ],
)
def test_bench_kernels_refuses_bad_lists(extra, message):
    res = CliRunner().invoke(app, ["bench", "kernels", "--device", "cpu", "--size", "16", *extra])
    assert res.exit_code == 2
    assert message in res.output and "Traceback" not in res.output
