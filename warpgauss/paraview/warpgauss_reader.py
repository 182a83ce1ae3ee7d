"""A ParaView reader for ``.wgs`` models (load this file with Tools > Manage Plugins > Load New;
``python -c "import warpgauss.paraview as p; print(p.PLUGIN)"`` prints its path).

Opening a ``.wgs`` gives two outputs: the model decoded as image data at a chosen resolution
(values in the source's units, the header's spacing and origin; a pipeline's update-extent
request, a sub-extent of it, is decoded alone as a region, :func:`decode_image`) and the primitives as a point
cloud (as ``warpgauss export`` writes it: scales, orientation, value and weight per point). The
header's default transfer function (or the one in ``TransferFunctionFile``, e.g. the colours edited
in ``warpgauss serve``) travels with the image as field data
(``warpgauss_rgb_points``, ``warpgauss_opacity_points``, ParaView's layouts) and
:func:`apply_default_transfer_function` applies it (in pvpython, or in ParaView's Python shell:
``apply_default_transfer_function()``, defined by this file once loaded; or import it by path).

ParaView's Python seldom has Warp: where ``import warpgauss`` fails inside ParaView the reader runs
the warpgauss command line instead (``warpgauss decode`` to a ``.vti``, ``warpgauss export`` to a
``.vtp``, in a temporary folder): the executable from ``$WARPGAUSS_CLI`` (a command line, e.g.
``/opt/venv/bin/warpgauss``) or ``warpgauss`` on the PATH. Outside ParaView the same class runs on
plain VTK (``vtkmodules``), which is how the tests drive it without pvpython.

Debian 12's ParaView 5.11 cannot load any Python plugin on its Python 3.11 (its
``paraview.detail.pythonalgorithm`` imports ``inspect.getargspec``, removed in 3.11); before
loading this one, run in its Python shell (or at the top of a pvpython script)
``import inspect; inspect.getargspec = inspect.getfullargspec``. ParaView 5.12 and later need nothing.
"""

from __future__ import annotations

import inspect
import json
import os
import shlex
import shutil
import struct
import subprocess
import tempfile
import zlib

if not hasattr(inspect, "getargspec"):  # ParaView 5.11's pythonalgorithm on Python >= 3.11
    setattr(inspect, "getargspec", inspect.getfullargspec)  # noqa: B010

import numpy as np

try:  # inside ParaView: the decorators make the class a reader proxy
    from paraview.util.vtkAlgorithm import VTKPythonAlgorithmBase, smdomain, smhint, smproperty, smproxy

    IN_PARAVIEW = True
except ImportError:  # plain VTK: the same algorithm class, the decorators do nothing
    from vtkmodules.util.vtkAlgorithm import VTKPythonAlgorithmBase

    IN_PARAVIEW = False

    class _Passthrough:
        def __getattr__(self, _name):
            def decorator_factory(*_args, **_kwargs):
                return lambda f: f

            return decorator_factory

    smproxy = smproperty = smdomain = smhint = _Passthrough()

_PREFIX = struct.Struct("<8sIII")
MAGIC = b"WGAUSS\x00\x01"
# our colormap names -> ParaView presets (used where the header carries no LUT, e.g. coded files)
PARAVIEW_PRESETS = {
    "viridis": "Viridis (matplotlib)",
    "magma": "Magma (matplotlib)",
    "inferno": "Inferno (matplotlib)",
    "plasma": "Plasma (matplotlib)",
    "cividis": "Cividis",
    "turbo": "Turbo",
    "coolwarm": "Cool to Warm",
    "jet": "Jet",
    "grayscale": "Grayscale",
}
TF_POINTS = 33  # colour / opacity points written for ParaView


class ReaderError(RuntimeError):
    """A file the reader cannot open (the message says why and what to do)."""


def read_header(path: str) -> dict:
    """The JSON header of a ``.wgs`` file, read with the standard library alone."""
    try:
        with open(path, "rb") as f:
            raw = f.read(_PREFIX.size)
            if len(raw) < _PREFIX.size:
                raise ReaderError(f"{path}: not a warpgauss model (too short)")
            magic, _version, hlen, crc = _PREFIX.unpack(raw)
            if magic != MAGIC:
                raise ReaderError(f"{path}: not a warpgauss model (bad magic); open a .wgs file")
            area = f.read(hlen)
    except OSError as e:
        raise ReaderError(f"cannot open {path}: {e.strerror}") from None
    if len(area) != hlen or zlib.crc32(area) != crc:
        raise ReaderError(f"{path}: the header is damaged (checksum); restore the file or re-encode")
    return json.loads(area.decode("utf-8"))


