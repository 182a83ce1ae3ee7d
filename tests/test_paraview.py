"""The ParaView reader (issue #22): the same algorithm class on plain VTK (in process, and through
the warpgauss command line as inside a ParaView without Warp), and in pvpython when Debian's
paraview is installed."""

from __future__ import annotations

import json
import os
import shlex
import shutil
import subprocess
import sys

import numpy as np
import pytest

import warpgauss
from warpgauss.readers.synthetic import generate

pytest.importorskip("vtkmodules")

CLI = f"{shlex.quote(sys.executable)} -c 'from warpgauss.cli.main import run; run()'"


@pytest.fixture(scope="module")
def model_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("pv") / "bubbles.wgs"
    vol = generate("bubbles", 20)
    m = warpgauss.encode(vol, budget=150, iterations=20, samples=256, device="cpu", self_test=False, format="full")
    m.header["transfer_function"] = {"colormap": "magma", "opacity": [[0.0, 0.0], [0.5, 0.2], [1.0, 1.0]]}  # no LUT: from the name
    m.save(path)
    return path


def _read(path, resolution, monkeypatch=None, cli=False, tf_file=None):
    from vtkmodules.util.numpy_support import vtk_to_numpy

    from warpgauss.paraview import WarpgaussReader

    if monkeypatch is not None:
        monkeypatch.setenv("WARPGAUSS_PARAVIEW_CLI", "1" if cli else "0")
        monkeypatch.setenv("WARPGAUSS_CLI", CLI)
    r = WarpgaussReader()
    r.SetFileName(str(path))
    r.SetResolution(resolution)
    if tf_file is not None:
        r.SetTransferFunctionFile(str(tf_file))
    r.SetDevice("cpu")
    r.Update()
    img, pts = r.GetOutputDataObject(0), r.GetOutputDataObject(1)
    return img, pts, vtk_to_numpy(img.GetPointData().GetScalars()), vtk_to_numpy(pts.GetPoints().GetData())


def test_the_reader_decodes_at_a_resolution_with_the_primitives_and_the_transfer_function(model_file, monkeypatch):
    from vtkmodules.util.numpy_support import vtk_to_numpy

    from warpgauss.format.export import primitive_arrays
    from warpgauss.paraview import transfer_function_points
    from warpgauss.render.transfer import from_header

    m = warpgauss.Model.load(model_file)
    img, pts, values, points = _read(model_file, 30, monkeypatch)
    assert img.GetDimensions() == (30, 30, 30)
    np.testing.assert_allclose(img.GetSpacing(), m.decoded_spacing((30, 30, 30)))
    np.testing.assert_allclose(img.GetOrigin(), m.decoded_origin((30, 30, 30)))
    np.testing.assert_array_equal(values, m.decode(shape_xyz=(30, 30, 30), device="cpu").ravel())  # x fastest, as VTK
    assert pts.GetNumberOfPoints() == pts.GetNumberOfVerts() == m.n == 150
    arrays = primitive_arrays(m)
    np.testing.assert_allclose(points, arrays["points"], rtol=1e-6)
    np.testing.assert_allclose(vtk_to_numpy(pts.GetPointData().GetArray("value")), arrays["value"], rtol=1e-6)
    fd = img.GetFieldData()
    assert fd.GetAbstractArray("warpgauss_colormap").GetValue(0) == "magma"
    rgb = vtk_to_numpy(fd.GetArray("warpgauss_rgb_points")).reshape(-1, 4)
    lo, hi = m.value_range
    assert rgb[0, 0] == pytest.approx(lo) and rgb[-1, 0] == pytest.approx(hi)
    np.testing.assert_allclose(rgb[-1, 1:], from_header(m.header).rgb[-1], atol=1e-6)  # magma's last colour
    want_rgb, want_op, _ = transfer_function_points(m.header, from_header(m.header).rgba)
    np.testing.assert_allclose(vtk_to_numpy(fd.GetArray("warpgauss_opacity_points")), want_op)
    _, _, native, _ = _read(model_file, 0, monkeypatch)
    assert native.size == int(np.prod(m.shape_xyz))  # 0: the model's own grid


def test_without_warp_the_reader_runs_the_command_line_and_reads_the_same(model_file, monkeypatch):
    img, pts, values, points = _read(model_file, 24, monkeypatch)
    img2, pts2, values2, points2 = _read(model_file, 24, monkeypatch, cli=True)
    assert img2.GetDimensions() == img.GetDimensions()
    np.testing.assert_allclose(img2.GetSpacing(), img.GetSpacing())
    np.testing.assert_allclose(img2.GetOrigin(), img.GetOrigin())
    np.testing.assert_array_equal(values2, values)
    np.testing.assert_allclose(points2, points, rtol=1e-6)
    assert img2.GetFieldData().GetArray("warpgauss_opacity_points") is not None


