"""A numcodecs codec: Zarr (and xarray, through Zarr) stores each chunk as a warpgauss model.

``WarpGauss(ratio=..., max_error=..., device=...)`` encodes a chunk (a numpy array) with
:func:`warpgauss.encode` and returns the model's ``.wgs`` bytes (:meth:`warpgauss.Model.to_bytes`),
which describe themselves (grid, value range, source dtype); ``decode`` evaluates the model on the
chunk's grid and returns it in the chunk's dtype, within ``max_error`` of the source on every
finite voxel where one was given. Registered as codec id ``"warpgauss"`` on import and through
numcodecs' ``numcodecs.codecs`` entry point, so ``numcodecs.get_codec({"id": "warpgauss", ...})``
finds it without an import.

Chunks:

- 3-D chunks are volumes, (nz, ny, nx) as numpy orders them; a 2-D chunk is encoded as a
  one-slice volume and decodes as ``(1, ny, nx)``, which Zarr (and ``out``) reshape to the
  chunk's shape. Other ranks, non-numeric dtypes and non-native byte orders are refused.
- A chunk with a single value (every finite voxel equal, or none finite) has no structure for
  Gaussians: it is stored as a small constant record (``b"WGSCONST"``, a JSON description and no
  model) and decodes to that value everywhere.
- Non-finite voxels are not kept: a decode has the model's value there.
- Each chunk is a model of its own with a header of about 2 KB: a small chunk spends most of its
  bytes on it, and a ratio its bytes cannot reach is refused (docs/guide/zarr.md measures it).

Only JSON values configure it (:meth:`WarpGauss.get_config`), and nothing read is evaluated:
``decode`` reads a model as :meth:`warpgauss.Model.from_bytes` validates it.
"""

from __future__ import annotations

import json
import math
import struct
import threading

import numpy as np

from .errors import WarpgaussError

try:
    from numcodecs.abc import Codec
    from numcodecs.compat import ensure_bytes, ensure_ndarray_like, ndarray_copy
    from numcodecs.registry import register_codec
except ImportError:  # the zarr extra is optional: importing warpgauss never needs it
    raise WarpgaussError("warpgauss.codec needs numcodecs: pip install 'warpgauss[zarr]'") from None

CONSTANT_MAGIC = b"WGSCONST"  # a constant chunk's record: magic, u32 JSON length, JSON
_CONST = struct.Struct("<8sI")
_PRESETS = ("paper", "fast", "quality")
_FORMATS = ("coded", "float32", "full", "compact96", "compact")
MAX_CHUNK_VOXELS = 1 << 31  # a constant record describing more is refused as damaged
# Zarr encodes and decodes chunks on a pool of threads; one chunk at a time goes to Warp (its CPU
# device runs a kernel on one thread, and a device is busy with one chunk's kernels anyway)
_WARP = threading.Lock()


def _positive(name: str, v, *, integer: bool = False, zero: bool = False) -> None:
    """Refuse ``v`` unless it is None or a finite positive number (an integer; >= 0 with ``zero``)."""
    if v is None:
        return
    kind = (int,) if integer else (int, float)
    ok = not isinstance(v, bool) and isinstance(v, kind) and math.isfinite(v) and (v >= 0 if zero else v > 0)
    if not ok:
        what = ("a non-negative" if zero else "a positive") + (" integer" if integer else " finite number")
        raise WarpgaussError(f"WarpGauss({name}=...) must be {what} or None, got {v!r}")


