"""Checkpoints, Ctrl-C and resume: an interrupted run continues to the model an uninterrupted one gives."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

import warpgauss
from warpgauss.cli.main import app
from warpgauss.errors import WarpgaussError
from warpgauss.format import checkpoint

RUN = {"example": "vortex", "example_size": 24, "budget": 300, "iterations": 120, "samples": 512, "device": "cpu", "seed": 3}
# the same run on the command line
RUN_ARGS = "encode --example vortex --size 24 --budget 300 --iterations 120 --samples 512 --device cpu --seed 3".split()


def _reference(tmp_path):
    return warpgauss.encode(**RUN, output=tmp_path / "ref.wgs")


def test_ctrl_c_writes_a_valid_model_and_resume_gives_the_uninterrupted_model(tmp_path, cpu):
    ref = _reference(tmp_path)
    out = tmp_path / "run.wgs"

    def progress(it, total, rec):  # a real SIGINT to this process, as Ctrl-C sends
        if it == 50:
            os.kill(os.getpid(), signal.SIGINT)

    a = warpgauss.encode(**RUN, output=out, checkpoint_every=3600, on_progress=progress)
    assert a.report["interrupted"] and a.report["refinement"]["iterations_done"] == 50
    ckpt = Path(str(out) + ".ckpt")
    assert ckpt.is_file()
    part = warpgauss.Model.load(out)  # the state reached, as a valid model
    assert part.n == 300 and np.all(np.isfinite(part.params))
    assert not np.array_equal(part.params, ref.params)
    b = warpgauss.encode(**RUN, output=out, resume=True)
    assert not b.report["interrupted"]
    assert b.params.tobytes() == ref.params.tobytes()  # bit-identical on the CPU
    assert warpgauss.Model.load(out).params.tobytes() == ref.params.tobytes()
    r = b.report["refinement"]
    assert [(s["from_iteration"], s["to_iteration"]) for s in r["sessions"]] == [(0, 50), (50, 120)]
    assert r["seconds"] == pytest.approx(sum(s["seconds"] for s in r["sessions"]))
    assert r["checkpoint"]["resumed_from_iteration"] == 50
    assert not ckpt.exists()  # removed once the final model is written


def test_resume_between_two_re_bins_keeps_the_uniform_stratum_support(tmp_path, cpu):
    """The support the uniform samples are drawn from is marked at re-bins; a checkpoint taken
    between two (iteration 25) carries it, so the resumed run is the uninterrupted one."""
    run = {"example": "bubbles", "example_size": 40, "budget": 600, "iterations": 60, "samples": 512, "device": "cpu", "seed": 3}
    ref = warpgauss.encode(**run, output=tmp_path / "ref.wgs")
    assert 0.0 < ref.report["refinement"]["uniform_support_share"] < 1.0  # the restriction is in play
    out = tmp_path / "run.wgs"

    def progress(it, total, rec):
        if it == 25:  # progress comes every 25 iterations; re-bins every 10
            os.kill(os.getpid(), signal.SIGINT)

    a = warpgauss.encode(**run, output=out, checkpoint_every=3600, on_progress=progress)
    assert a.report["refinement"]["iterations_done"] == 25
    b = warpgauss.encode(**run, output=out, resume=True)
    assert b.params.tobytes() == ref.params.tobytes()


def test_sigkill_mid_run_then_resume_from_the_last_periodic_checkpoint(tmp_path, cpu):
    ref = _reference(tmp_path)
    out = tmp_path / "killed.wgs"
    ckpt = Path(str(out) + ".ckpt")
    args = [
        sys.executable,
        "-m",
        "warpgauss.cli.main",
        *RUN_ARGS,
        "--checkpoint-every",
        "0",
        "-o",
        str(out),
    ]
    proc = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        deadline = time.time() + 120
        reached = 0
        while time.time() < deadline and proc.poll() is None:
            if ckpt.is_file():
                try:
                    reached = checkpoint.load(ckpt)[1]["iteration"]
                except WarpgaussError:
                    reached = 0  # never a partial file, but be safe while polling
                if reached >= 20:
                    break
            time.sleep(0.05)
        assert proc.poll() is None, proc.stderr.read().decode()
        proc.send_signal(signal.SIGKILL)
        proc.wait(30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert not out.exists()  # nothing partial at the destination
    arrays, meta = checkpoint.load(ckpt)
    assert 20 <= meta["iteration"] < 120
    res = CliRunner().invoke(
        app,
        [
            *RUN_ARGS,
            "-o",
            str(out),
            "--resume",
            "--json",
        ],
    )
    assert res.exit_code == 0, res.output
    assert warpgauss.Model.load(out).params.tobytes() == ref.params.tobytes()
    rep = json.loads(Path(str(out) + ".report.json").read_text())
    sessions = rep["refinement"]["sessions"]
    assert sessions[0]["from_iteration"] == 0 and sessions[-1]["to_iteration"] == 120
    assert all(a["to_iteration"] == b["from_iteration"] for a, b in zip(sessions, sessions[1:]))
    assert rep["refinement"]["seconds"] == pytest.approx(sum(s["seconds"] for s in sessions))


def test_resume_refuses_other_options_and_damaged_checkpoints(tmp_path, cpu):
    out = tmp_path / "m.wgs"

    def progress(it, total, rec):
        if it == 25:
            os.kill(os.getpid(), signal.SIGINT)

    warpgauss.encode(**RUN, output=out, checkpoint_every=3600, on_progress=progress)
    ckpt = Path(str(out) + ".ckpt")
    other = dict(RUN, seed=4)
    with pytest.raises(WarpgaussError, match="another input, budget, seed or other refinement options"):
        warpgauss.encode(**other, output=out, resume=True)
    good = ckpt.read_bytes()
    cases = {
        "truncated": good[: len(good) // 2],
        "flipped": good[:100] + bytes([good[100] ^ 0xFF]) + good[101:],
        "garbage": b"not a checkpoint at all",
    }
    for name, data in cases.items():
        ckpt.write_bytes(data)
        res = CliRunner().invoke(
            app,
            [
                *RUN_ARGS,
                "-o",
                str(out),
                "--resume",
            ],
        )
        assert res.exit_code == 2, (name, res.output)
        assert "checkpoint" in res.output and "Traceback" not in res.output, (name, res.output)
    ckpt.unlink()
    res = CliRunner().invoke(app, ["encode", "--example", "vortex", "--size", "24", "-o", str(out), "--resume", "--device", "cpu"])
    assert res.exit_code == 2 and "no checkpoint at" in res.output


@pytest.mark.parametrize("mode", ["straight-through", "refit"])
def test_resume_inside_the_quantisation_aware_phase_gives_the_uninterrupted_coded_model(tmp_path, cpu, mode):
    """format="coded" with quantisation-aware refinement from 80 % (iterations 96-120 here): a
    run stopped at 100 and resumed writes the file an uninterrupted run writes, byte for byte."""
    from warpgauss.encoding.refine import RefineConfig
    from warpgauss.format.coded import CODED_BITS

    RUN = {**globals()["RUN"], "refine": RefineConfig(quantise=dict(CODED_BITS), quantise_from=0.8, quantise_mode=mode)}
    ref = warpgauss.encode(**RUN, format="coded", output=tmp_path / "ref.wgs")
    out = tmp_path / "run.wgs"

    def progress(it, total, rec):
        if it == 100:
            os.kill(os.getpid(), signal.SIGINT)

    a = warpgauss.encode(**RUN, format="coded", output=out, checkpoint_every=3600, on_progress=progress)
    assert a.report["interrupted"] and a.report["refinement"]["iterations_done"] == 100
    b = warpgauss.encode(**RUN, format="coded", output=out, resume=True)
    assert not b.report["interrupted"]
    assert out.read_bytes() == (tmp_path / "ref.wgs").read_bytes()
    assert b.params.tobytes() == ref.params.tobytes()
