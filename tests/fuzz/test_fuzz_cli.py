"""Fuzz the command line: random option values and files for encode, decode, info and eval.

Invariant: every invocation ends with exit code 0 (and its outputs in place and valid) or exit
code 2 with an error on stderr and no traceback; a failed run leaves no file behind. Option parsing
errors are click's (exit 2, "Usage: ..."); every other refusal is our one line, and never an
"internal error" (the catch-all of ``handle_errors`` for exceptions that are bugs).
"""

from __future__ import annotations

import os
import re
import shutil
import tempfile
from pathlib import Path

import numpy as np
import pytest
from fuzz_support import fuzz
from hypothesis import example, given
from hypothesis import strategies as st
from typer.testing import CliRunner

from warpgauss.cli.main import app

_TMP = Path(tempfile.mkdtemp(prefix="cli-fuzz-"))
runner = CliRunner()


def _volume() -> Path:
    z, y, x = np.meshgrid(*(np.arange(8.0),) * 3, indexing="ij")
    v = (0.5 + 0.4 * np.sin(0.8 * x) * np.cos(0.6 * y) * np.sin(0.5 * z + 1.0)).astype(np.float32)
    path = _TMP / "vol_8x8x8_float32.raw"
    v.tofile(path)
    return path


VOLUME = _volume()


def _model() -> Path:
    path = _TMP / "m.wgs"
    r = runner.invoke(app, ["encode", str(VOLUME), "-o", str(path), "--budget", "12", "--iterations", "0", "--device", "cpu"])
    assert r.exit_code == 0, r.output
    return path


MODEL = _model()


def invoke(args: list[str], outputs: list[Path] = (), on_success=None):
    """Run the CLI in a fresh directory; check the invariant; return the result.

    ``on_success(workdir)`` checks the outputs of a run that succeeded.
    """
    work = Path(tempfile.mkdtemp(dir=_TMP))
    old = os.getcwd()
    os.chdir(work)
    try:
        r = runner.invoke(app, [str(a) for a in args], env={"WARPGAUSS_DEBUG": ""})
    finally:
        os.chdir(old)
    assert r.exit_code in (0, 2), (args, r.exit_code, r.output, r.exception)
    assert "Traceback" not in r.output, (args, r.output)
    assert r.exception is None or isinstance(r.exception, SystemExit), (args, repr(r.exception))
    if r.exit_code == 2:
        err = [line for line in r.stderr.splitlines() if line.strip()]
        assert err, (args, r.output)
        if not any(line.startswith("Usage:") for line in err):  # click's parser reports in its own format
            assert len(err) == 1 and err[0].startswith("error:"), (args, err)
            assert "internal error" not in err[0], (args, err)
        for out in outputs:
            assert not (work / out).exists(), (args, out)
        leftovers = [p.name for p in work.iterdir()]
        assert not leftovers, (args, leftovers)
    elif on_success is not None:
        on_success(work)
    shutil.rmtree(work, ignore_errors=True)
    return r


NUMBER = st.one_of(
    st.integers(-(2**70), 2**70).map(str),
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.sampled_from(["0", "-1", "1", "1e-300", "1e300", "nan", "inf", "-inf", "", "x", "0x10", "1_000"]),
)
SMALL = st.one_of(st.integers(-3, 40).map(str), NUMBER)
TEXT = st.one_of(
    st.text(max_size=12),
    st.sampled_from(["8x8x8", "8,8,8", "0x8x8", "8x8", "999999x999999x999999", "float32", "uint8", "big", "little", "middle", "/", "g/d"]),
)
ENCODE_OPTIONS = {
    "--budget": SMALL,
    "--ratio": NUMBER,
    "--seed": NUMBER,
    "--iterations": st.integers(-2, 4).map(str),
    "--samples": st.integers(-3, 4096).map(
        str
    ),  # huge counts: see test_huge_sample_counts_are_refused "--lr": NUMBER, "--w-density": NUMBER, "--w-smooth": NUMBER, "--w-anchor": NUMBER,
    "--w-value-empty": NUMBER,
    "--w-cap": NUMBER,
    "--w-aniso": NUMBER,
    "--w-smooth-final": NUMBER,
    "--time-budget": NUMBER,
    "--stride": SMALL,
    "--fill-value": NUMBER,
    "--shape": TEXT,
    "--dtype": TEXT,
    "--endian": TEXT,
    "--dataset": TEXT,
    "--variable": TEXT,
    "--preset": TEXT,
    "--device": st.just("cpu"),
}


@fuzz(60)
@given(
    st.dictionaries(st.sampled_from(sorted(ENCODE_OPTIONS)), st.none(), max_size=5).flatmap(
        lambda keys: st.fixed_dictionaries({k: ENCODE_OPTIONS[k] for k in keys})
    ),
    st.booleans(),
)
@example({"--budget": "5", "--iterations": "3", "--samples": "64", "--lr": "nan"}, False)
@example({"--budget": "5", "--ratio": "20"}, False)
@example({"--budget": "5", "--seed": str(2**70)}, False)
@example({"--budget": "5", "--time-budget": "nan"}, False)
@example({"--budget": "5", "--stride": "1000"}, False)
def test_encode_options(opts, compact):
    opts.setdefault("--budget", "6")
    opts.setdefault("--iterations", "2")
    opts.setdefault("--samples", "64")
    opts["--device"] = "cpu"
    args = ["encode", VOLUME, "-o", "out.wgs", "--no-self-test"]
    for k, v in opts.items():
        args += [k, v]
    if compact:
        args.append("--compact")
    invoke(args, outputs=[Path("out.wgs"), Path("out.wgs.report.json")], on_success=_model_ok)


