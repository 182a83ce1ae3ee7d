"""Transfer functions: named colormaps, opacity curves, our JSON, ParaView exports (checked against VTK)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from warpgauss.errors import WarpgaussError
from warpgauss.format.model import default_transfer_function
from warpgauss.render.transfer import (
    LUT_SIZE,
    colormap,
    colormap_names,
    from_header,
    load_transfer_function,
    make_transfer_function,
    parse_opacity,
    resolve_transfer_function,
)

X = np.linspace(0.0, 1.0, LUT_SIZE)


def test_named_colormaps():
    assert {"viridis", "magma", "coolwarm", "grayscale", "inferno", "plasma", "cividis", "turbo"} <= set(colormap_names())
    v = colormap("viridis")
    assert v.shape == (LUT_SIZE, 3)
    np.testing.assert_allclose(v[0], np.array([68, 1, 84]) / 255, atol=1 / 255)  # viridis' dark purple
    np.testing.assert_allclose(v[-1], np.array([253, 231, 37]) / 255, atol=1 / 255)  # ... to yellow
    np.testing.assert_allclose(colormap("Viridis_r"), v[::-1])
    np.testing.assert_allclose(colormap("gray"), np.repeat(X[:, None], 3, axis=1), atol=1e-12)
    mid = colormap("coolwarm")[LUT_SIZE // 2]
    assert abs(mid[0] - mid[2]) < 0.05 and mid.min() > 0.8  # diverging: light grey in the middle
    with pytest.raises(WarpgaussError, match="unknown colormap"):
        colormap("rainbow-ish")


def test_opacity_curves():
    assert parse_opacity("linear") == [(0.0, 0.0), (1.0, 1.0)]
    assert parse_opacity("0.25") == [(0.0, 0.25), (1.0, 0.25)]
    assert parse_opacity("1:1, 0:0 ,0.5:0.1") == [(0.0, 0.0), (0.5, 0.1), (1.0, 1.0)]
    tf = make_transfer_function("magma", "0:0,0.4:0,1:1")
    np.testing.assert_allclose(tf.opacity, np.clip((X - 0.4) / 0.6, 0, 1), atol=1e-6)
    np.testing.assert_allclose(tf([0.0, 0.7, 2.0])[:, 3], [0.0, 0.5, 1.0], atol=2e-3)  # clamped beyond 1
    for bad in ("0:0,1", "a:b", "0:2", "", "0:nan"):
        with pytest.raises(WarpgaussError):
            parse_opacity(bad)


def test_header_default_and_overrides():
    h = {"transfer_function": default_transfer_function(), "values": {"min": -2.0, "max": 6.0}}
    tf = from_header(h)
    lut = np.frombuffer(bytes.fromhex(h["transfer_function"]["lut_rgba8"]), np.uint8).reshape(-1, 4) / 255.0
    np.testing.assert_allclose(tf.rgb, lut[:, :3], atol=1e-6)
    np.testing.assert_allclose(tf.opacity, X, atol=1e-6)  # the header's opacity points: a linear ramp
    tf2 = resolve_transfer_function(h, colormap_name="grayscale", opacity="0:0,0.5:1")
    np.testing.assert_allclose(tf2.rgb[:, 0], X, atol=1e-6)
    assert tf2.opacity[LUT_SIZE // 2 + 1] == pytest.approx(1.0)
    assert from_header({}).name == "viridis"  # no stored TF: viridis, linear


def test_our_json(tmp_path):
    p = tmp_path / "tf.json"
    p.write_text(json.dumps({"colormap": "magma", "opacity": [[0.2, 0.0], [1.0, 0.8]]}))
    tf = load_transfer_function(p)
    np.testing.assert_allclose(tf.rgb, colormap("magma"), atol=1e-6)
    assert tf.opacity[0] == 0 and tf.opacity[-1] == pytest.approx(0.8)
    p.write_text(json.dumps({"colors": [[0, 0, 0, 1], [1, 1, 0, 0]], "opacity": [[0, 0.5], [10, 0.5]], "space": "data"}))
    tf = load_transfer_function(p, value_range=(0.0, 10.0))  # colour points at data 0 and 1 -> normalised 0 and 0.1
    np.testing.assert_allclose(tf.rgb[-1], [1, 0, 0], atol=1e-6)
    np.testing.assert_allclose(tf.rgb[0], [0, 0, 1], atol=1e-6)
    np.testing.assert_allclose(tf.opacity, 0.5, atol=1e-6)
    for doc, msg in [
        ({"colour": "red"}, "unknown key"),
        ({"colors": [[0, 1, 1]]}, "colors"),
        ({"opacity": [[0, 2]]}, "opacities"),
        ({"space": "log"}, "space"),
        ([1, 2], "ParaView"),
    ]:
        p.write_text(json.dumps(doc))
        with pytest.raises(WarpgaussError, match=msg):
            load_transfer_function(p)
    p.write_text("{not json")
    with pytest.raises(WarpgaussError, match="not a JSON"):
        load_transfer_function(p)


@pytest.mark.parametrize("space", ["RGB", "Lab", "Diverging", "HSV"])
def test_paraview_export_matches_vtk(tmp_path, space):
    """A ParaView colormap/opacity export gives the colours vtkColorTransferFunction and the opacity
    vtkPiecewiseFunction give (interpolation space, midpoints, sharpness)."""
    from vtkmodules.vtkCommonDataModel import vtkPiecewiseFunction
    from vtkmodules.vtkRenderingCore import vtkColorTransferFunction

    rgb_points = [0.0, 0.23, 0.299, 0.754, 0.3, 0.865, 0.865, 0.865, 1.0, 0.706, 0.016, 0.15]
    points = [0.0, 0.0, 0.5, 0.0, 0.4, 0.2, 0.25, 0.6, 1.0, 0.9, 0.5, 0.0]
    p = tmp_path / "pv.json"
    p.write_text(json.dumps([{"ColorSpace": space, "Name": "test", "NanColor": [1, 1, 0], "RGBPoints": rgb_points, "Points": points}]))
    tf = load_transfer_function(p)
    ctf = vtkColorTransferFunction()
    getattr(ctf, f"SetColorSpaceTo{space}")()
    for k in range(0, len(rgb_points), 4):
        ctf.AddRGBPoint(*rgb_points[k : k + 4])
    pwf = vtkPiecewiseFunction()
    for k in range(0, len(points), 4):
        pwf.AddPoint(*points[k : k + 4])
    np.testing.assert_allclose(tf.rgb, [ctf.GetColor(float(x)) for x in X], atol=1e-4)
    np.testing.assert_allclose(tf.opacity, [pwf.GetValue(float(x)) for x in X], atol=1e-6)


def test_paraview_ranges(tmp_path):
    """Points within the model's value range are data units; a preset's own range is stretched over it."""
    p = tmp_path / "pv.json"
    p.write_text(json.dumps({"Name": "d", "RGBPoints": [2.0, 0, 0, 0, 4.0, 1, 1, 1]}))
    tf = load_transfer_function(p, value_range=(0.0, 8.0))  # data units: black up to 0.25, white from 0.5
    assert tf.rgb[:60].max() == 0 and tf.rgb[130:].min() == pytest.approx(1.0)
    tf = load_transfer_function(p, value_range=(10.0, 20.0))  # outside: a preset, stretched over [0, 1]
    np.testing.assert_allclose(tf.rgb[:, 0], X, atol=1e-6)
    p.write_text(json.dumps([{"Name": "cat", "IndexedColors": [1, 0, 0]}]))
    with pytest.raises(WarpgaussError, match="no ParaView colormap"):
        load_transfer_function(p)


def test_cli_render_with_transfer_function_files(cpu, tmp_path):
    """--tf takes our JSON and a ParaView export; both render."""
    import warpgauss
    from warpgauss.cli.main import app

    model = warpgauss.encode(example="bubbles", example_size=24, budget=300, iterations=0, device=cpu, evaluate=False)
    model.save(tmp_path / "b.wgs")
    ours = tmp_path / "ours.json"
    ours.write_text(json.dumps({"colormap": "inferno", "opacity": [[0, 0], [0.2, 0], [1, 1]]}))
    pv = tmp_path / "pv.json"
    pv.write_text(
        json.dumps([{"ColorSpace": "Diverging", "Name": "Cool to Warm", "RGBPoints": [0, 0.23, 0.299, 0.754, 1, 0.706, 0.016, 0.15]}])
    )
    runner = CliRunner()
    for f in (ours, pv):
        out = tmp_path / f"{f.stem}.png"
        r = runner.invoke(app, ["render", str(tmp_path / "b.wgs"), "-o", str(out), "--tf", str(f), "--size", "24", "--device", cpu])
        assert r.exit_code == 0, r.output
        assert out.stat().st_size > 0
    bad = tmp_path / "bad.json"
    bad.write_text("[]")
    r = runner.invoke(app, ["render", str(tmp_path / "b.wgs"), "-o", str(tmp_path / "x.png"), "--tf", str(bad), "--device", cpu])
    assert r.exit_code == 2 and "ParaView" in r.stderr and not (tmp_path / "x.png").exists()
