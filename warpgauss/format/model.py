"""The encoded model: N primitives plus the self-describing header of the ``.wgs`` file.

``Model.params`` is an (N, 12) float32 array, one row per primitive:
``mu_x, mu_y, mu_z, log_sx, log_sy, log_sz, q_x, q_y, q_z, q_w, a, w`` (centre in voxel units
of the model grid, log-sigmas, unit quaternion in Warp's order, value in normalised units,
weight in (0, 1]). The header keeps the grid, the value range for decoding to original units,
the source's dtype and size (for the compression ratio), the encoding configuration and seed,
and a default transfer function.
"""

from __future__ import annotations

import hashlib
import math
import os
from collections.abc import Callable
from pathlib import Path

import numpy as np

from .._version import __version__
from ..errors import WarpgaussError
from .residual import Residual

# viridis at nine evenly spaced stops (RGB 0..255); the default colormap of the header's LUT
_VIRIDIS = np.array(
    [
        (68, 1, 84),
        (71, 44, 122),
        (59, 82, 139),
        (44, 113, 142),
        (33, 145, 140),
        (39, 173, 129),
        (92, 200, 99),
        (170, 220, 50),
        (253, 231, 37),
    ],
    np.float64,
)


def default_transfer_function(entries: int = 256) -> dict:
    """Viridis colour with a linear opacity ramp, as a 256-entry RGBA8 LUT (hex) over [0, 1]."""
    x = np.linspace(0.0, 1.0, entries)
    stops = np.linspace(0.0, 1.0, len(_VIRIDIS))
    rgb = np.stack([np.interp(x, stops, _VIRIDIS[:, c]) for c in range(3)], axis=1)
    alpha = 255.0 * x
    lut = np.concatenate([rgb, alpha[:, None]], axis=1).round().astype(np.uint8)
    return {"colormap": "viridis", "opacity": [[0.0, 0.0], [1.0, 1.0]], "lut_rgba8": lut.tobytes().hex()}


def make_header(
    *,
    shape_xyz,
    spacing,
    origin,
    vmin: float,
    vmax: float,
    source_dtype: str,
    source_itemsize: int,
    name: str,
    encoding: dict,
    seed: int,
) -> dict:
    """The header fields of SPEC section 6 that the caller owns (the format adds n and payload)."""
    nx, ny, nz = (int(s) for s in shape_xyz)
    return {
        "format": "warpgauss",
        "warpgauss_version": __version__,
        "name": name,
        "grid": {
            "shape_xyz": [nx, ny, nz],
            "spacing": [float(s) for s in spacing],
            "origin": [float(o) for o in origin],
        },
        "values": {"min": float(vmin), "max": float(vmax)},
        "source": {
            "dtype": source_dtype,
            "itemsize": int(source_itemsize),
            "bytes": int(nx * ny * nz * int(source_itemsize)),
        },
        "encoding": dict(encoding),
        "seed": int(seed),
        "transfer_function": default_transfer_function(),
    }


def _is_number(x) -> bool:
    return not isinstance(x, bool) and isinstance(x, (int, float)) and math.isfinite(x)


def _is_count(x, least: int) -> bool:
    return not isinstance(x, bool) and isinstance(x, int) and x >= least


