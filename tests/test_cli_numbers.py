"""Every number `warpgauss encode` prints is one of its report's, and `warpgauss eval` prints its
JSON's and agrees with the encode (issue #57 item 4): a plain, two bounded (one lossless), a
``--target-psnr`` and a ``--psnr`` encode of tiny volumes on the CPU.

Where the numbers disagreed: eval said ``max abs error 0.007843`` and then ``2 source units`` (one
error, two units, neither named); a lossless file encoded at 200 dB and error 0 but evaluated at
153 dB and 7.4e-8 (eval compared against a float32 copy of the source); a ``--psnr`` summary gave
the Gaussians' ratio first and the file's later, and the Gaussians' size as two numbers.
"""

from __future__ import annotations

import json
import math
import re

import numpy as np
import pytest
from typer.testing import CliRunner

from warpgauss.cli.main import app

# a number as printed: 18,651  6.48  0.007843  7.433e-08; with its binary unit where one follows
NUMBER = re.compile(r"(?<![\w.])(-?\d[\d,]*(?:\.\d+)?(?:e[-+]?\d+)?)(?:\s(KiB|MiB|GiB))?(?!\d|\.\d)")
UNITS = {None: 1, "KiB": 1024, "MiB": 1024**2, "GiB": 1024**3}


def run(*args) -> str:
    r = CliRunner().invoke(app, [str(a) for a in args])
    assert r.exit_code == 0, r.output
    return r.stdout


def leaves(obj):
    """Every number in a JSON object (and the length of every list: "1 note on ...")."""
    if isinstance(obj, dict):
        for v in obj.values():
            yield from leaves(v)
    elif isinstance(obj, list):
        yield len(obj)
        for v in obj:
            yield from leaves(v)
    elif isinstance(obj, (int, float)) and not isinstance(obj, bool) and math.isfinite(obj):
        yield float(obj)


def strings(obj):
    if isinstance(obj, dict):
        for v in obj.values():
            yield from strings(v)
    elif isinstance(obj, list):
        for v in obj:
            yield from strings(v)
    elif isinstance(obj, str):
        yield obj


def unexplained(text: str, *sources) -> list[str]:
    """The numbers printed in ``text`` that are no number of the JSON ``sources`` rounded as
    printed (half a unit in the last printed digit); the sources' own strings (names, paths, the
    sizing sentence, the device) are taken out of the text first."""
    for s in sorted({s for src in sources for s in strings(src) if len(s) >= 3}, key=len, reverse=True):
        text = text.replace(s, " ")
    values = [v for src in sources for v in leaves(src)]
    missing = []
    for m in NUMBER.finditer(text):
        token, unit = m.group(1), m.group(2)
        shown = float(token.replace(",", ""))
        mantissa, _, exp = token.partition("e")
        decimals = len(mantissa.partition(".")[2])
        half = 0.5 * 10.0 ** (int(exp or 0) - decimals) * (1 + 1e-9)
        if not any(abs(v / UNITS[unit] - shown) <= half for v in values):
            missing.append(m.group(0))
    return missing


@pytest.fixture(scope="module")
def volumes(tmp_path_factory):
    from warpgauss.readers.synthetic import generate

    d = tmp_path_factory.mktemp("numbers")
    run("example", "vortex", "--size", "32", "-o", d / "v_32x32x32_float32.raw")
    v = generate("vortex", 32, seed=0)
    np.save(d / "u8.npy", np.round(255 * (v - v.min()) / (v.max() - v.min())).astype(np.uint8))
    return d


FAST = ("--iterations", "10", "--samples", "512", "--device", "cpu")
CASES = {
    "plain": ("v_32x32x32_float32.raw", "--ratio", "20", *FAST),
    "bounded": ("u8.npy", "--max-error", "2", *FAST),
    "lossless": ("u8.npy", "--max-error", "0.4", *FAST),  # below 1/2 on integers: the source's own values
    "target_psnr": ("v_32x32x32_float32.raw", "--budget", "60", "--iterations", "300", "--samples", "256", "--target-psnr", "16"),
    "psnr": ("v_32x32x32_float32.raw", "--psnr", "45", *FAST),
}