def _model_ok(work: Path) -> None:
    import json

    from warpgauss.format.model import Model

    m = Model.load(work / "out.wgs")
    assert np.isfinite(m.params).all()
    rep = json.loads((work / "out.wgs.report.json").read_text())
    assert rep["budget"]["n"] == m.n


@fuzz(30)
@given(
    st.sampled_from(["vortex", "bubbles", "turbulence", "interface", "nope", ""]), st.integers(-2, 12).map(str)
)  # huge sizes: see test_huge_example_sizes_are_refused
def test_encode_examples_of_any_size(name, size):
    invoke(
        ["encode", "--example", name, "--size", size, "--budget", "4", "--iterations", "0", "--device", "cpu", "-o", "out.wgs"],
        outputs=[Path("out.wgs")],
    )


@fuzz(40)
@given(shape=st.one_of(st.none(), TEXT), normalised=st.booleans(), ext=st.sampled_from([".npy", ".raw", ".h5", ".vti", ".xyz", ""]))
@example(shape="100000x100000x100000", normalised=False, ext=".npy")
@example(shape="3x2x1", normalised=True, ext=".vti")
def test_decode_options(shape, normalised, ext):
    out = Path("dec" + ext)
    args = ["decode", MODEL, "-o", out, "--device", "cpu"]
    if shape is not None:
        args += ["--shape", shape]
    if normalised:
        args.append("--normalised")
    r = invoke(args, outputs=[out], on_success=lambda work: _decoded_ok(work / out))
    if r.exit_code == 0:
        assert ext in (".npy", ".raw", ".h5", ".vti")


def _decoded_ok(path: Path) -> None:
    if path.suffix == ".npy":
        assert np.isfinite(np.load(path)).all()
    else:
        assert path.stat().st_size > 0


@fuzz(40)
@given(st.binary(max_size=200), st.sampled_from(["info", "decode", "eval"]))
def test_commands_on_garbage_model_files(data, command):
    bad = _TMP / "garbage.wgs"
    bad.write_bytes(data)
    args = {"info": ["info", bad], "decode": ["decode", bad, "-o", "d.npy"], "eval": ["eval", bad, VOLUME]}[command]
    r = invoke(args, outputs=[Path("d.npy")])
    assert r.exit_code == 2


@fuzz(30)
@given(
    stride=st.one_of(st.none(), SMALL),
    fill=st.one_of(st.none(), NUMBER),
    volume=st.sampled_from(["same", "missing", "other-shape", "garbage"]),
)
def test_eval_options(stride, fill, volume):
    vol = {
        "same": VOLUME,
        "missing": _TMP / "missing_8x8x8_float32.raw",
        "other-shape": _TMP / "o_4x4x4_uint8.raw",
        "garbage": _TMP / "g.npy",
    }[volume]
    if volume == "other-shape":
        vol.write_bytes(bytes(64))
    elif volume == "garbage":
        vol.write_bytes(b"\x93NUMPY garbage")
    args = ["eval", MODEL, vol, "--device", "cpu", "--json"]
    if stride is not None:
        args += ["--stride", stride]
    if fill is not None:
        args += ["--fill-value", fill]
    r = invoke(args)
    if volume != "same":
        assert r.exit_code == 2


def test_huge_sample_counts_are_refused():
    invoke(
        [
            "encode",
            VOLUME,
            "-o",
            "out.wgs",
            "--budget",
            "6",
            "--iterations",
            "2",
            "--device",
            "cpu",
            "--no-self-test",
            "--samples",
            str(10**12),
        ],
        outputs=[Path("out.wgs")],
    )


@pytest.mark.parametrize("size", [10**6, 2**40])
def test_huge_example_sizes_are_refused(size):
    invoke(
        ["encode", "--example", "vortex", "--size", str(size), "--budget", "4", "--iterations", "0", "--device", "cpu", "-o", "out.wgs"],
        outputs=[Path("out.wgs")],
    )


def test_info_on_a_good_model():
    r = invoke(["info", MODEL])
    assert r.exit_code == 0 and re.search(r"^Gaussians\s+12,", r.stdout, re.M), r.stdout


@pytest.mark.slow
def test_encode_options_long():
    """The encode fuzz with 20x the examples and fresh random draws (run with -m slow)."""
    inner = test_encode_options.hypothesis.inner_test
    given(
        st.dictionaries(st.sampled_from(sorted(ENCODE_OPTIONS)), st.none(), max_size=6).flatmap(
            lambda keys: st.fixed_dictionaries({k: ENCODE_OPTIONS[k] for k in keys})
        ),
        st.booleans(),
    )(fuzz(1200, derandomize=False)(inner))()