def _header_problem(h: dict) -> str | None:
    """What is wrong with the fields of a loaded header that decoding and reports read, or None.

    The checksums prove a file is as written, not that its writer filled the fields sensibly: a
    crafted header must be refused here, not crash later (a string grid, a zero-voxel axis, an
    inverted value range, a grid too large to index).
    """
    from ..field.limits import MAX_HOST_VOXELS

    g, v, src = h.get("grid"), h.get("values"), h.get("source")
    if not isinstance(g, dict):
        return "'grid' is not an object"
    shape = g.get("shape_xyz")
    if not (isinstance(shape, list) and len(shape) == 3 and all(_is_count(x, 1) for x in shape)):
        return f"grid shape_xyz {shape!r} is not three positive integers"
    if math.prod(shape) > MAX_HOST_VOXELS:  # what an encode with the volume in host memory indexes; decoded by slabs
        return f"grid {shape!r} has more than {MAX_HOST_VOXELS} voxels"
    for key in ("spacing", "origin"):
        x = g.get(key)
        if not (isinstance(x, list) and len(x) == 3 and all(_is_number(c) for c in x)):
            return f"grid {key} {x!r} is not three finite numbers"
    if not all(c > 0 for c in g["spacing"]):
        return f"grid spacing {g['spacing']!r} is not three positive numbers"
    if not (isinstance(v, dict) and _is_number(v.get("min")) and _is_number(v.get("max")) and v["min"] < v["max"]):
        return f"value range {v!r} is not two finite numbers min < max"
    if not (isinstance(src, dict) and _is_count(src.get("bytes"), 0)):
        return f"source {src!r} has no byte count"
    if "itemsize" in src and not _is_count(src["itemsize"], 1):
        return f"source itemsize {src['itemsize']!r} is not a positive integer"
    for key in ("encoding", "transfer_function"):
        if h.get(key) is not None and not isinstance(h[key], dict):
            return f"'{key}' is not an object"
    tf = h.get("transfer_function") or {}
    if "colormap" in tf and not isinstance(tf["colormap"], str):
        return f"transfer_function colormap {tf['colormap']!r} is not a string"
    if "lut_rgba8" in tf and not isinstance(tf["lut_rgba8"], str):
        return "transfer_function lut_rgba8 is not a hex string"
    op = tf.get("opacity")
    if op is not None and not (isinstance(op, list) and all(isinstance(q, list) and len(q) == 2 and all(map(_is_number, q)) for q in op)):
        return f"transfer_function opacity {op!r} is not a list of [value, opacity] pairs"
    stride = (h.get("encoding") or {}).get("stride", 1)
    if not _is_count(stride, 1):
        return f"encoding stride {stride!r} is not a positive integer"
    if "name" in h and not isinstance(h["name"], str):
        return f"name {h['name']!r} is not a string"
    return None


def _check_header(p: Path | str, header: dict) -> None:
    """Refuse a header (of the file ``p``) that lacks what a reader uses or holds it unusable."""
    for key in ("grid", "values", "source"):
        if key not in header:
            raise WarpgaussError(f"{p}: the header lacks '{key}'; the file was not written by warpgauss")
    problem = _header_problem(header)
    if problem is not None:
        raise WarpgaussError(f"{p}: the header's {problem}; the file is damaged or was not written by warpgauss")


def _residual_of(p: Path | str, header: dict, data: bytes | None = None) -> Residual:
    """The residual of the file ``p`` (its bytes end the file, or ``data``, the file's bytes in
    memory: checked against its SHA-256 here), its description checked."""
    from .residual import check_info

    info = header["residual"]
    problem = check_info(info, math.prod(header["grid"]["shape_xyz"]))
    if problem is not None:
        raise WarpgaussError(f"{p}: the header's {problem}; the file is damaged or was not written by warpgauss")
    if data is None:
        assert isinstance(p, Path)
        return Residual(info, path=p, offset=p.stat().st_size - int(info["payload_bytes"]))
    tail = bytes(data[len(data) - int(info["payload_bytes"]) :])
    if hashlib.sha256(tail).hexdigest() != info["sha256"]:
        raise WarpgaussError(f"{p}: residual checksum mismatch: the bytes are damaged; restore them or re-encode")
    return Residual(info, data=tail)


