"""One encode configuration (warpgauss.encoding.driver.config): every warpgauss.encode argument has one
place in EncodeConfig and maps back, every path takes its settings from it, and an unknown
option is refused where it is given, in one line."""

from __future__ import annotations

import inspect

import pytest

import warpgauss
from warpgauss.encoding.allocate import AllocationConfig
from warpgauss.encoding.driver.config import FIELDS, NOT_SETTINGS, EncodeConfig
from warpgauss.encoding.refine import RefineConfig
from warpgauss.errors import WarpgaussError
from warpgauss.readers import ReadOptions

# a value for every setting that differs from its default
SAMPLE = {
    "budget": 1234,
    "ratio": 55.0,
    "file_bytes": 99_000,
    "format": "full",
    "compact": True,
    "seed": 7,
    "device": "cpu",
    "devices": "cpu,cpu",
    "preset": "fast",
    "iterations": 33,
    "samples": 512,
    "refine": RefineConfig(lr={"mu": 1e-3}),
    "target_psnr": 40.0,
    "plateau_db": 0.1,
    "self_test": False,
    "time_budget": 5.0,
    "allocation": AllocationConfig(scale_cap=3.0),
    "read": ReadOptions(stride=2),
    "example": "vortex",
    "example_size": 40,
    "checkpoint": "run.ckpt",
    "checkpoint_every": 10.0,
    "resume": True,
    "evaluate": False,
    "full_eval": True,
    "output": "out.wgs",
    "force": True,
    "analytic_output": "a.wgs",
    "bricks": "2x2x1",
    "halo": 3,
    "max_device_memory": "24GiB",
    "max_host_memory": "8GiB",
    "read_by_bricks": True,
    "volume_on_host": True,
    "max_error": 0.5,
    "max_error_rel": 0.01,
    "residual_psnr": 60.0,
    "warm_start": "previous",
    "motion": False,
}


def test_every_encode_argument_has_one_place_in_the_configuration():
    params = set(inspect.signature(warpgauss.encode).parameters)
    assert params - set(NOT_SETTINGS) == set(FIELDS)
    assert set(SAMPLE) == set(FIELDS)
    assert len({v for v in FIELDS.values()}) == len(FIELDS)  # no two arguments share a place


def test_every_encode_argument_is_described_once_in_full_and_once_in_a_line():
    """encode's docstring gives one line a keyword and points to docs/guide/options.md, which
    describes every keyword (issue #54: encode within 120 lines), with its command-line flags."""
    import re
    from pathlib import Path

    from warpgauss.encoding.driver.config import OPTIONS

    params = list(inspect.signature(warpgauss.encode).parameters)
    doc = inspect.getdoc(warpgauss.encode) or ""
    args = doc.split("Args:\n", 1)[1].split("\n\n", 1)[0].splitlines()
    assert [line.split(":", 1)[0].strip() for line in args] == params  # one line each, in order
    assert "(guide/options.md)" in doc
    page = (Path(__file__).resolve().parents[1] / "docs" / "guide" / "options.md").read_text()
    entries = dict(re.findall(r"^- \*\*`(\w+)`\*\*(.*?)(?=^- |^#|\Z)", page, re.M | re.S))
    assert sorted(entries) == sorted(params)
    for key, opt in OPTIONS.items():
        if key in entries:
            flags = [f for flag in opt.flags for f in flag.split("/")] or [f"--{key.replace('_', '-')}"]
            assert all(f"`{f}`" in entries[key].split(":", 1)[0] for f in flags), (key, flags)


def test_each_setting_maps_to_its_place_and_back():
    for name, value in SAMPLE.items():
        cfg = EncodeConfig.from_kwargs(**{name: value})
        assert cfg.get(name) is value or cfg.get(name) == value, name
        assert cfg.to_kwargs() == {name: value}, name  # nothing else moved off its default
    every = EncodeConfig.from_kwargs(**SAMPLE)
    assert every.to_kwargs() == SAMPLE
    assert EncodeConfig.from_kwargs(**every.to_kwargs()) == every
    assert set(EncodeConfig().to_kwargs(every=True)) == set(FIELDS) and EncodeConfig().to_kwargs() == {}
    assert every.replace(seed=1).seed == 1 and every.replace(seed=1).budget == every.budget
    # the groups: the budget is one place for N, ratio and bytes
    assert (every.budget.n, every.budget.ratio, every.budget.bytes) == (1234, 55.0, 99_000)
    assert every.reading.stride == 2 and every.bound.psnr == 60.0 and every.start.motion is False