@pytest.mark.parametrize("cli", [False, True])
def test_an_update_extent_is_decoded_alone_as_the_whole_decodes_part(model_file, monkeypatch, cli):
    """A pipeline asking for a sub-extent (a view zoomed in, a piece of a parallel run) gets a region
    decode of just those voxels: the whole decode's values there, bit for bit, at the whole
    decode's origin and spacing, in process and through the command line's --box."""
    from vtkmodules.util.numpy_support import vtk_to_numpy

    from warpgauss.paraview import WarpgaussReader

    monkeypatch.setenv("WARPGAUSS_PARAVIEW_CLI", "1" if cli else "0")
    monkeypatch.setenv("WARPGAUSS_CLI", CLI)
    whole, _, values, _ = _read(model_file, 30, monkeypatch, cli=cli)
    r = WarpgaussReader()
    r.SetFileName(str(model_file))
    r.SetResolution(30)
    r.SetDevice("cpu")
    r.UpdateExtent((4, 17, 0, 9, 21, 29))
    img = r.GetOutputDataObject(0)
    assert img.GetExtent() == (4, 17, 0, 9, 21, 29)
    np.testing.assert_allclose(img.GetOrigin(), whole.GetOrigin(), rtol=1e-12)
    np.testing.assert_allclose(img.GetSpacing(), whole.GetSpacing(), rtol=1e-12)
    got = vtk_to_numpy(img.GetPointData().GetScalars()).reshape(9, 10, 14)
    np.testing.assert_array_equal(got, values.reshape(30, 30, 30)[21:30, 0:10, 4:18])


def test_the_colours_edited_in_the_browser_travel_to_paraview(model_file, tmp_path, monkeypatch, capsys):
    """TransferFunctionFile: the file warpgauss serve offers after an edit (Viewer.tf_json) replaces
    the header's transfer function in the field data, in process and through the command line
    alike (there parsed without warpgauss); the header's stays when it is empty; a bad file is
    refused in one line."""
    from vtkmodules.util.numpy_support import vtk_to_numpy

    from warpgauss.paraview import transfer_function_points
    from warpgauss.render.transfer import load_transfer_function
    from warpgauss.render.viewer import Viewer

    m = warpgauss.Model.load(model_file)
    v = Viewer([m], [str(model_file)], device="cpu")
    v.set_colors([(0.0, (0.1, 0.2, 0.9)), (0.6, (0.9, 0.9, 0.1)), (1.0, (0.8, 0.1, 0.1))])
    v.set_opacity([(0.0, 0.0), (0.35, 0.05), (1.0, 0.7)])
    tf_file = tmp_path / "view_tf.json"
    tf_file.write_text(v.tf_json())

    def points(img):
        fd = img.GetFieldData()
        return vtk_to_numpy(fd.GetArray("warpgauss_rgb_points")), vtk_to_numpy(fd.GetArray("warpgauss_opacity_points"))

    want_rgb, want_op, _ = transfer_function_points(m.header, load_transfer_function(tf_file, m.value_range).rgba, own=True)
    for cli in (False, True):
        img, _, _, _ = _read(model_file, 12, monkeypatch, cli=cli, tf_file=tf_file)
        rgb, op = points(img)
        np.testing.assert_allclose(rgb, want_rgb, atol=1e-9)
        np.testing.assert_allclose(op, want_op, atol=1e-9)
        assert img.GetFieldData().GetAbstractArray("warpgauss_colormap").GetValue(0) == "custom"
    assert np.asarray(want_op).reshape(-1, 4)[-1, 1] == pytest.approx(0.7)
    plain = _read(model_file, 12, monkeypatch)[0].GetFieldData()  # no file: the header's (magma, its own opacity)
    assert plain.GetAbstractArray("warpgauss_colormap").GetValue(0) == "magma"
    assert not np.allclose(vtk_to_numpy(plain.GetArray("warpgauss_opacity_points")), want_op)
    bad = tmp_path / "bad.json"
    bad.write_text('{"colormap": "magma"}')  # fine in process, not without warpgauss
    from warpgauss.paraview import WarpgaussReader

    monkeypatch.setenv("WARPGAUSS_PARAVIEW_CLI", "1")
    r = WarpgaussReader()
    r.SetFileName(str(model_file))
    r.SetTransferFunctionFile(str(bad))
    r.Update()
    assert "what warpgauss serve writes" in capsys.readouterr().out and r.GetOutputDataObject(0).GetNumberOfPoints() == 0