class WarpGauss(Codec):
    """Each chunk a fixed budget of Gaussians (:func:`warpgauss.encode` with the options below).

    Args:
        ratio: Compression ratio of each chunk's model (the Gaussians' bytes with ``max_error``);
            None with no ``budget``: :data:`warpgauss.encoding.driver.DEFAULT_RATIO`.
        max_error: A point-wise bound in the chunk's units: a residual makes every finite voxel
            of a decoded chunk lie within it of the source.
        budget: Gaussians per chunk instead of ``ratio``.
        iterations: Refinement iterations per chunk (None: the encoder's default, 1,500).
        samples: Samples per iteration (None: the encoder's default).
        preset: "paper", "fast" or "quality" (:func:`warpgauss.encode`).
        format: The model's payload format: "coded" (default), "float32" or "compact96".
        seed: Encoding seed: the same chunk, seed and device give the same bytes.
        device: Warp device that encodes and decodes ("cpu", "cuda:0"; None: CUDA when present).
    """

    codec_id = "warpgauss"

    def __init__(
        self,
        ratio: float | None = None,
        max_error: float | None = None,
        budget: int | None = None,
        iterations: int | None = None,
        samples: int | None = None,
        preset: str | None = None,
        format: str | None = None,
        seed: int = 0,
        device: str | None = None,
    ):
        _positive("ratio", ratio)
        _positive("max_error", max_error)
        _positive("budget", budget, integer=True)
        _positive("iterations", iterations, integer=True, zero=True)
        _positive("samples", samples, integer=True)
        _positive("seed", seed, integer=True, zero=True)
        if ratio is not None and budget is not None:
            raise WarpgaussError("WarpGauss takes one of ratio= and budget=, not both")
        for name, v, allowed in (("preset", preset, _PRESETS), ("format", format, _FORMATS)):
            if v is not None and v not in allowed:
                raise WarpgaussError(f"WarpGauss({name}={v!r}) is not one of {', '.join(allowed)}")
        if device is not None and not isinstance(device, str):
            raise WarpgaussError(f"WarpGauss(device=...) must be a Warp device name such as 'cpu' or 'cuda:0', got {device!r}")
        self.ratio = None if ratio is None else float(ratio)
        self.max_error = None if max_error is None else float(max_error)
        self.budget, self.iterations, self.samples = budget, iterations, samples
        self.preset, self.format, self.seed, self.device = preset, format, seed, device

    def get_config(self) -> dict:
        """The codec's id and options, JSON values only (:meth:`from_config` takes them back)."""
        keys = ("ratio", "max_error", "budget", "iterations", "samples", "preset", "format", "seed", "device")
        return {"id": self.codec_id, **{k: getattr(self, k) for k in keys}}

    def __repr__(self) -> str:
        given = {k: v for k, v in self.get_config().items() if k != "id" and v is not None}
        return f"WarpGauss({', '.join(f'{k}={v!r}' for k, v in given.items())})"

    def encode(self, buf) -> bytes:
        """The ``.wgs`` bytes of the chunk ``buf`` (a 3-D or 2-D numeric array), or its constant record."""
        from .encoding.entry import encode

        a = _chunk(buf)
        record = _constant_record(a)
        if record is not None:
            return record
        with _WARP:
            model = encode(
                a,
                budget=self.budget,
                ratio=self.ratio,
                max_error=self.max_error,
                iterations=self.iterations,
                samples=self.samples,
                preset=self.preset,
                format=self.format,
                seed=self.seed,
                device=self.device,
                self_test=False,
                evaluate=False,
                progress=False,
            )
        return model.to_bytes()

    def decode(self, buf, out=None):
        """The chunk that :meth:`encode` made ``buf`` of, in its dtype (into ``out`` where given)."""
        from .format.model import Model

        data = ensure_bytes(buf)
        if data[: len(CONSTANT_MAGIC)] == CONSTANT_MAGIC:
            return ndarray_copy(_from_constant(data), out)
        model = Model.from_bytes(data)
        dtype = _source_dtype(model.header["source"].get("dtype"))
        with _WARP:
            values = model.decode(device=self.device)
        return ndarray_copy(_as_dtype(values, dtype), out)