def test_an_unknown_option_is_refused_where_it_is_given(tmp_path):
    with pytest.raises(WarpgaussError, match="unknown encode option itertions; the options are warpgauss.encode's keyword arguments"):
        EncodeConfig.from_kwargs(itertions=5)
    with pytest.raises(WarpgaussError, match="unknown encode options bogus, itertions"):
        EncodeConfig.from_kwargs(itertions=5, bogus=1)
    with pytest.raises(WarpgaussError, match="unknown encode option itertions"):
        warpgauss.Encoder(budget=10, itertions=5)  # at construction, not at the first call
    with pytest.raises(WarpgaussError, match="unknown encode option itertions"):
        warpgauss.encode_series([tmp_path / "a.npy"], budget=10, itertions=5)
    with pytest.raises(WarpgaussError, match="a series does not take output="):
        warpgauss.encode_series([tmp_path / "a.npy"], budget=10, output="x.wgs")


def test_the_ladder_takes_its_settings_from_the_configuration():
    """encode_ladder's arguments are encode's (the same names and defaults) besides its own."""
    ladder = inspect.signature(warpgauss.encode_ladder).parameters
    encode = inspect.signature(warpgauss.encode).parameters
    own = {"budgets", "output_pattern"}
    for name, p in ladder.items():
        if name in own:
            continue
        assert name in FIELDS or name in NOT_SETTINGS, name
        assert p.default == encode[name].default, name


def test_a_ladder_keeps_its_stop_rules_and_reading_through_the_configuration():
    from warpgauss.readers.synthetic import generate

    ms = warpgauss.encode_ladder(
        generate("vortex", 24), budgets=[40, 80], iterations=5, samples=128, device="cpu", self_test=False, format="full", target_psnr=90.0
    )
    assert [m.n for m in ms] == [40, 80]
    assert all(m.header["encoding"]["refinement"]["target_psnr"] == 90.0 for m in ms)


def test_a_series_keeps_its_stop_rules_from_the_command_line(tmp_path):
    """warpgauss encode 'GLOB' --target-psnr --plateau: every timestep's model was refined with them
    (the series path takes its settings from the one configuration the command line builds)."""
    import json

    import numpy as np
    from typer.testing import CliRunner

    from warpgauss.cli.main import app
    from warpgauss.readers.synthetic import generate_series

    for t, v in enumerate(generate_series("vortex", 16, 2)):
        np.save(tmp_path / f"t_{t}.npy", v)
    out = tmp_path / "s.wgs"
    args = ["encode", str(tmp_path / "t_*.npy"), "--budget", "40", "--iterations", "5", "--samples", "128", "--device", "cpu"]
    args += ["--no-self-test", "--format", "full", "--target-psnr", "95", "--plateau", "0.5", "-o", str(out), "--json"]
    r = CliRunner().invoke(app, args)
    assert r.exit_code == 0, r.output
    for row in json.loads(r.output)["series"]:
        refinement = warpgauss.Model.load(row["output"]).header["encoding"]["refinement"]
        assert refinement["target_psnr"] == 95.0 and refinement["plateau_db"] == 0.5


def test_every_setting_the_command_line_offers_comes_from_the_one_table():
    """warpgauss encode's options of the settings are OPTIONS' rows: flags, panel, help and the
    setting's own default; a value given there lands in EncodeConfig where the row says."""
    import typer

    from warpgauss.cli.encode import encode as command
    from warpgauss.cli.main import app
    from warpgauss.encoding.driver.config import FIELDS, OPTIONS, config_from_options, option_default

    click_cmd = typer.main.get_command(app).commands["encode"]
    params = {p.name: p for p in click_cmd.params}
    for key, opt in OPTIONS.items():
        assert key.split(".")[0] in FIELDS or key.startswith(("read.", "refine.")), key
        p = params[opt.param or key.rpartition(".")[2]]
        assert p.help == opt.help and p.rich_help_panel == opt.panel and p.default == option_default(key), key
        assert not opt.flags or set(opt.flags[0].split("/")[0:1]) <= set(p.opts) | set(p.secondary_opts), key
    assert callable(command)
    values = {k: option_default(k) for k in OPTIONS}
    cfg = config_from_options({**values, "refine.weights.cap": 2.5, "read.stride": 3, "self_test": True, "residual_psnr": 40.0})
    assert cfg.refinement.refine.weights.cap == 2.5 and cfg.reading.stride == 3 and cfg.refinement.self_test is False
    assert cfg.bound.psnr == 40.0 and cfg.seed == 0 and cfg.start.motion is True