def decode_shape(header: dict, resolution: int) -> tuple[int, int, int]:
    """The decoded grid (x, y, z): the model's, or ``resolution`` voxels along its longest axis."""
    shape = [int(s) for s in header["grid"]["shape_xyz"]]
    if resolution <= 0:
        return (shape[0], shape[1], shape[2])
    k = resolution / max(shape)
    return (max(1, round(shape[0] * k)), max(1, round(shape[1] * k)), max(1, round(shape[2] * k)))


def _spacing_origin(header: dict, shape) -> tuple[list[float], list[float]]:
    g = header["grid"]
    sp = [float(g["spacing"][a]) * int(g["shape_xyz"][a]) / int(shape[a]) for a in range(3)]
    # the first decoded voxel's centre (as warpgauss.Model.decoded_origin)
    org = [float(g["origin"][a]) + 0.5 * (sp[a] - float(g["spacing"][a])) for a in range(3)]
    return sp, org


def transfer_function_points(header: dict, lut: np.ndarray | None = None, own: bool = False) -> tuple[list[float], list[float], str]:
    """ParaView's RGBPoints (x, r, g, b, ...) and opacity points (x, a, 0.5, 0, ...) in the
    source's units, from the header's LUT (or ``lut``: (K, 4) RGBA in [0, 1]); and the colormap
    name. Without a LUT (coded files) the colours come from the named preset and only the opacity
    points are exact. ``own``: ``lut`` is a transfer function of its own (a file's), not the
    header's: its opacity is kept and its name is "custom"."""
    t = {"colormap": "custom"} if own else header.get("transfer_function") or {}
    vmin, vmax = float(header["values"]["min"]), float(header["values"]["max"])
    name = str(t.get("colormap") or "viridis")
    if lut is None and isinstance(t.get("lut_rgba8"), str):
        raw = np.frombuffer(bytes.fromhex(t["lut_rgba8"]), np.uint8)
        if raw.size >= 8 and raw.size % 4 == 0:
            lut = raw.reshape(-1, 4).astype(np.float64) / 255.0
    xs = np.linspace(0.0, 1.0, TF_POINTS)
    rgb_points: list[float] = []
    alpha = None
    if lut is not None:
        k = np.linspace(0.0, 1.0, lut.shape[0])
        cols = np.stack([np.interp(xs, k, lut[:, c]) for c in range(4)], axis=1)
        rgb_points = [v for x, c in zip(xs, cols) for v in (vmin + x * (vmax - vmin), c[0], c[1], c[2])]
        alpha = cols[:, 3]
    if isinstance(t.get("opacity"), list) and t["opacity"]:
        pts = sorted((float(p[0]), float(p[1])) for p in t["opacity"])
        alpha = np.interp(xs, [p[0] for p in pts], [p[1] for p in pts])
    if alpha is None:
        alpha = xs.copy()
    opacity_points = [v for x, a in zip(xs, alpha) for v in (vmin + x * (vmax - vmin), float(a), 0.5, 0.0)]
    return rgb_points, opacity_points, name