def _chunk(buf) -> np.ndarray:
    """``buf`` as a C-ordered 3-D array, or a one-line refusal saying why it is not a chunk."""
    a = np.asarray(ensure_ndarray_like(buf))
    if a.ndim == 2:
        a = a[None]
    if a.ndim != 3:
        raise WarpgaussError(
            f"the warpgauss codec encodes 3-D chunks (2-D as one slice), got a {a.ndim}-D one of shape {a.shape}; "
            "use it as the compressor of a 2-D or 3-D array, after no bytes filter"
        )
    if a.dtype.kind not in "iuf":
        raise WarpgaussError(f"the warpgauss codec encodes integer and float chunks, got dtype {a.dtype}; cast the array first")
    if not a.dtype.isnative:
        raise WarpgaussError(
            f"the warpgauss codec encodes native byte order, got dtype {a.dtype.str}; store the array as {a.dtype.newbyteorder('=')}"
        )
    return np.ascontiguousarray(a)


def _constant_record(a: np.ndarray) -> bytes | None:
    """The record of a chunk whose finite voxels hold one value (or that has none), else None."""
    finite = np.isfinite(a) if a.dtype.kind == "f" else None
    values = a if finite is None else a[finite]
    if values.size and values.min() != values.max():
        return None
    value = a.dtype.type(values.flat[0]) if values.size else a.flat[0]  # none finite: its first (a NaN or inf)
    desc = {"dtype": a.dtype.str, "shape": [int(s) for s in a.shape], "value": np.asarray(value, a.dtype).tobytes().hex()}
    body = json.dumps(desc, sort_keys=True).encode()
    return _CONST.pack(CONSTANT_MAGIC, len(body)) + body


def _from_constant(data: bytes) -> np.ndarray:
    def bad(what: str) -> WarpgaussError:
        return WarpgaussError(f"a warpgauss constant chunk record {what}: the chunk is damaged; rewrite it")

    if len(data) < _CONST.size:
        raise bad("is shorter than its prefix")
    _, n = _CONST.unpack_from(data)
    if len(data) != _CONST.size + n:
        raise bad(f"is {len(data)} bytes, its prefix says {_CONST.size + n}")
    try:
        desc = json.loads(data[_CONST.size :].decode("utf-8"))
    except (UnicodeDecodeError, ValueError):
        raise bad("is not UTF-8 JSON") from None
    if not isinstance(desc, dict) or not {"dtype", "shape", "value"} <= desc.keys():
        raise bad("lacks its dtype, shape or value")
    dtype = _source_dtype(desc["dtype"])
    shape = desc["shape"]
    if not (isinstance(shape, list) and len(shape) == 3 and all(isinstance(s, int) and not isinstance(s, bool) and s > 0 for s in shape)):
        raise bad(f"has shape {shape!r}, not three positive integers")
    if math.prod(shape) > MAX_CHUNK_VOXELS:
        raise bad(f"claims {math.prod(shape)} voxels, more than a chunk holds ({MAX_CHUNK_VOXELS})")
    try:
        raw = bytes.fromhex(desc["value"]) if isinstance(desc["value"], str) else b""
    except ValueError:
        raw = b""
    if len(raw) != dtype.itemsize:
        raise bad(f"has a value that is not {dtype.itemsize} bytes of hex")
    return np.full(shape, np.frombuffer(raw, dtype)[0], dtype)


def _source_dtype(name) -> np.dtype:
    """The dtype a header or record names, refused unless a native integer or float one."""
    try:
        dtype = np.dtype(name) if isinstance(name, str) else None
    except TypeError:
        dtype = None
    if dtype is None or dtype.kind not in "iuf":
        raise WarpgaussError(f"the chunk's model names source dtype {name!r}, not an integer or float one; the chunk is damaged")
    return dtype.newbyteorder("=")


def _as_dtype(values: np.ndarray, dtype: np.dtype) -> np.ndarray:
    """A decode in the chunk's dtype: integers rounded and clipped to the dtype's range."""
    if values.dtype == dtype:
        return values
    if dtype.kind in "iu":
        info = np.iinfo(dtype)
        return np.clip(np.rint(values), info.min, info.max).astype(dtype)
    return values.astype(dtype)


register_codec(WarpGauss)