def _decode_shape(shape, shape_zyx, shape_xyz) -> tuple[int, int, int] | None:
    """The (x, y, z) grid of :meth:`Model.decode` from its three ways of giving one (at most one)."""
    import warnings

    given = [n for n, v in (("shape", shape), ("shape_zyx", shape_zyx), ("shape_xyz", shape_xyz)) if v is not None]
    if len(given) > 1:
        raise WarpgaussError(f"give one of shape_zyx (the array's shape) and shape_xyz, not {' and '.join(given)}")
    if shape is not None:
        warnings.warn(
            "Model.decode(shape) reads (x, y, z) and returns a (z, y, x) array; write decode(shape_zyx=(nz, ny, nx)) "
            "for the returned array's shape, or decode(shape_xyz=(nx, ny, nz)); the positional shape goes in the next release",
            DeprecationWarning,
            stacklevel=3,
        )
        return shape
    if shape_zyx is not None:
        dims = tuple(shape_zyx)
        if len(dims) != 3:
            raise WarpgaussError(f"shape_zyx must be three positive integers (nz, ny, nx), got {shape_zyx!r}")
        return (dims[2], dims[1], dims[0])
    return shape_xyz


def _check_decode_size(shape) -> None:
    """Refuse a decode grid this machine cannot hold (the result, and a float64 copy on the way to
    source units) before anything is allocated for it."""
    try:
        dims = [int(v) for v in shape]
    except (TypeError, ValueError):
        dims = []
    if len(dims) != 3 or min(dims) < 1:
        raise WarpgaussError(f"decode shape must be three positive sizes (x, y, z), got {shape!r}")
    need = math.prod(dims) * 12  # float32 result + float64 source units
    try:
        ram = int(os.sysconf("SC_PHYS_PAGES")) * int(os.sysconf("SC_PAGE_SIZE"))
    except (AttributeError, ValueError, OSError):
        return
    if need > ram:
        raise WarpgaussError(
            f"decoding to {'x'.join(map(str, dims))} needs about {need / 2**30:.1f} GiB, more than this machine's "
            f"{ram / 2**30:.1f} GiB of memory; choose a smaller --shape"
        )


class _Ratio(float):
    """:attr:`Model.compression_ratio`, a number that a call still answers as the method it was
    (deprecated: the call goes in the next release)."""

    _model: Model

    def __new__(cls, value: float, model: Model):
        self = super().__new__(cls, value)
        self._model = model
        return self

    def __call__(self, compact: bool = False, *, encoding: str | None = None) -> float:
        import warnings

        warnings.warn(
            "Model.compression_ratio is a property now, as Model.n is: write model.compression_ratio for the file save() "
            "writes, or model.source_bytes / model.file_size(encoding=...) for another format; the call goes in the next release",
            DeprecationWarning,
            stacklevel=2,
        )
        m = self._model
        return m.source_bytes / m.file_size(compact, encoding=encoding)

    def __reduce__(self):  # a plain number wherever it is copied
        return (float, (float(self),))