def file_transfer_function(path: str, header: dict) -> np.ndarray:
    """(K, 4) RGBA in [0, 1] over the normalised values of a transfer-function file: any that
    ``warpgauss render --tf`` reads where warpgauss is importable; else (ParaView's Python without
    Warp) our JSON with ``"colors"`` and ``"opacity"``, as ``warpgauss serve`` writes it."""
    vmin, vmax = float(header["values"]["min"]), float(header["values"]["max"])
    if not _use_cli():
        from warpgauss.errors import WarpgaussError
        from warpgauss.render.transfer import load_transfer_function

        try:
            return load_transfer_function(path, (vmin, vmax)).rgba
        except WarpgaussError as e:
            raise ReaderError(str(e)) from None
    try:
        with open(path, encoding="utf-8") as f:
            doc = json.load(f)
        colors = np.asarray(doc["colors"], np.float64)
        opacity = np.asarray(doc["opacity"], np.float64)
        if colors.ndim != 2 or colors.shape[1] != 4 or opacity.ndim != 2 or opacity.shape[1] != 2:
            raise ValueError("shape")
    except OSError as e:
        raise ReaderError(f"cannot open {path}: {e.strerror}") from None
    except (ValueError, KeyError, TypeError):
        raise ReaderError(
            f"{path}: without warpgauss in this Python the reader takes a transfer function as"
            ' {"colors": [[x, r, g, b], ...], "opacity": [[x, a], ...]} (what warpgauss serve writes)'
        ) from None
    if str(doc.get("space", "normalised")).lower() == "data":
        span = vmax - vmin or 1.0
        colors[:, 0] = (colors[:, 0] - vmin) / span
        opacity[:, 0] = (opacity[:, 0] - vmin) / span
    colors, opacity = colors[np.argsort(colors[:, 0], kind="stable")], opacity[np.argsort(opacity[:, 0], kind="stable")]
    x = np.linspace(0.0, 1.0, 256)
    rgb = [np.interp(x, colors[:, 0], np.clip(colors[:, c], 0.0, 1.0)) for c in (1, 2, 3)]
    return np.stack([*rgb, np.interp(x, opacity[:, 0], np.clip(opacity[:, 1], 0.0, 1.0))], axis=1)


def _cli() -> list[str]:
    cmd = os.environ.get("WARPGAUSS_CLI")
    if cmd:
        return shlex.split(cmd)
    exe = shutil.which("warpgauss")
    if exe is None:
        raise ReaderError(
            "warpgauss is not importable in this Python and no warpgauss command is on the PATH: set WARPGAUSS_CLI to it (e.g. /opt/venv/bin/warpgauss)"
        )
    return [exe]


def _use_cli() -> bool:
    if os.environ.get("WARPGAUSS_PARAVIEW_CLI") == "1":
        return True
    try:
        import warpgauss  # noqa: F401
    except ImportError:
        return True
    return False


def extent_box(header: dict, shape, extent) -> tuple[tuple[float, float], ...] | None:
    """The box (voxel bounds of the encoded grid, :mod:`warpgauss.field.region`) that the voxels
    ``extent`` (VTK's i0, i1, j0, j1, k0, k1, inclusive) of a decode at ``shape`` cover, or None
    for the whole extent: its decode is that extent of the whole decode, bit for bit."""
    full = [int(v) for v in header["grid"]["shape_xyz"]]
    if list(extent) == [0, int(shape[0]) - 1, 0, int(shape[1]) - 1, 0, int(shape[2]) - 1]:
        return None
    return tuple((extent[2 * a] * full[a] / int(shape[a]), (extent[2 * a + 1] + 1) * full[a] / int(shape[a])) for a in range(3))


def decode_image(path: str, shape, device: str | None = None, residual: bool = False, extent=None):
    """(vtkImageData of the decode at ``shape``, vtkPolyData of the primitives, (K, 4) LUT or None).
    ``residual``: apply a bounded residual (on the model's own grid; default: the Gaussians alone).
    ``extent``: only these voxels (VTK's inclusive i0, i1, j0, j1, k0, k1) of the decode, a
    region decode (``Model.decode(box=...)``, ``warpgauss decode --box``); the image then has that
    extent and the whole decode's origin, as a pipeline's update-extent request wants it."""
    header = read_header(path)
    box = None if extent is None else extent_box(header, shape, extent)
    part = shape if box is None else tuple(int(extent[2 * a + 1] - extent[2 * a] + 1) for a in range(3))
    img, poly, lut = _decode_image(path, part, device, residual, box)
    if box is not None:
        _, origin = _spacing_origin(header, shape)
        img.SetOrigin(*origin)
        img.SetExtent(*extent)
    return img, poly, lut


