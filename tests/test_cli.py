"""The `warpgauss` command line: the issue's user journey, and one-line refusals of bad input."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest
from typer.testing import CliRunner

from warpgauss.cli.main import app

runner = CliRunner()


def cli(*args, cwd=None):
    old = os.getcwd()
    if cwd is not None:
        os.chdir(cwd)
    try:
        return runner.invoke(app, [str(a) for a in args])
    finally:
        os.chdir(old)


def assert_refused(result, pattern: str):
    """Exit code 2, one line on stderr matching the pattern, no traceback."""
    assert result.exit_code == 2, (result.exit_code, result.output)
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, result.stderr
    assert "Traceback" not in result.output
    assert pattern.lower() in lines[0].lower(), lines[0]


@pytest.fixture(scope="module")
def vortex_raw(tmp_path_factory):
    d = tmp_path_factory.mktemp("cli")
    r = cli("example", "vortex", "--size", "24", "-o", d / "vortex_24x24x24_float32.raw")
    assert r.exit_code == 0, r.output
    return d / "vortex_24x24x24_float32.raw"


def test_example_encode_info_decode_eval_journey(vortex_raw, tmp_path):
    assert vortex_raw.stat().st_size == 24**3 * 4
    model = tmp_path / "vortex.wgs"
    analytic = tmp_path / "analytic.wgs"
    r = cli(
        "encode",
        vortex_raw,
        "--budget",
        "300",
        "-o",
        model,
        "--device",
        "cpu",
        "--iterations",
        "40",
        "--format",
        "full",
        "--samples",
        "512",
        "--save-analytic",
        analytic,
    )
    assert r.exit_code == 0, r.output
    assert model.stat().st_size == analytic.stat().st_size == 48 * 300 + 4096  # 48 N + H, H one 4 KiB block
    rep = json.loads((tmp_path / "vortex.wgs.report.json").read_text())
    assert rep["budget"]["n"] == 300
    assert [s["stage"] for s in rep["stages"]] == ["P", "S1a", "S1b", "S1c", "S1d", "S1e", "S1x", "S2", "EV", "S3"]
    assert all(s["seconds"] >= 0 and s["host_peak_bytes"] > 0 for s in rep["stages"])
    assert rep["psnr_db"] > 15 and rep["warp_version"] and rep["device"] == "cpu"
    ev = rep["evaluation"]
    assert ev["final"]["psnr_db"] > ev["analytic"]["psnr_db"] + 1.0  # even 40 iterations help
    assert rep["refinement"]["iterations"] == 40 and rep["refinement"]["self_test"]["passed"]
    assert len(rep["refinement"]["loss_history"]) >= 1

    r = cli("info", model, "--json")
    assert r.exit_code == 0, r.output
    info = json.loads(r.stdout)
    assert info["n"] == 300 and info["bytes"] == model.stat().st_size
    assert info["compression_ratio"] == pytest.approx(24**3 * 4 / model.stat().st_size)

    vti = tmp_path / "decoded.vti"
    r = cli("decode", model, "-o", vti, "--device", "cpu")
    assert r.exit_code == 0, r.output
    import pyvista as pv

    grid = pv.read(vti)
    assert tuple(grid.dimensions) == (24, 24, 24)
    decoded = np.asarray(grid.point_data[grid.array_names[0]]).reshape((24, 24, 24), order="F").transpose(2, 1, 0)
    from warpgauss.format.model import Model

    np.testing.assert_allclose(decoded, Model.load(model).decode(device="cpu"), rtol=1e-6)

    r = cli("eval", model, vortex_raw, "--json", "--device", "cpu")
    assert r.exit_code == 0, r.output
    ev = json.loads(r.stdout)
    assert ev["n"] == 300
    assert ev["psnr_db"] == pytest.approx(rep["psnr_db"], abs=1e-9)  # same evaluator, same points


def test_ratio_gives_the_spec_budget(vortex_raw, tmp_path):
    model = tmp_path / "r.wgs"
    r = cli("encode", vortex_raw, "--ratio", "5", "-o", model, "--device", "cpu", "--json", "--iterations", "0", "--format", "full")
    assert r.exit_code == 0, r.output
    rep = json.loads(r.stdout)
    expected = int(np.floor((24**3 * 4 / 5 - 4096) / 48))
    assert rep["budget"]["n"] == expected
    assert model.stat().st_size == 48 * expected + 4096


def test_bad_input_is_refused_in_one_line(tmp_path, vortex_raw):
    cases = []
    cases.append((["encode", tmp_path / "missing.raw"], "no such file"))
    bad = tmp_path / "vol_10x10x10_float32.raw"
    bad.write_bytes(b"\0" * 1000)
    cases.append((["encode", bad, "--budget", "5"], "4000"))
    flat = tmp_path / "flat.npy"
    np.save(flat, np.zeros((8, 8), np.float32))
    cases.append((["encode", flat, "--budget", "5"], "2D"))
    nan = tmp_path / "nan.npy"
    np.save(nan, np.full((8, 8, 8), np.nan, np.float32))
    cases.append((["encode", nan, "--budget", "5"], "no finite value"))
    const = tmp_path / "const.npy"
    np.save(const, np.full((8, 8, 8), 2.0, np.float32))
    cases.append((["encode", const, "--budget", "5"], "constant"))
    cases.append((["encode", vortex_raw, "--budget", "0"], "--budget must be a positive whole number"))
    cases.append((["encode", vortex_raw, "--budget", "100000"], "N_max"))
    odd = tmp_path / "volume.xyz"
    odd.write_bytes(b"abc")
    cases.append((["encode", odd, "--budget", "5"], "extension"))
    cases.append((["info", tmp_path / "nope.wgs"], "no such"))
    garbage = tmp_path / "garbage.wgs"
    garbage.write_bytes(b"x" * 64)
    cases.append((["info", garbage], "not a warpgauss model"))
    for args, pattern in cases:
        out = tmp_path / "out.wgs"
        r = cli(*args, "-o", out) if args[0] == "encode" else cli(*args)
        assert_refused(r, pattern)
        assert not out.exists()
    assert not any(p.name.startswith(".out") for p in tmp_path.iterdir())  # no temp files left


def test_existing_output_is_not_overwritten(vortex_raw, tmp_path):
    out = tmp_path / "m.wgs"
    out.write_bytes(b"precious")
    r = cli("encode", vortex_raw, "--budget", "10", "-o", out)
    assert_refused(r, "already exists")
    assert out.read_bytes() == b"precious"


def test_a_second_encode_to_the_same_name_names_the_file_the_user_gave(vortex_raw, tmp_path):
    """Both the model and its report exist (the README's tour run twice): the refusal names the
    model file the user typed, not the report beside it."""
    out = tmp_path / "scan.wgs"
    out.write_bytes(b"earlier model")
    (tmp_path / "scan.wgs.report.json").write_text("{}")
    r = cli("encode", vortex_raw, "--budget", "10", "-o", out)
    assert_refused(r, f"{out} already exists")
    assert out.read_bytes() == b"earlier model"


def test_infeasible_budget_is_refused_before_warp_starts(tmp_path):
    """A 256^3 volume with an impossible budget: refused fast, Warp never imported."""
    v = np.zeros((256, 256, 256), np.uint8)
    v[100:110, 100:110, 100:110] = 200
    path = tmp_path / "sparse_256x256x256_uint8.raw"
    v.tofile(path)
    code = (
        "import sys, time; t = time.perf_counter();"
        "from warpgauss.cli.main import app;"
        f"sys.argv = ['warpgauss', 'encode', {str(path)!r}, '--budget', '5000', '-o', {str(tmp_path / 'x.wgs')!r}];"
        "\ntry:\n    app()\nexcept SystemExit as e:\n    code = e.code\n"
        "print('WARP' if 'warp' in sys.modules else 'NOWARP', code, time.perf_counter() - t)"
    )
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    tag, code, seconds = p.stdout.split()
    assert tag == "NOWARP" and code == "2"
    # 1000 occupied voxels, 488 of them on the cube's faces with a non-zero gradient:
    # N_max = floor(min(488 / 0.55, 1000 / 0.45)) = 887
    assert "N_max = 887" in p.stderr
    assert float(seconds) < 5.0  # measured well under 1 s; the bound only guards against heavy work


def test_encode_builtin_example_writes_model_and_report(tmp_path):
    r = cli(
        "encode",
        "--example",
        "bubbles",
        "--size",
        "32",
        "--budget",
        "200",
        "--device",
        "cpu",
        "--iterations",
        "0",
        "--format",
        "full",
        cwd=tmp_path,
    )
    assert r.exit_code == 0, r.output
    assert (tmp_path / "bubbles.wgs").stat().st_size == 48 * 200 + 4096
    rep = json.loads((tmp_path / "bubbles.wgs.report.json").read_text())
    assert rep["input"]["example"] == "bubbles" and rep["budget"]["n"] == 200
    assert 0.01 < rep["structure"]["occupancy"] < 0.05


def test_unexpected_failure_is_one_line_and_debug_shows_the_traceback(tmp_path, monkeypatch):
    import warpgauss.format.model

    def broken(*a, **k):
        raise RuntimeError("boom\nsecond line")

    monkeypatch.setattr(warpgauss.format.model.Model, "load_header", broken)
    path = tmp_path / "m.wgs"
    path.write_bytes(b"x")
    res = CliRunner().invoke(app, ["info", str(path)])
    assert res.exit_code == 2
    assert "internal error: RuntimeError: boom (rerun with --debug" in res.output
    assert "second line" not in res.output and "Traceback" not in res.output
    monkeypatch.delenv("WARPGAUSS_DEBUG", raising=False)
    res = CliRunner().invoke(app, ["--debug", "info", str(path)])
    os.environ.pop("WARPGAUSS_DEBUG", None)  # --debug sets it for the process
    assert isinstance(res.exception, RuntimeError)  # propagated with its traceback


def test_encode_help_groups_options_in_panels():
    """The options sit under Input, Budget and format, Error bound, Refinement, Loss weights, Run control and
    Output, in that order, each option under its own panel."""
    r = CliRunner().invoke(app, ["encode", "--help"], env={"COLUMNS": "200"})
    assert r.exit_code == 0, r.output
    heads = [line.rstrip(":") for line in r.output.splitlines() if line and not line.startswith(" ") and line.endswith(":")]
    assert heads == [
        "Arguments",
        "Input",
        "Budget and format",
        "Error bound",
        "Refinement",
        "Loss weights",
        "Bricks and cluster",
        "Run control",
        "Output",
        "Time series",
        "Other options",
    ]
    sections = r.output.split("\n\n")
    where = {s.splitlines()[0].rstrip(":"): s for s in sections if s and s.splitlines()[0].endswith(":")}
    assert "--w-smooth " in where["Loss weights"] and "--bytes" in where["Budget and format"] and "--config" in where["Run control"]
    assert "--samples" in where["Refinement"] and "--shape" in where["Input"] and "--report" in where["Output"]


def test_config_file_sets_options_and_the_report_repeats_the_run(tmp_path):
    """A TOML file sets any option (the command line wins); the report records the resolved
    options, and --config REPORT gives the same model bit for bit (same seed, same device)."""
    cfg = tmp_path / "run.toml"
    cfg.write_text(
        'example = "vortex"\nsize = 20\nbudget = 40\niterations = 50\ndevice = "cpu"\nno-self-test = true\nw-smooth = 0.02\nformat = "full"\n'
    )
    out = tmp_path / "a.wgs"
    r = CliRunner().invoke(app, ["encode", "--config", str(cfg), "--iterations", "4", "-o", str(out)])
    assert r.exit_code == 0, r.output
    rep = json.loads((tmp_path / "a.wgs.report.json").read_text())
    assert rep["config"]["iterations"] == 4 and rep["config"]["w-smooth"] == 0.02 and rep["config"]["budget"] == 40
    from warpgauss.format.model import Model

    assert rep["refinement"]["iterations"] == 4 and Model.load(out).header["encoding"]["refinement"]["weights"]["smooth"] == 0.02
    assert "force" not in rep["config"]  # a repeat must ask again to overwrite
    r = CliRunner().invoke(app, ["encode", "--config", str(tmp_path / "a.wgs.report.json")])
    assert r.exit_code == 2 and "exists" in r.output  # the report names a.wgs: not overwritten
    again = tmp_path / "b.wgs"
    r = CliRunner().invoke(app, ["encode", "--config", str(tmp_path / "a.wgs.report.json"), "-o", str(again)])
    assert r.exit_code == 0, r.output
    np.testing.assert_array_equal(Model.load(out).params, Model.load(again).params)


@pytest.mark.parametrize(
    "text, message",
    [
        ("ratioo = 5\n", "unknown option 'ratioo'"),
        ("ratio = [\n", "not valid TOML"),
    ],
)
def test_bad_config_file_is_refused_in_one_line(tmp_path, text, message):
    cfg = tmp_path / "bad.toml"
    cfg.write_text(text)
    out = tmp_path / "x.wgs"
    r = CliRunner().invoke(app, ["encode", "--example", "vortex", "--size", "16", "--config", str(cfg), "-o", str(out)])
    assert r.exit_code == 2 and message in r.output and len(r.output.strip().splitlines()) == 1, r.output
    assert not out.exists()
    r = CliRunner().invoke(app, ["encode", "--example", "vortex", "--config", str(tmp_path / "missing.toml")])
    assert r.exit_code == 2 and "no such configuration file" in r.output


def test_a_value_of_the_wrong_type_is_refused_in_one_line_naming_where_it_came_from(tmp_path):
    """A --config file's value of the wrong type, or a non-integer --bytes, printed click's usage
    block; now one line naming the file and key, or the option (#34)."""
    bad = tmp_path / "bad.toml"
    bad.write_text('ratio = "abc"\n')
    res = CliRunner().invoke(app, ["encode", "--config", str(bad), "--example", "vortex", "--size", "16", "-o", str(tmp_path / "c.wgs")])
    lines = res.output.strip().splitlines()
    assert res.exit_code == 2 and len(lines) == 1 and f"{bad}: ratio = 'abc'" in lines[0] and "Usage" not in res.output
    res = CliRunner().invoke(app, ["encode", "--example", "vortex", "--size", "16", "--bytes", "1.5", "-o", str(tmp_path / "c.wgs")])
    lines = res.output.strip().splitlines()
    assert res.exit_code == 2 and len(lines) == 1 and "'--bytes'" in lines[0] and "Usage" not in res.output
    assert not (tmp_path / "c.wgs").exists()


def test_the_summary_says_how_a_coded_file_met_its_size(tmp_path):
    """One sentence on the size by default; with --verbose the report's coded_choice, printed for
    people: the sizing, the re-plan and the rate control, in words, without result-file names."""
    res = CliRunner().invoke(
        app,
        [
            "encode",
            "--verbose",
            "--example",
            "vortex",
            "--size",
            "32",
            "--ratio",
            "20",
            "--iterations",
            "10",
            "--samples",
            "256",
            "--device",
            "cpu",
            "-o",
            str(tmp_path / "v.wgs"),
        ],
    )
    assert res.exit_code == 0, res.output
    size = [line for line in res.stdout.splitlines() if line.startswith("size: N ")]
    assert len(size) == 1 and "rate control:" in size[0] and "benchmarks/" not in size[0]
    n = int(size[0].split()[2].replace(",", ""))
    res = CliRunner().invoke(app, ["encode", "--example", "vortex", "--size", "32", "--ratio", "20", "--iterations", "10",
                                   "--samples", "256", "--device", "cpu", "-o", str(tmp_path / "w.wgs")])  # fmt: skip
    assert res.exit_code == 0, res.output
    short = [line for line in res.stdout.splitlines() if line.startswith("size: ")]
    assert short == [f"size: {n:,} Gaussians on the grids their accuracy needs fill the budget (--verbose: how they were chosen)"]


def test_encode_and_info_speak_to_people_and_verbose_shows_the_rest(vortex_raw, tmp_path):
    """#34: the default encode output is a line per phase in words and a summary (N, bytes, ratio,
    PSNR, time, the files), no stage codes, no stage table, no paragraphs on what was skipped;
    --verbose adds them. info prints rows, not a Python dict; --verbose lists every setting."""
    out = tmp_path / "v.wgs"
    args = ["encode", str(vortex_raw), "--budget", "80", "--iterations", "5", "--samples", "256", "--device", "cpu", "-o", str(out)]
    r = CliRunner().invoke(app, args)
    assert r.exit_code == 0, r.output
    text = r.stdout
    for code in ("S1a", "S1x", "S2 ", "stage", "skipped "):
        assert code not in text, (code, text)
    assert "80 Gaussians" in text and "compression" in text and "PSNR" in text and "time:" in text
    assert f"model: {out}" in text and "report:" in text
    for words in ("read the volume", "place the Gaussians", "refine", "measure the accuracy", "write the model"):
        assert any(line.strip().startswith(words) and line.rstrip().endswith(" s") for line in r.stderr.splitlines()), (words, r.stderr)
    r = CliRunner().invoke(app, [*args, "--force", "--verbose"])
    assert r.exit_code == 0, r.output
    assert "S1a" in r.stdout and "device peak" in r.stdout

    r = CliRunner().invoke(app, ["info", str(out)])
    assert r.exit_code == 0, r.output
    assert "{" not in r.stdout and "80," in r.stdout and "24 x 24 x 24" in r.stdout
    r = CliRunner().invoke(app, ["info", str(out), "--verbose"])
    assert r.exit_code == 0 and "encoding.refinement.lr " in r.stdout and "{" not in r.stdout, r.output


def test_every_stage_an_encode_records_has_a_phase_in_words():
    """The progress lines name phases, never stage codes: every stage code the driver records
    (found in its source) maps to words, the longest prefix winning (bricks' S1-S2b is not S1)."""
    import re
    from pathlib import Path

    from warpgauss.core.profiling import PHASES, phase_of

    root = Path(__file__).resolve().parents[1] / "warpgauss"
    codes = {m for f in root.rglob("*.py") for m in re.findall(r'stage\(\s*"([A-Za-z0-9-]+)"', f.read_text())}
    assert {"P", "S1a", "S2", "EV", "S3", "S1-S2b"} <= codes, codes
    words = {w for _, w in PHASES}
    for code in codes:
        assert phase_of(code) in words, code
    assert phase_of("S1-S2b") != phase_of("S1a")


def test_a_report_repeats_the_run_from_another_folder(vortex_raw, tmp_path):
    """#34: --config REPORT found the input only from the folder the first run started in: the
    report's paths are relative to the report, and a config file's relative paths to the file."""
    import shutil

    a, b = tmp_path / "a", tmp_path / "b"
    (a / "data").mkdir(parents=True)
    b.mkdir()
    shutil.copy(vortex_raw, a / "data" / vortex_raw.name)
    (a / "out").mkdir()
    r = cli("encode", f"data/{vortex_raw.name}", "--budget", "60", "--iterations", "4", "--device", "cpu", "-o", "out/m.wgs", cwd=a)
    assert r.exit_code == 0, r.output
    report = a / "out" / "m.wgs.report.json"
    cfg = json.loads(report.read_text())["config"]
    assert cfg["input"] == f"../data/{vortex_raw.name}" and cfg["output"] == "m.wgs"
    r = cli("encode", "--config", report, cwd=b)
    assert r.exit_code == 2 and "exists" in r.output  # the same output, found from b: not overwritten
    r = cli("encode", "--config", report, "-o", "again.wgs", cwd=b)
    assert r.exit_code == 0, r.output
    from warpgauss.format.model import Model

    np.testing.assert_array_equal(Model.load(a / "out" / "m.wgs").params, Model.load(b / "again.wgs").params)


def test_example_writes_a_series_that_encode_takes_into_a_folder(tmp_path):
    """#34: no command wrote an example series, and -o DIR (an existing folder) wrote DIR_000.wgs
    beside it: example --steps writes one file a timestep (names checked first), and a series
    encoded with -o FOLDER lands inside it."""
    series = tmp_path / "run"
    series.mkdir()
    r = cli("example", "vortex", "--size", "12", "--steps", "3", "-o", series)
    assert r.exit_code == 0, r.output
    files = sorted(p.name for p in series.iterdir())
    assert files == [f"vortex_{t:03d}_12x12x12_float32.raw" for t in range(3)]
    from warpgauss.readers.synthetic import generate_series

    want = list(generate_series("vortex", 12, steps=3))
    for t, name in enumerate(files):
        np.testing.assert_array_equal(np.fromfile(series / name, np.float32).reshape(12, 12, 12), want[t])
    assert_refused(cli("example", "vortex", "--size", "12", "--steps", "3", "-o", tmp_path / "x.raw"), "holding {t}")
    assert_refused(cli("example", "vortex", "--size", "12", "--steps", "3", "-o", series), "already exists")
    models = tmp_path / "models"
    models.mkdir()
    r = cli("encode", str(series / "vortex_*_12x12x12_float32.raw"), "--budget", "20", "--iterations", "2", "--device", "cpu", "-o", models)
    assert r.exit_code == 0, r.output
    assert sorted(p.name for p in models.glob("*.wgs")) == [f"step_{t:03d}.wgs" for t in range(3)]
    assert not list(tmp_path.glob("models_*"))


def test_key_frames_are_described_alike_in_help_and_docs():
    """#34: commands.md and --help described the key-frame rule differently."""
    from pathlib import Path

    from typer.main import get_command

    rule = "best warm PSNR since the chain's last cold timestep"
    helptext = next(p.help for p in get_command(app).commands["encode"].params if p.name == "keyframe_drift")
    root = Path(__file__).resolve().parents[1]
    flat = {name: " ".join((root / name).read_text().split()) for name in ("docs/guide/commands.md", "docs/guide/python.md")}
    assert rule in helptext
    for name, text in flat.items():
        assert rule in text, name


# how `warpgauss encode`'s options reach warpgauss.encode: the same name, another name (this
# table), a part of a settings object, or a command-line matter; a new option on either side must
# be placed here, so that none is dropped on the way (#33)
CLI_TO_API = {
    "input": "source",
    "size": "example_size",
    "fmt": "format",
    "no_self_test": "self_test",
    "plateau": "plateau_db",
    "save_analytic": "analytic_output",
    "psnr": "residual_psnr",
    # parts of the settings objects encode takes
    "lr": "refine",
    "w_value_empty": "refine",
    "w_density": "refine",
    "w_smooth": "refine",
    "w_smooth_final": "refine",
    "w_anchor": "refine",
    "w_aniso": "refine",
    "w_cap": "refine",
    "stride": "read",
    "shape": "read",
    "dtype": "read",
    "endian": "read",
    "dataset": "read",
    "variable": "read",
    "fill_value": "read",
    "workers": "client",
    "scheduler": "client",
}
CLI_ONLY = {
    "ctx",
    "ladder",
    "report",
    "as_json",
    "verbose",
    "config",
    "cold",
    "warm_iterations",
    "keyframe_drift",
}  # ladder/series paths, output
API_ONLY = {
    "allocation",
    "evaluate",
    "on_bricks",
    "on_progress",
    "on_stage",
    "on_stats",
    "progress",
    "session",
    "warm_start",
}  # Python callers


def test_every_command_line_option_maps_to_the_api_and_back():
    import inspect

    import warpgauss
    from warpgauss.cli.encode import encode as cli_encode

    cli = set(inspect.signature(cli_encode).parameters)
    api = set(inspect.signature(warpgauss.encode).parameters)
    mapped = {CLI_TO_API.get(p, p) for p in cli - CLI_ONLY}
    assert mapped - api == set(), sorted(mapped - api)  # every option reaches an encode argument
    assert api - mapped == API_ONLY, sorted((api - mapped) ^ API_ONLY)  # and every argument has an option or is for Python


def test_an_error_line_shows_bracketed_text_as_given(tmp_path):
    """Error lines went through rich markup, which swallowed text such as '[b]' in the value quoted."""
    res = CliRunner().invoke(
        app, ["encode", "--example", "vortex", "--size", "16", "--budget", "10", "--bricks", "[b]2x2x2", "-o", str(tmp_path / "b.wgs")]
    )
    assert res.exit_code == 2 and "'[b]2x2x2'" in res.output, res.output


def test_a_raw_name_must_say_the_shape_and_dtype_it_holds(tmp_path):
    """A .raw holds no shape: `example --size 48 -o vortex_128x128x128_float32.raw` wrote a 48^3
    volume the next command could not read; now the name is refused in one line with the name
    that fits, before anything is written, and a name without the tail is refused the same way."""
    wrong = tmp_path / "vortex_128x128x128_float32.raw"
    r = cli("example", "vortex", "--size", "12", "-o", wrong)
    assert_refused(r, "says 128x128x128 float32 but the volume is 12x12x12 float32; name it vortex_12x12x12_float32.raw")
    assert not wrong.exists()
    bare = tmp_path / "out.raw"
    assert_refused(cli("example", "vortex", "--size", "12", "-o", bare), "name it out_12x12x12_float32.raw")
    assert not bare.exists()
    right = tmp_path / "vortex_12x12x12_float32.raw"
    assert cli("example", "vortex", "--size", "12", "-o", right).exit_code == 0 and right.stat().st_size == 4 * 12**3


def test_decode_to_a_raw_name_without_its_shape_is_refused_before_the_decode(vortex_raw, tmp_path):
    model = tmp_path / "m.wgs"
    assert cli("encode", vortex_raw, "--budget", "10", "--iterations", "3", "-o", model).exit_code == 0
    bare = tmp_path / "out.raw"
    assert_refused(cli("decode", model, "-o", bare, "--shape", "8x9x10"), "name it out_8x9x10_float32.raw")
    assert not bare.exists()
    named = tmp_path / "out_8x9x10_float32.raw"
    assert cli("decode", model, "-o", named, "--shape", "8x9x10").exit_code == 0 and named.stat().st_size == 4 * 8 * 9 * 10


def test_a_run_stopped_at_its_target_says_the_iterations_it_ran(vortex_raw, tmp_path):
    """--target-psnr reached early: the summary says "100 of 300 iterations", as the report's
    iterations_done, where it said 300 beside a line that skipped 100-300 (issue #57 item 4)."""
    import json

    out = tmp_path / "t.wgs"
    r = cli("encode", vortex_raw, "--budget", "40", "--iterations", "300", "--samples", "256", "--target-psnr", "16", "-o", out)
    assert r.exit_code == 0, r.output
    rep = json.loads((tmp_path / "t.wgs.report.json").read_text())["refinement"]
    assert rep["iterations_done"] < rep["iterations"] == 300
    assert f"refinement: {rep['iterations_done']} of 300 iterations x" in r.stdout
