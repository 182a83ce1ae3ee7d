"""A bounded residual: the Gaussians as a predictor, plus what makes every decoded voxel lie
within an absolute bound E of the source (``warpgauss encode --max-error``).

Coding (SZ's linear quantisation, applied as cuSZ does: quantise first, then predict the integers)::

    s   = 2 E (1 - 2^-30)            float sources: the lattice step
        = 2 floor(E) + 1             integer sources (odd: no ties, |V - s k| <= floor(E) exactly)
    kV  = round(V / s)               the source on the lattice: decoded value = s kV, cast to its dtype
    kP  = round(P / s)               P: the Gaussians in float64, source units (kernels/predict.py)
    symbols, by the predictor that codes smallest (all are tried):
        "gaussians"          kV - kP
        "gaussians+lorenzo"  L(kV - kP)     L: 3D Lorenzo (first differences along x, y and z)
        "lorenzo"            L(kV)          (the Gaussians unused: SZ's own predictor)

The decoded value ``s kV`` depends on the prediction only through ``kP``, an integer: a reader
whose float64 prediction differs from the encoder's by less than ``MARGIN_REL`` of the value range
(measured differences between the CPU and CUDA are about 1e-15) gets the same kP except where
P / s lies within that margin of a rounding boundary, or where a pair lies on the 5-sigma cut
(``fragile``); those voxels are stored outright (*literals*, the source value exactly), as is
any voxel whose lattice value, cast to the source's dtype, is not within E (a bound below the
dtype's resolution) or does not fit the lattice. So every valid voxel decodes within E on every
device, bit for bit the same; masked voxels (NaN, Inf, the fill value) carry no symbol and decode
to the fill value (NaN where none was given), from a stored mask.

Symbols are zigzag-mapped to the narrowest of 1, 2, 4 or 8 bytes, split into byte planes and
coded with Zstandard, as the coded model format is (:mod:`warpgauss.coded`).

The payload is a sequence of Zstandard frames (symbols, literal positions, literal values, mask)
whose lengths the header's ``residual`` entry lists; reading decompresses each into at most its
declared size and refuses a frame that claims more than Zstandard can produce from its bytes.
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .coded import ZSTD_LARGE_RAW, zstandard_module
from .errors import WarpgaussError

DEFAULT_RATIO = 200.0  # the Gaussians' share of a bounded file when no budget is given (see docs/guide/bounded.md)
MARGIN_REL = 1e-9  # of the value range: how far two readers' float64 predictions may differ
ZSTD_MAX_RATIO = 1 << 16  # Zstandard never expands past ~32,768 : 1 (an RLE block of 128 KiB in 4 bytes)
ZSTD_LEVEL = 9  # streams up to ZSTD_LARGE_RAW; larger ones level 3 (symbols past a prediction are noise-like)
PREDICTORS = ("gaussians", "gaussians+lorenzo", "lorenzo")
STREAMS = ("symbols", "positions", "values", "mask")
_LATTICE_LIMIT = float(1 << 50)  # |V / s| beyond this is stored outright (keeps every int64 sum exact)
DTYPES = ("int8", "uint8", "int16", "uint16", "int32", "uint32", "int64", "uint64", "float32", "float64")


def check_bound_options(max_error: float | None, max_error_rel: float | None) -> None:
    """Refuse a bound that is not one positive finite number, before any work."""
    if max_error is not None and max_error_rel is not None:
        raise WarpgaussError("give --max-error or --max-error-rel, not both")
    for name, v in (("--max-error", max_error), ("--max-error-rel", max_error_rel)):
        if v is not None and not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
            raise WarpgaussError(f"{name} must be a positive finite number, got {v!r}")


def resolve_bound(max_error: float | None, max_error_rel: float | None, vmin: float, vmax: float) -> float:
    """The absolute bound E in source units (``max_error_rel`` is a share of the value range)."""
    if max_error is not None:
        return float(max_error)
    assert max_error_rel is not None
    return float(max_error_rel) * (float(vmax) - float(vmin))


@dataclass
class Residual:
    """A coded residual: the header's ``residual`` entry and where its bytes are (in memory, or a
    span of a model file read on demand and checked against its SHA-256)."""

    info: dict
    data: bytes | None = None
    path: Path | None = None
    offset: int = 0

    @property
    def nbytes(self) -> int:
        return int(self.info["payload_bytes"])

    def payload(self) -> bytes:
        if self.data is not None:
            return self.data
        assert self.path is not None
        try:
            with open(self.path, "rb") as f:
                f.seek(self.offset)
                data = f.read(self.nbytes)
        except OSError as e:
            raise WarpgaussError(f"cannot read the residual of {self.path}: {e.strerror}") from None
        if len(data) != self.nbytes or hashlib.sha256(data).hexdigest() != self.info["sha256"]:
            raise WarpgaussError(f"{self.path}: residual checksum mismatch: the file is damaged or changed; restore it or re-encode")
        return data


# -- the lattice ---------------------------------------------------------------------------------
def _lattice(bound: float, dtype: np.dtype) -> tuple[float, bool, np.dtype]:
    """(step s, integer lattice?, decoded dtype) for a bound in source units.

    An integer source keeps its dtype on the odd integer lattice 2 floor(E) + 1 unless the float
    lattice 2E is coarser (E < 1, or its fraction >= 1/2: at E = 0.646 the integer lattice is
    lossless, 1 against 1.29): then it decodes to float32 (float64 past 16-bit integers)."""
    if dtype.kind in "iu" and bound >= 1.0 and bound - math.floor(bound) < 0.5:
        return float(2 * math.floor(bound) + 1), True, dtype
    out = dtype if dtype.kind == "f" else np.dtype(np.float32 if dtype.itemsize <= 2 else np.float64)
    return 2.0 * bound * (1.0 - 2.0**-30), False, out


def _on_lattice(k: np.ndarray, step: float, integer: bool, dtype: np.dtype) -> np.ndarray:
    """The decoded values s k in the source's dtype (integers clipped to its range: the source
    lies within it, so clipping never moves a value away from it)."""
    if integer:
        info = np.iinfo(dtype)
        v = k * np.int64(step)
        return np.clip(v, max(info.min, -(2**62)), min(info.max, 2**62)).astype(dtype)
    with np.errstate(over="ignore", invalid="ignore"):
        return (k.astype(np.float64) * step).astype(dtype)


def _round_index(x: np.ndarray, step: float, integer: bool) -> np.ndarray:
    """round(x / s) as int64 (x integer-valued on an integer lattice: exact floor division)."""
    if integer and x.dtype.kind in "iu":
        k = int(step) // 2
        return np.floor_divide(x.astype(np.int64) + k, int(step))
    return np.rint(x / step).astype(np.int64)


def _lorenzo(x: np.ndarray) -> np.ndarray:
    for a in range(3):
        x = np.diff(x, axis=a, prepend=np.zeros_like(x[:1] if a == 0 else x[:, :1] if a == 1 else x[:, :, :1]))
    return x


def _unlorenzo(x: np.ndarray) -> np.ndarray:
    for a in (2, 1, 0):
        x = np.cumsum(x, axis=a)
    return x


def _zigzag(d: np.ndarray) -> np.ndarray:
    return ((d << 1) ^ (d >> 63)).view(np.uint64)


def _unzigzag(u: np.ndarray) -> np.ndarray:
    return (u >> np.uint64(1)).view(np.int64) ^ -(u & np.uint64(1)).view(np.int64)


def _width(u: np.ndarray) -> int:
    top = int(u.max()) if u.size else 0
    return next(w for w in (1, 2, 4, 8) if top < 1 << (8 * w))


def _planes(u: np.ndarray, width: int) -> bytes:
    b = u.astype(f"<u{width}").view(np.uint8).reshape(-1, width)
    return b.T.tobytes()  # byte planes: the high bytes, mostly 0, code apart from the low ones


def _from_planes(raw: bytes, n: int, width: int) -> np.ndarray:
    b = np.frombuffer(raw, np.uint8).reshape(width, n).T
    return np.ascontiguousarray(b).view(f"<u{width}").reshape(n).astype(np.uint64)


def _compress(raw: bytes, level: int | None = None) -> bytes:
    zstd = zstandard_module()
    lvl = level if level is not None else (ZSTD_LEVEL if len(raw) <= ZSTD_LARGE_RAW else 3)
    return zstd.ZstdCompressor(level=lvl, write_checksum=True).compress(raw)


def _decompress(frame: bytes, size: int, what: str) -> bytes:
    """A frame's bytes, refused unless it yields exactly ``size`` bytes (checked before allocating
    against what Zstandard can produce from the frame's length)."""
    if size > len(frame) * ZSTD_MAX_RATIO + 1024:
        raise WarpgaussError(
            f"the residual's {what} claim {size:,} bytes from a {len(frame):,}-byte frame, more than Zstandard can produce; the file is damaged"
        )
    zstd = zstandard_module()
    try:
        raw = zstd.ZstdDecompressor().decompress(frame, max_output_size=max(size, 1))
    except zstd.ZstdError:
        raise WarpgaussError(f"the residual's {what} do not decompress: the file is damaged; restore it or re-encode") from None
    if len(raw) != size:
        raise WarpgaussError(f"the residual's {what} hold {len(raw):,} bytes where the header says {size:,}; the file is damaged")
    return raw