def _decode_image(path: str, shape, device: str | None, residual: bool, box):
    from vtkmodules.vtkCommonDataModel import vtkImageData, vtkPolyData

    if _use_cli():
        from vtkmodules.vtkIOXML import vtkXMLImageDataReader, vtkXMLPolyDataReader

        with tempfile.TemporaryDirectory(prefix="warpgauss-pv-") as d:
            vti, vtp = os.path.join(d, "decoded.vti"), os.path.join(d, "primitives.vtp")
            dev = ["--device", device] if device else []
            res = ["--residual" if residual else "--no-residual"]
            if box is not None:
                res += ["--box", ",".join(f"{lo!r}:{hi!r}" for lo, hi in box)]
            for args in (["decode", path, "-o", vti, "--shape", "x".join(map(str, shape)), *dev, *res], ["export", path, "-o", vtp]):
                r = subprocess.run([*_cli(), *args], capture_output=True, text=True)
                if r.returncode != 0:
                    raise ReaderError(f"warpgauss {args[0]} failed: {(r.stderr or r.stdout).strip().splitlines()[-1:]}")
            ri, rp = vtkXMLImageDataReader(), vtkXMLPolyDataReader()
            ri.SetFileName(vti)
            rp.SetFileName(vtp)
            ri.Update()
            rp.Update()
            img, pts = vtkImageData(), vtkPolyData()
            img.DeepCopy(ri.GetOutput())
            pts.DeepCopy(rp.GetOutput())
        return img, pts, None
    import warpgauss
    from warpgauss.format.export import primitives_polydata
    from warpgauss.readers.write import image_data
    from warpgauss.render.transfer import from_header

    m = warpgauss.Model.load(path)
    shape = tuple(shape)
    name = str(m.header.get("name") or "value")  # as warpgauss decode names it
    data = m.decode(shape_xyz=shape, box=box, device=device, residual=residual and m.residual is not None)
    img = image_data(data, m.decoded_spacing(shape, box), m.decoded_origin(shape, box), name)
    poly = primitives_polydata(m)  # as warpgauss export writes it
    tf = from_header(m.header)
    return img, poly, tf.rgba


@smproxy.reader(name="WarpgaussReader", label="warpgauss model", extensions="wgs", file_description="warpgauss Gaussian models")
@smhint.xml('<RepresentationType view="RenderView" type="Volume" port="0" />')
class WarpgaussReader(VTKPythonAlgorithmBase):
    """Reads a ``.wgs`` model: output 0 the decoded image data, output 1 the primitives."""

    def __init__(self):
        VTKPythonAlgorithmBase.__init__(self, nInputPorts=0, nOutputPorts=2, outputType="vtkImageData")
        self._filename = None
        self._resolution = 0
        self._device = ""
        self._tf_file = ""
        self._residual = False

    def FillOutputPortInformation(self, port, info):
        from vtkmodules.vtkCommonDataModel import vtkDataObject

        info.Set(vtkDataObject.DATA_TYPE_NAME(), "vtkImageData" if port == 0 else "vtkPolyData")
        return 1

    @smproperty.stringvector(name="FileName")
    @smdomain.filelist()
    @smhint.filechooser(extensions="wgs", file_description="warpgauss Gaussian models")
    def SetFileName(self, name):
        if name != self._filename:
            self._filename = name
            self.Modified()

    @smproperty.intvector(name="Resolution", default_values=0)
    @smdomain.intrange(min=0, max=2048)
    def SetResolution(self, n):
        """Voxels along the longest axis of the decode (0: the model's own grid)."""
        if int(n) != self._resolution:
            self._resolution = int(n)
            self.Modified()

    @smproperty.stringvector(name="Device", default_values="")
    def SetDevice(self, device):
        """Warp device for the decode (empty: CUDA when present, else CPU)."""
        if device != self._device:
            self._device = device
            self.Modified()

    @smproperty.intvector(name="Residual", default_values=0)
    @smdomain.intrange(min=0, max=1)
    def SetResidual(self, on):
        """1: apply a model's bounded residual (every voxel within its bound; the model's own grid
        only, Resolution 0); 0: the Gaussians alone."""
        if bool(on) != self._residual:
            self._residual = bool(on)
            self.Modified()

    @smproperty.stringvector(name="TransferFunctionFile", default_values="")
    @smdomain.filelist()
    @smhint.filechooser(extensions="json", file_description="transfer function")
    def SetTransferFunctionFile(self, path):
        """A transfer function to carry instead of the header's (empty: the header's): the file
        ``warpgauss serve`` offers after the colours are edited, or any ``warpgauss render --tf`` reads."""
        if path != self._tf_file:
            self._tf_file = path or ""
            self.Modified()

    def _header(self) -> dict:
        if not self._filename:
            raise ReaderError("no file name set")
        return read_header(self._filename)

    def RequestInformation(self, request, in_info, out_info):
        from vtkmodules.vtkCommonDataModel import vtkDataObject
        from vtkmodules.vtkCommonExecutionModel import vtkAlgorithm
        from vtkmodules.vtkCommonExecutionModel import vtkStreamingDemandDrivenPipeline as sddp

        try:
            header = self._header()
        except ReaderError as e:
            print(f"warpgauss reader: {e}")
            return 0
        shape = decode_shape(header, self._resolution)
        sp, org = _spacing_origin(header, shape)
        info = out_info.GetInformationObject(0)
        info.Set(sddp.WHOLE_EXTENT(), 0, shape[0] - 1, 0, shape[1] - 1, 0, shape[2] - 1)
        info.Set(vtkAlgorithm.CAN_PRODUCE_SUB_EXTENT(), 1)  # an update extent is decoded alone (a region decode)
        info.Set(vtkDataObject.SPACING(), *sp)
        info.Set(vtkDataObject.ORIGIN(), *org)
        return 1

    def RequestData(self, request, in_info, out_info):
        from vtkmodules.util.numpy_support import numpy_to_vtk
        from vtkmodules.vtkCommonCore import vtkStringArray
        from vtkmodules.vtkCommonDataModel import vtkImageData, vtkPolyData
        from vtkmodules.vtkCommonExecutionModel import vtkStreamingDemandDrivenPipeline as sddp

        try:
            header = self._header()
            shape = decode_shape(header, self._resolution)
            port = out_info.GetInformationObject(0)
            extent = list(port.Get(sddp.UPDATE_EXTENT())) if port.Has(sddp.UPDATE_EXTENT()) else None
            if extent is not None and not all(0 <= extent[2 * a] <= extent[2 * a + 1] < shape[a] for a in range(3)):
                extent = None  # empty or outside the whole extent: the whole decode
            path = str(self._filename)  # _header() checked it is set
            img, poly, lut = decode_image(path, shape, self._device or None, self._residual, extent)
            own = bool(self._tf_file)
            if own:
                lut = file_transfer_function(self._tf_file, header)
        except ReaderError as e:
            print(f"warpgauss reader: {e}")
            return 0
        rgb, opacity, name = transfer_function_points(header, lut, own)
        for key, values in (("warpgauss_rgb_points", rgb), ("warpgauss_opacity_points", opacity)):
            if values:
                a = numpy_to_vtk(np.asarray(values, np.float64), deep=1)
                a.SetName(key)
                img.GetFieldData().AddArray(a)
        s = vtkStringArray()
        s.SetName("warpgauss_colormap")
        s.InsertNextValue(name)
        img.GetFieldData().AddArray(s)
        vtkImageData.GetData(out_info.GetInformationObject(0)).ShallowCopy(img)
        vtkPolyData.GetData(out_info.GetInformationObject(1)).ShallowCopy(poly)
        return 1