def test_a_bad_file_is_refused_with_a_message(tmp_path, monkeypatch, capsys):
    from warpgauss.paraview import WarpgaussReader

    bad = tmp_path / "x.wgs"
    bad.write_bytes(b"not a model at all, longer than the prefix")
    r = WarpgaussReader()
    r.SetFileName(str(bad))
    r.Update()
    assert "bad magic" in capsys.readouterr().out
    assert r.GetOutputDataObject(0).GetNumberOfPoints() == 0


PV_SCRIPT = r"""
import inspect  # Debian 12's ParaView 5.11 imports inspect.getargspec, gone in Python 3.11
inspect.getargspec = getattr(inspect, "getargspec", inspect.getfullargspec)
import importlib.util, json, sys
import numpy as np
from paraview.simple import LoadPlugin, GetActiveViewOrCreate, Show
from paraview import servermanager
plugin, model, out, tf_file = sys.argv[1:5]
LoadPlugin(plugin, ns=globals())
r = warpgaussmodel(FileName=model, Resolution=16, Device="cpu")
r.UpdatePipeline()
img = servermanager.Fetch(r)
if img.IsA("vtkMultiBlockDataSet"):
    img = img.GetBlock(0)
from vtkmodules.util.numpy_support import vtk_to_numpy
np.save(out + ".npy", vtk_to_numpy(img.GetPointData().GetScalars()))
default = str(Show(r, GetActiveViewOrCreate("RenderView")).GetPropertyValue("Representation"))
spec = importlib.util.spec_from_file_location("wg_pv", plugin)
mod = importlib.util.module_from_spec(spec); spec.loader.exec_module(mod)
disp = mod.apply_default_transfer_function(r)
from paraview.simple import GetColorTransferFunction
lut = GetColorTransferFunction(img.GetPointData().GetScalars().GetName())
edited = warpgaussmodel(FileName=model, Resolution=8, Device="cpu", TransferFunctionFile=tf_file)
edited.UpdatePipeline()
mod.apply_default_transfer_function(edited)
json.dump({"dims": list(img.GetDimensions()), "rgb_points": len(lut.RGBPoints), "representation": str(disp.GetPropertyValue("Representation")), "default": default, "edited_rgb_points": list(GetColorTransferFunction(img.GetPointData().GetScalars().GetName()).RGBPoints)}, open(out, "w"))
"""


@pytest.mark.skipif(
    shutil.which("pvpython") is None, reason="pvpython (Debian's paraview) is not installed; the plain-VTK tests cover the reader"
)
def test_the_plugin_in_pvpython(model_file, tmp_path):
    import warpgauss.paraview as plugin
    from warpgauss.paraview import file_transfer_function, read_header, transfer_function_points

    script = tmp_path / "drive.py"
    script.write_text(PV_SCRIPT)
    tf_file = tmp_path / "view_tf.json"  # as warpgauss serve writes it after an edit
    tf_file.write_text(
        json.dumps({"name": "warpgauss serve view", "colors": [[0, 0, 0, 1], [1, 1, 0.5, 0]], "opacity": [[0, 0], [1, 0.6]]})
    )
    out = tmp_path / "pv.json"
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME")}
    env.update(WARPGAUSS_CLI=CLI)
    r = subprocess.run(
        ["pvpython", str(script), plugin.PLUGIN, str(model_file), str(out), str(tf_file)],
        capture_output=True,
        text=True,
        env=env,
        timeout=300,
    )
    assert r.returncode == 0, r.stdout + r.stderr
    got = json.loads(out.read_text())
    # no LUT in this header: the colours come from ParaView's magma preset
    assert got["dims"] == [16, 16, 16] and got["representation"].strip("'") == "Volume" and got["rgb_points"] > 0
    assert got["default"].strip("'") == "Volume"  # the reader's hint: a model opens as a volume
    m = warpgauss.Model.load(model_file)
    np.testing.assert_array_equal(np.load(str(out) + ".npy"), m.decode(shape_xyz=(16, 16, 16), device="cpu").ravel())
    header = read_header(str(model_file))  # the edited colours reached ParaView's colour map (through the CLI path there)
    want, _, _ = transfer_function_points(header, file_transfer_function(str(tf_file), header), own=True)
    np.testing.assert_allclose(got["edited_rgb_points"], want, atol=1e-9)