class Model:
    """A fixed-budget Gaussian model of a scalar volume.

    Args:
        params: (N, 12) float32 primitive parameters.
        header: Header dict (see :func:`make_header`).
    """

    def __init__(self, params: np.ndarray, header: dict):
        params = np.ascontiguousarray(params, dtype=np.float32)
        if params.ndim != 2 or params.shape[1] != 12 or params.shape[0] < 1:
            raise WarpgaussError(f"a model needs an (N, 12) parameter array with N >= 1, got shape {params.shape}")
        self.params = params
        self.header = header
        self.report: dict | None = None  # filled by warpgauss.encode
        self.coded_bits: dict | None = None  # bit depths a coded save uses (None: the format's default)
        self.format: str | None = None  # the format it was encoded for or read from (save's default)
        self.kept_rows: np.ndarray | None = None  # fit_bytes: the rows of the model it was fitted from that it keeps
        self.residual: Residual | None = None  # a bounded residual (encode --max-error): decode() applies it

    @property
    def run_report(self) -> dict:
        """The report of the encode that made this model (:attr:`report`); a model loaded from a
        file has none (its run's report is the ``.report.json`` written beside it)."""
        if self.report is None:
            raise WarpgaussError("this model has no run report: it was loaded from a file (its report is the .report.json beside it)")
        return self.report

    # -- description -----------------------------------------------------------------------
    @property
    def n(self) -> int:
        return int(self.params.shape[0])

    @property
    def shape_xyz(self) -> tuple[int, ...]:
        return tuple(int(s) for s in self.header["grid"]["shape_xyz"])

    @property
    def value_range(self) -> tuple[float, float]:
        v = self.header["values"]
        return float(v["min"]), float(v["max"])

    @property
    def source_bytes(self) -> int:
        return int(self.header["source"]["bytes"])

    def file_size(self, compact: bool = False, *, encoding: str | None = None) -> int:
        """Exact bytes of this model's file: 48 N + H (full precision), 12 N + H (compact) or
        the coded payload + H (``encoding="coded"``: the payload is coded to measure it)."""
        return self.file_sizes(compact, encoding=encoding)[0]

    def file_sizes(self, compact: bool = False, *, encoding: str | None = None) -> tuple[int, int]:
        """(file bytes, payload bytes) of this model's file (see :meth:`file_size`); a residual's
        bytes count in both."""
        from .wgs import ENCODINGS, header_size, payload_size, resolve_encoding, wgs_bytes

        enc = resolve_encoding(compact, encoding)
        per = ENCODINGS[enc]
        if per is None or self.residual is not None:
            data = wgs_bytes(self.params, self.header, encoding=enc, bits=self.coded_bits, residual=self.residual)
            return len(data), payload_size(data)
        payload = per * self.n
        return payload + header_size(self.header, self.n, encoding=enc), payload

    @property
    def compression_ratio(self) -> _Ratio:
        """Source bytes over the bytes of the file :meth:`save` writes by default (the format the
        model was encoded for or read from, else float32; a residual counted), the ratio
        ``warpgauss info`` prints; a coded model is coded to measure it. A property, as :attr:`n`
        is; the call it was (``compression_ratio(compact, encoding=...)``) still answers this
        release with a DeprecationWarning: write ``source_bytes / file_size(encoding=...)``."""
        return _Ratio(self.source_bytes / self.file_size(encoding=self.format or "float32"), self)

    def stored(self, encoding: str) -> Model:
        """This model as a file of ``encoding`` would hand it back on reading (for "coded": on the
        coded grids, in the file's Morton order; float32 and compact96: unchanged, since the
        encoder evaluates those before quantisation)."""
        if encoding != "coded":
            return self
        from .coded import as_stored

        m = Model(as_stored(self.params, self.coded_bits), self.header)
        m.report, m.coded_bits, m.format = self.report, self.coded_bits, "coded"
        return m  # no residual: it belongs to the exact parameters it was coded against

    def fit_bytes(
        self, total_bytes: int, prune_share: float | None = None, score: Callable[[Model], float] | None = None
    ) -> tuple[Model, dict]:
        """This model coded to fit ``total_bytes`` (header included): see :func:`warpgauss.format.ratefit.fit_bytes`
        (``score(model)``: a fitted model's PSNR, where the rate control may choose by it).
        The rows of this model that the result keeps are its ``kept_rows`` (for a refit)."""
        from .ratefit import fit_bytes
        from .wgs import wgs_bytes

        def size_of(params, bits) -> int:
            return len(wgs_bytes(params, self.header, encoding="coded", bits=bits))

        rate = None if score is None else (lambda params, bits: score(Model(params, self.header)))
        stored, bits, info = fit_bytes(self.params, total_bytes, self.coded_bits, size_of, prune_share, rate)
        m = Model(stored, self.header)
        m.report, m.coded_bits, m.format = self.report, bits, "coded"
        m.kept_rows = info.pop("kept")
        return m, {**info, "bits": bits}

    # -- file I/O --------------------------------------------------------------------------
    def save(self, path: str | os.PathLike, *, compact: bool = False, encoding: str | None = None, force: bool = True) -> int:
        """Write the model atomically (``encoding``: "float32", "compact96" or "coded"; overrides
        ``compact``; neither: the format it was encoded for or read from, else float32); returns
        the file size in bytes. An existing file is replaced, as numpy and pyvista replace theirs
        (``force=False`` refuses it instead; the command line refuses unless given ``--force``)."""
        from .wgs import write_wgs

        if encoding is None and not compact:
            encoding = self.format or "float32"
        return write_wgs(
            path, self.params, self.header, compact=compact, encoding=encoding, force=force, bits=self.coded_bits, residual=self.residual
        )

    @classmethod
    def load(cls, path: str | os.PathLike) -> Model:
        """Read and validate a ``.wgs`` file (magic, version, sizes, checksums)."""
        from .wgs import read_wgs

        p = Path(path)
        if not p.is_file():
            raise WarpgaussError(f"no such model file: {p}")
        params, header = read_wgs(p)
        _check_header(p, header)
        m = cls(params, header)
        m.format = header["payload"]["encoding"]
        if m.format == "coded":
            m.coded_bits = dict(header["payload"]["quant"]["bits"])  # saved again, it codes to the same bytes
        if "residual" in header:  # its bytes are read (and checked) when a decode applies it
            m.residual = _residual_of(p, header)
        return m

    def to_bytes(self, *, encoding: str | None = None) -> bytes:
        """The bytes :meth:`save` writes, in memory (``encoding`` as :meth:`save` takes it)."""
        from .wgs import wgs_bytes

        enc = encoding or self.format or "float32"
        return wgs_bytes(self.params, self.header, encoding=enc, bits=self.coded_bits, residual=self.residual)

    @classmethod
    def from_bytes(cls, data: bytes) -> Model:
        """A model from a whole ``.wgs`` file's bytes (:meth:`to_bytes`), validated as :meth:`load`
        validates a file, the residual's checksum included."""
        from .wgs import read_wgs_bytes

        label = "the model bytes"
        params, header = read_wgs_bytes(data)
        _check_header(label, header)
        m = cls(params, header)
        m.format = header["payload"]["encoding"]
        if m.format == "coded":
            m.coded_bits = dict(header["payload"]["quant"]["bits"])
        if "residual" in header:
            m.residual = _residual_of(label, header, data)
        return m

    @staticmethod
    def load_header(path: str | os.PathLike) -> dict:
        """The header of a ``.wgs`` file, validated as :meth:`load` validates it, without reading
        (or checking the checksum of) its payload: what ``warpgauss info`` shows."""
        from .wgs import read_wgs_header

        p = Path(path)
        if not p.is_file():
            raise WarpgaussError(f"no such model file: {p}")
        header = read_wgs_header(p)
        _check_header(p, header)
        if "residual" in header:
            _residual_of(p, header)
        return header

    # -- evaluation ------------------------------------------------------------------------
    def field(self, device: str | None = None):
        """The model resident on a Warp device, ready for evaluation (:class:`GaussianField`)."""
        from ..field.gaussians import GaussianField

        return GaussianField(self.params, self.shape_xyz, device=device)

    def decode(
        self,
        shape: tuple[int, int, int] | None = None,
        *,
        shape_zyx: tuple[int, int, int] | None = None,
        shape_xyz: tuple[int, int, int] | None = None,
        box=None,
        device: str | None = None,
        normalised: bool = False,
        progress: Callable[[int, int], None] | None = None,
        info: dict | None = None,
        residual: bool | None = None,
    ) -> np.ndarray:
        """Evaluate the model on a grid spanning the model's extent, or a box of it.

        Args:
            shape: Deprecated: the output grid as (x, y, z), which returned a (z, y, x) array;
                give ``shape_zyx`` (the returned array's shape) or ``shape_xyz`` instead. It
                works for this release, with a warning.
            shape_zyx: The returned array's shape (nz, ny, nx), as numpy orders it; None (and no
                ``shape_xyz``): the encoded grid (with ``box``: the box at the encoded resolution).
            shape_xyz: The same grid as (nx, ny, nz), as the command line's ``--shape XxYxZ``.
            box: Decode only this region, ``((x0, x1), (y0, y1), (z0, z1))`` in voxel
                coordinates of the encoded grid (not physical units): bounds on voxel faces, so
                integer bounds hold the voxels ``x0 <= x < x1`` (the slice
                ``volume[z0:z1, y0:y1, x0:x1]``); fractional bounds are fine with a shape. The
                shape is then the box's output voxels, sampled as a whole decode samples the
                whole extent (:mod:`warpgauss.field.region`): a box on faces of a whole decode's grid
                returns that decode's crop, bit for bit. It costs its output voxels and the
                Gaussians that reach them, not the whole extent.
            device: Warp device (None: CUDA when present, else CPU).
            normalised: Return [0, 1] values instead of the source's units.
            progress: Optional callback(done, total).
            info: Optional dict that receives ``bricks_evaluated_share``: the share of 8^3
                bricks of the model grid some Gaussian reaches (the rest are written 0
                unevaluated; None for a box), ``clamped_voxels``: voxels whose value fell outside
                the source's range, and ``residual_applied`` (whether the residual's bound holds
                for the result: False where a residual exists but the grid or box is not on the
                encoded grid, which the result then says).
            residual: Apply the model's bounded residual (:mod:`warpgauss.format.residual`): True
                requires one (and the encoded grid: no shape, or a box of whole voxels at the
                encoded resolution); None (default) applies one where present and possible; False:
                the Gaussians alone. The residual is coded over the whole grid (its predictors
                interpolate across it): a bounded box costs the whole bounded decode, then the crop.

        Returns:
            (nz, ny, nx) float32 array (float64 where float32 cannot hold the value range, see
            :func:`warpgauss.field.analysis.denormalise`), within the source's [min, max]: a value the
            Gaussians put outside it (an overshoot at a sharp edge) is clamped. With a residual:
            the source's dtype, every valid voxel within the residual's bound of the source.
        """
        from ..field.analysis import denormalise
        from ..field.region import box_shape, check_box, crop, on_encoded_grid

        shape = _decode_shape(shape, shape_zyx, shape_xyz)
        if box is not None:
            box = check_box(box, self.shape_xyz)
            shape = box_shape(box) if shape is None else shape
        _check_decode_size(shape if shape is not None else self.shape_xyz)
        on_grid = on_encoded_grid(box, shape, self.shape_xyz)
        if residual and self.residual is None:
            raise WarpgaussError("this model has no residual (encode with --max-error for one); decode without --residual")
        if residual and not (on_grid and not normalised):
            fix = "give a box of whole voxels without --shape (or --normalised)" if box is not None else "drop --shape (or --normalised)"
            raise WarpgaussError(f"a residual applies on the encoded grid in source units; {fix}, or pass --no-residual")
        if residual is not False and self.residual is not None and on_grid and not normalised:
            out = self._decode_bounded(device, info)
            return out if box is None else crop(out, box)
        if info is not None:
            info["residual_applied"] = False
        gf = self.field(device)
        v = gf.decode(shape, box=box, progress=progress)
        if info is not None:
            info["bricks_evaluated_share"] = gf.active_fraction if box is None else None
            info["clamped_voxels"] = gf.clamped_voxels
        if normalised:
            return v
        lo, hi = self.value_range
        out = denormalise(v, lo, hi)
        if np.isfinite(lo) and np.isfinite(hi):  # float rounding of lo + v (hi - lo) stays in the source's range too
            np.clip(out, min(lo, hi), max(lo, hi), out=out)
        return out

    def to_pyvista(
        self,
        shape: tuple[int, int, int] | None = None,
        box=None,
        *,
        device: str | None = None,
        normalised: bool = False,
        residual: bool | None = None,
        name: str | None = None,
    ):
        """The decode as a ``pyvista.ImageData``, for a notebook (``model.to_pyvista().plot(volume=True)``)
        or any VTK pipeline: what ``warpgauss decode -o grid.vti`` writes, without the file.

        Args:
            shape: Output grid (nx, ny, nz), the order of ``ImageData.dimensions`` (None: the
                encoded grid, or ``box`` at the encoded resolution).
            box: A region, ``((x0, x1), (y0, y1), (z0, z1))`` in voxel coordinates of the encoded
                grid, as :meth:`decode` takes it.
            device: As :meth:`decode`.
            normalised: As :meth:`decode`.
            residual: As :meth:`decode`.
            name: The point-data array's name (default: the header's name, else "value").

        Returns:
            ``pyvista.ImageData`` of dimensions (nx, ny, nz), spacing and origin in the header's
            physical units (the first voxel's centre; a box's own), the decoded values as its
            active point scalars (x fastest), and field data ``residual_applied`` (1 where the
            residual's bound holds for the values, else 0).
        """
        from ..readers.write import image_data

        info: dict = {}
        data = self.decode(shape_xyz=shape, box=box, device=device, normalised=normalised, info=info, residual=residual)
        grid_shape = (data.shape[2], data.shape[1], data.shape[0])
        label = name or str(self.header.get("name") or "value")
        img = image_data(data, self.decoded_spacing(grid_shape, box), self.decoded_origin(grid_shape, box), label)
        img.set_active_scalars(label)
        img.field_data["residual_applied"] = np.array([int(bool(info.get("residual_applied")))], np.int8)
        return img

    def _decode_bounded(self, device: str | None, info: dict | None) -> np.ndarray:
        from .residual import DECODE_BYTES_PER_VOXEL, apply_residual, check_memory, prediction

        assert self.residual is not None
        check_memory(math.prod(self.shape_xyz), DECODE_BYTES_PER_VOXEL, "applying the residual to")
        from .interpolation import residual_device

        pred, _ = prediction(self, device)
        out = apply_residual(self.residual, pred, residual_device(device, pred.size))
        if info is not None:
            info.update(residual_applied=True, max_error=self.residual.info["bound"])
        return out

    def decoded_spacing(self, shape: tuple[int, int, int] | None = None, box=None) -> tuple[float, ...]:
        """Physical voxel spacing of a decode at ``shape`` (x, y, z) of the encoded grid's extent,
        or of ``box`` (see :meth:`decode`; shape None: the box at the encoded resolution)."""
        if box is not None:
            return self._box_geometry(shape, box)[0]
        sp = self.header["grid"]["spacing"]
        if shape is None:
            return tuple(float(s) for s in sp)
        return tuple(float(sp[a]) * self.shape_xyz[a] / int(shape[a]) for a in range(3))

    def decoded_origin(self, shape: tuple[int, int, int] | None = None, box=None) -> tuple[float, ...]:
        """Physical position of the first voxel centre of a decode at ``shape`` (of ``box``)."""
        if box is not None:
            return self._box_geometry(shape, box)[1]
        sp = self.header["grid"]["spacing"]
        org = self.header["grid"]["origin"]
        if shape is None:
            return tuple(float(o) for o in org)
        return tuple(float(org[a]) + float(sp[a]) * (0.5 * self.shape_xyz[a] / int(shape[a]) - 0.5) for a in range(3))

    def _box_geometry(self, shape, box) -> tuple[tuple[float, ...], tuple[float, ...]]:
        from ..field.region import box_shape, check_box, spacing_origin

        box = check_box(box, self.shape_xyz)
        return spacing_origin(self.header, box, box_shape(box) if shape is None else shape)