# -- coding --------------------------------------------------------------------------------------
def prediction(model, device: str | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(P, fragile): the model in float64 source units at every voxel of its grid, clamped to the
    source's range, and the voxels where readers could disagree (see :mod:`warpgauss.kernels.predict`)."""
    from .field import GaussianField

    gf = GaussianField(model.params, model.shape_xyz, device=device)
    v, fragile = gf.predict(model.params)
    lo, hi = model.value_range
    p = lo + v * (hi - lo)
    np.clip(p, lo, hi, out=p)
    return p, fragile


def code_residual(
    source: np.ndarray,
    valid: np.ndarray | None,
    pred: np.ndarray,
    fragile: np.ndarray,
    bound: float,
    value_range: tuple[float, float],
    *,
    fill_value: float | None = None,
    predictors: tuple[str, ...] = PREDICTORS,
) -> tuple[Residual, dict]:
    """Code ``source`` against the prediction so that every valid voxel decodes within ``bound``
    (in the source's dtype, or float where the bound admits values between its integers).

    Args:
        source: (nz, ny, nx) source values in their own dtype.
        valid: Usable voxels (None: all); the rest carry nothing and decode to ``fill_value``.
        pred, fragile: From :func:`prediction` on the model the residual goes with.
        bound: E in source units (> 0).
        value_range: The model's (min, max) (the margin is a share of it).
        predictors: Those to try (the smallest coding wins).

    Returns:
        (the residual, facts for the report: sizes of every predictor tried, literals, seconds).
    """
    dtype = np.dtype(source.dtype)
    if dtype.name not in DTYPES:
        raise WarpgaussError(f"a bounded residual takes integer or float32/float64 volumes, not {dtype.name}")
    if not (math.isfinite(bound) and bound > 0):
        raise WarpgaussError(f"the error bound must be a positive finite number, got {bound!r}")
    lo, hi = value_range
    span = hi - lo if hi > lo else max(abs(lo), 1.0)  # a constant volume: its magnitude
    margin = MARGIN_REL * span + 1e-14 * max(abs(lo), abs(hi))  # and float64 rounding at the values' magnitude
    step, integer, out_dtype = _lattice(bound, dtype)
    ok = np.ones(source.shape, bool) if valid is None else valid
    src64 = source.astype(np.float64)
    with np.errstate(invalid="ignore", over="ignore"):
        fits = ok & (np.abs(src64) < _LATTICE_LIMIT * step)
        kv = np.zeros(source.shape, np.int64)
        kv[fits] = _round_index(source[fits], step, integer)
        t = pred / step
        kp = np.rint(t).astype(np.int64)
        ambiguous = np.abs(t - np.floor(t) - 0.5) <= margin / step + 4e-16 * np.abs(t)
    out = _on_lattice(kv, step, integer, out_dtype)
    err = np.abs(out.astype(np.float64) - src64)
    bad = ok & ~(fits & (err <= bound))  # below the dtype's resolution, or off the lattice
    facts: dict = {"sizes": {}}
    best: tuple[int, str, dict[str, bytes], np.ndarray, int] | None = None
    for name in predictors:
        literal = bad | (ok & (fragile | ambiguous)) if name != "lorenzo" else bad
        k = np.where(ok & ~literal, kv, kp)  # nothing to code where a voxel is masked or stored outright
        sym = k - kp if name == "gaussians" else _lorenzo(k - kp) if name == "gaussians+lorenzo" else _lorenzo(k)
        u = _zigzag(sym.ravel())
        width = _width(u)
        streams = _streams(u, width, literal, source.astype(out_dtype, copy=False), valid)
        size = sum(len(b) for b in streams.values())
        facts["sizes"][name] = size
        if best is None or size < best[0]:
            best = (size, name, streams, literal, width)
    assert best is not None
    size, name, streams, literal, best_width = best
    data = b"".join(streams[s] for s in STREAMS)
    info = {
        "bound": float(bound),
        "bound_rel": float(bound / span),
        "dtype": out_dtype.name,
        "source_dtype": dtype.name,
        "step": step,
        "lattice": "integer" if integer else "float",
        "predictor": name,
        "symbol_bytes": best_width,
        "streams": {s: len(streams[s]) for s in STREAMS},
        "literals": int(literal.sum()),
        "masked": 0 if valid is None else int((~valid).sum()),
        "masked_value": None if fill_value is None else float(fill_value),
        "margin": margin,
        "payload_bytes": len(data),
        "sha256": hashlib.sha256(data).hexdigest(),
    }
    facts.update(predictor=name, literals=info["literals"], fragile=int((ok & fragile).sum()), bytes=len(data))
    return Residual(info, data), facts


def _streams(u: np.ndarray, width: int, literal: np.ndarray, source: np.ndarray, valid: np.ndarray | None) -> dict[str, bytes]:
    pos = np.flatnonzero(literal.ravel()).astype(np.int64)
    gaps = np.diff(pos, prepend=np.int64(0)).astype("<u8")
    return {
        "symbols": _compress(_planes(u, width)),
        "positions": _compress(_planes(gaps, 8)),
        "values": _compress(np.ascontiguousarray(source.ravel()[pos]).astype(source.dtype.newbyteorder("<")).tobytes()),
        "mask": b"" if valid is None else _compress(np.packbits(~valid.ravel()).tobytes()),
    }


# -- decoding ------------------------------------------------------------------------------------
def check_info(info, n_voxels: int) -> str | None:
    """What is wrong with a header's ``residual`` entry (None: usable), before anything is read."""
    if not isinstance(info, dict):
        return "'residual' is not an object"
    if info.get("dtype") not in DTYPES:
        return f"residual dtype {info.get('dtype')!r} is not one of {', '.join(DTYPES)}"
    if info.get("predictor") not in PREDICTORS:
        return f"residual predictor {info.get('predictor')!r} is not one of {', '.join(PREDICTORS)}"
    if info.get("lattice") not in ("integer", "float"):
        return f"residual lattice {info.get('lattice')!r} is not integer or float"
    for key in ("bound", "step", "margin"):
        v = info.get(key)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0 or (key != "margin" and v <= 0):
            return f"residual {key} {v!r} is not a positive finite number"
    if info["lattice"] == "integer" and (info["step"] != int(info["step"]) or info["step"] > 2**31):
        return f"residual integer step {info['step']!r} is not a whole number"
    if info.get("symbol_bytes") not in (1, 2, 4, 8):
        return f"residual symbol width {info.get('symbol_bytes')!r} is not 1, 2, 4 or 8 bytes"
    streams = info.get("streams")
    if not (isinstance(streams, dict) and all(_count(streams.get(s)) for s in STREAMS)):
        return f"residual streams {streams!r} are not byte counts"
    if not all(_count(info.get(k)) for k in ("literals", "masked", "payload_bytes")):
        return "residual literal, mask or byte counts are not non-negative integers"
    if info["literals"] > n_voxels or info["masked"] > n_voxels:
        return f"the residual claims more literals or masked voxels than the grid's {n_voxels:,}"
    if sum(streams[s] for s in STREAMS) != info["payload_bytes"]:
        return "residual stream lengths do not add up to its payload bytes"
    if not (isinstance(info.get("sha256"), str) and len(info["sha256"]) == 64):
        return "residual sha256 is not a 64-digit hex string"
    mv = info.get("masked_value")
    if mv is not None and not (isinstance(mv, (int, float)) and not isinstance(mv, bool)):
        return f"residual masked value {mv!r} is not a number"
    return None


def _count(v) -> bool:
    return not isinstance(v, bool) and isinstance(v, int) and v >= 0


def apply_residual(res: Residual, pred: np.ndarray) -> np.ndarray:
    """The bounded decode: the prediction (:func:`prediction`) plus the residual, in the source's dtype."""
    info = res.info
    shape = pred.shape
    n = int(pred.size)
    problem = check_info(info, n)
    if problem is not None:
        raise WarpgaussError(f"the header's {problem}; the file is damaged")
    dtype = np.dtype(info["dtype"])
    step, integer, width = float(info["step"]), info["lattice"] == "integer", int(info["symbol_bytes"])
    data = res.payload()
    frames, at = {}, 0
    for s in STREAMS:
        frames[s] = data[at : at + info["streams"][s]]
        at += info["streams"][s]
    u = _from_planes(_decompress(frames["symbols"], n * width, "symbols"), n, width)
    sym = _unzigzag(u).reshape(shape)
    kp = np.rint(pred / step).astype(np.int64)
    name = info["predictor"]
    if name == "gaussians":
        k = sym + kp
    elif name == "gaussians+lorenzo":
        k = _unlorenzo(sym) + kp
    else:
        k = _unlorenzo(sym)
    out = _on_lattice(k, step, integer, dtype).ravel()
    count = int(info["literals"])
    gaps = _from_planes(_decompress(frames["positions"], 8 * count, "literal positions"), count, 8).view(np.int64)
    pos = np.cumsum(gaps)
    if count and (pos.min() < 0 or pos.max() >= n):
        raise WarpgaussError("the residual's literal positions fall outside the grid; the file is damaged")
    values = np.frombuffer(_decompress(frames["values"], count * dtype.itemsize, "literal values"), dtype.newbyteorder("<"))
    out[pos] = values
    if info["masked"]:
        raw = _decompress(frames["mask"], (n + 7) // 8, "mask")
        masked = np.unpackbits(np.frombuffer(raw, np.uint8), count=n).astype(bool)
        if int(masked.sum()) != info["masked"]:
            raise WarpgaussError("the residual's mask does not hold the masked voxels its header counts; the file is damaged")
        mv = info["masked_value"]
        if mv is None:
            mv = math.nan if dtype.kind == "f" else 0
        out[masked] = mv
    return out.reshape(shape)


def verify(res: Residual, pred: np.ndarray, source: np.ndarray, valid: np.ndarray | None) -> dict:
    """Decode as a reader does and check every valid voxel against the bound (a violation is a bug,
    raised, never a warning). Returns the measured maximum error and PSNR (range-normalised, as
    :mod:`warpgauss.evaluate` scores)."""
    from .evaluate import psnr_from_mse

    out = apply_residual(res, pred)
    err = out.astype(np.float64) - source.astype(np.float64)
    if valid is not None:
        err = err[valid]
    worst = float(np.abs(err).max()) if err.size else 0.0
    bound = float(res.info["bound"])
    if not worst <= bound:
        raise WarpgaussError(
            f"internal error: the residual decodes {worst:.6g} from the source, beyond its bound {bound:.6g}; please report this"
        )
    rng = float(res.info["bound"]) / float(res.info["bound_rel"])
    mse = float(np.mean((err / rng) ** 2)) if err.size else 0.0
    return {"max_abs_error": worst, "psnr_db": psnr_from_mse(mse)}