def apply_default_transfer_function(source=None, view=None):
    """In ParaView (pvpython or its Python shell): show ``source`` (default: the active source) as
    a volume with the header's transfer function; returns the display."""
    from paraview import servermanager
    from paraview import simple as pvs

    source = source or pvs.GetActiveSource()
    view = view or pvs.GetActiveViewOrCreate("RenderView")
    data = servermanager.Fetch(source)
    if data.IsA("vtkMultiBlockDataSet"):
        data = data.GetBlock(0)
    fd = data.GetFieldData()
    name = data.GetPointData().GetScalars().GetName()
    display = pvs.Show(source, view)
    pvs.ColorBy(display, ("POINTS", name))
    display.SetRepresentationType("Volume")
    lut = pvs.GetColorTransferFunction(name)
    pwf = pvs.GetOpacityTransferFunction(name)
    rgb = fd.GetArray("warpgauss_rgb_points")
    if rgb is not None and rgb.GetNumberOfTuples() > 0:
        lut.RGBPoints = [rgb.GetValue(i) for i in range(rgb.GetNumberOfTuples())]
    else:
        cmap = fd.GetAbstractArray("warpgauss_colormap")
        preset = PARAVIEW_PRESETS.get(cmap.GetValue(0) if cmap is not None else "viridis", "Viridis (matplotlib)")
        lut.ApplyPreset(preset, True)
    op = fd.GetArray("warpgauss_opacity_points")
    if op is not None:
        pwf.Points = [op.GetValue(i) for i in range(op.GetNumberOfTuples())]
    return display