@pytest.mark.parametrize("case", list(CASES))
def test_every_number_printed_is_the_reports(volumes, tmp_path, case, cpu):
    src, *opts = CASES[case]
    out = tmp_path / f"{case}.wgs"
    text = run("encode", volumes / src, *opts, "-o", out)
    rep = json.loads((tmp_path / f"{case}.wgs.report.json").read_text())
    assert unexplained(text, rep) == [], text
    # one compression ratio, the file's as written, and the file's size as on disk
    size = out.stat().st_size
    assert re.findall(r"compression ([\d.]+)x", text) == [f"{rep['input']['source_bytes'] / size:.2f}"], text
    bytes_shown = {int(b.replace(",", "")) for b in re.findall(r"(?<![\d.,])(\d[\d,]*) B\b", text)}
    res = rep.get("residual")
    if res:
        assert bytes_shown == {size, res["gaussian_bytes"], res["residual_bytes"]}, text
        assert res["gaussian_bytes"] + res["residual_bytes"] == res["file_bytes"] == size
        assert f"{res['max_abs_error']:.6g} source units ({res['max_abs_error_normalised']:.4g} of the value range)" in text
    else:
        assert bytes_shown == {size} and rep["budget"]["bytes"] == size, text
    if case == "target_psnr":
        r = rep["refinement"]
        assert r["iterations_done"] < r["iterations"] and f"{r['iterations_done']} of {r['iterations']} iterations" in text

    # eval prints its JSON's numbers and measures what the encode reported, in the same units
    ev_text = run("eval", out, volumes / src, "--device", "cpu")
    ev = json.loads(run("eval", out, volumes / src, "--device", "cpu", "--json"))
    assert unexplained(ev_text, ev) == [], ev_text
    assert ev["bytes"] == size and ev_text.count("compression") == 1 and f"compression {ev['compression_ratio']:.2f}x" in text
    if res:
        assert (ev["psnr_db"], ev["psnr_occupied_db"]) == (res["psnr_db"], res["psnr_occupied_db"])
        assert (ev["max_abs_error_source"], ev["max_abs_error"]) == (res["max_abs_error"], res["max_abs_error_normalised"])
        assert ev["max_abs_error_source"] <= ev["bound"] == res["bound"]
        alone = json.loads(run("eval", out, volumes / src, "--device", "cpu", "--json", "--no-residual"))
        final = rep["evaluation"]["final"]
        assert alone["psnr_db"] == pytest.approx(final["psnr_db"], abs=1e-9)
        assert alone["max_abs_error"] == pytest.approx(final["max_abs_error"], abs=1e-9)
    else:
        assert ev["psnr_db"] == pytest.approx(rep["psnr_db"], abs=1e-9)
        assert ev["max_abs_error"] == pytest.approx(rep["evaluation"]["final"]["max_abs_error"], abs=1e-9)
    if case == "bounded":  # 2 source units of a uint8 range 0-255: both units printed, each named
        assert ev["max_abs_error_source"] == 2.0 and ev["max_abs_error"] == pytest.approx(2 / 255)
        assert "max abs error 2 source units (0.007843 of the value range), within the bound 2 source units" in ev_text
    if case == "lossless":  # exact in both, at the documented cap
        assert res["max_abs_error"] == ev["max_abs_error_source"] == 0.0 and res["psnr_db"] == ev["psnr_db"] == 200.0
        assert "PSNR 200.00 dB, occupied 200.00 dB (200 dB is the cap: no error)" in ev_text
        assert "with the residual: PSNR 200.00 dB, occupied 200.00 dB (200 dB is the cap: no error)" in text
