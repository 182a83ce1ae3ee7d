"""A bounded residual: the Gaussians as a predictor, plus what makes every decoded voxel lie
within an absolute bound E of the source (``warpgauss encode --max-error``).

Coding is SZ's: each voxel is predicted from what a reader already has, the error of that
prediction quantised with step 2E (error feedback: |error| <= E by construction), and the
quantisation indices q entropy-coded. The predictors are tried and the smallest coding kept::

    "gaussians"          P                       P: the Gaussians in float64, source units (kernels/predict.py)
    "gaussians+interp"   P + I(decoded V - P)    I: SZ3's interpolation (cubic, level by level, along z, y, x)
    "interp"             I(decoded V)            (the Gaussians unused: SZ3's own predictor)

each interpolation also linear ("interp-linear", "gaussians+interp-linear"), as SZ3 chooses; the
Gaussians plus interpolation are coded only with the kind that coded smaller alone.

The interpolation runs on decoded values in float64 numpy, or as Warp kernels on the encode's
device with floating-point contraction off (:mod:`warpgauss.kernels.interp`; the same operations,
so the same bits, on every machine) and never on P: a reader's prediction enters only as the final ``P + r``. Where
a reader's float64 prediction may differ from the encoder's (by less than ``MARGIN_REL`` of the
value range: CPU against CUDA measured about 1e-15), the step keeps that margin and a voxel is
checked at both ends of it; a voxel with a pair on the 5-sigma cut (``fragile``: a reader may
count the term or not), or whose value the decoded dtype cannot hold within E, is stored outright
(a *literal*, the source value exactly). So every valid voxel decodes within E on every device.

An integer source keeps its dtype on the odd integer step 2 floor(E) + 1 (|error| <= floor(E)),
the prediction rounded to an integer (a prediction within the margin of .5 is a literal), unless
the float step 2E is coarser (E < 1, or a fraction >= 1/2): then it decodes to float. Masked
voxels (NaN, Inf, the fill value) carry nothing (q = 0) and decode to the fill value (NaN where
none was given), from a stored mask.

The interpolation's axis order (``axes``: which axis each level interpolates first) is chosen on a
central block of the source, and the q's are stored in the axis order (``layout``) that codes
smallest: on the three head MRIs at 1e-2 and 1e-3 of the range, x before z before y coded the
residual 4-17 % smaller than z, y, x, and storing mni_icbm152's q's with x in the middle 1.4-1.6x
smaller than the raster at 1e-3 (benchmarks/bounded/README.md). The q's are zigzag-mapped to the
narrowest of 1, 2, 4 or 8 bytes, split into byte planes and coded with Zstandard, as the coded
model format is (:mod:`warpgauss.format.coded`), or bzip2 where that is smaller. The payload is a sequence of
Zstandard frames (q's, literal positions, literal values, mask) whose lengths the header's
``residual`` entry lists; reading decompresses each into at most its declared size and refuses a
frame that claims more than Zstandard can produce from its bytes.
"""

from __future__ import annotations

import hashlib
import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import WarpgaussError
from .interpolation import AXES, FLAT, ORDERS, cast, decoded, quantiser
from .planes import CODECS, decompress, from_planes, unzigzag
from .residual_coding import (  # noqa: F401 (CODE_BYTES_PER_VOXEL: read here by the encode's memory check)
    CODE_BYTES_PER_VOXEL,
    MIN_FRAME_BYTES,
    PREDICTORS,
    STREAMS,
    Coder,
    final_symbols,
)
from .residual_coding import parts as _parts

# the Gaussians' ratio in a bounded file when no budget is given: at 1e-2..1e-4 of the range, 1000
# gave a smaller whole file than 300 on 12 of 15 (volume, bound) pairs (three head MRIs, vortex and
# interface at 256^3; benchmarks/results/bounded/bounded_rd256_h200.json). The residual alone, with
# no Gaussians, was smaller still on 13 of 15: the Gaussians are there to be rendered, and pay as a
# predictor only on mean_reg2mean at 1e-2 and 1e-3
DEFAULT_RATIO = 1000.0
MIN_GAUSSIAN_BYTES = 8192  # and at least this (a small volume's thousandth holds no Gaussian beside its header)
MARGIN_REL = 1e-9  # of the value range: how far two readers' float64 predictions may differ
DTYPES = ("int8", "uint8", "int16", "uint16", "int32", "uint32", "int64", "uint64", "float32", "float64")


DECODE_BYTES_PER_VOXEL = 48


def check_memory(n_voxels: int, per_voxel: int, what: str) -> None:
    """Refuse, before the work, a residual this machine's memory cannot code or apply in one piece."""
    from ..core.limits import available_memory

    need, free = n_voxels * per_voxel, available_memory()
    if free is not None and need > free:
        raise WarpgaussError(
            f"{what} {n_voxels:,} voxels needs about {need / 2**30:.1f} GiB of memory, {free / 2**30:.1f} GiB are available; "
            "a bounded residual is coded in memory: use a machine with more, or encode without --max-error"
        )


@dataclass(frozen=True)
class Bound:
    """What a bounded encode asks for: exactly one of a point-wise bound in source units
    (``max_error``), as a share of the value range (``max_error_rel``), or the full-grid PSNR the
    decode must reach (``psnr``, dB: the largest bound that reaches it, searched)."""

    max_error: float | None = None
    max_error_rel: float | None = None
    psnr: float | None = None

    @property
    def given(self) -> bool:
        return any(v is not None for v in (self.max_error, self.max_error_rel, self.psnr))

    def check(self) -> None:
        """Refuse anything but one positive finite number, before any work."""
        named = [
            (n, v)
            for n, v in (("--max-error", self.max_error), ("--max-error-rel", self.max_error_rel), ("--psnr", self.psnr))
            if v is not None
        ]
        if len(named) > 1:
            raise WarpgaussError(f"give one of --max-error, --max-error-rel and --psnr, not {' and '.join(n for n, _ in named)}")
        for name, v in named:
            if isinstance(v, bool) or not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise WarpgaussError(f"{name} must be a positive finite number, got {v!r}")

    def absolute(self, vmin: float, vmax: float) -> float:
        """E in source units (for ``psnr``: the bound that guarantees it, MSE <= E^2; the search
        starts there)."""
        span = float(vmax) - float(vmin) if vmax > vmin else max(abs(float(vmin)), 1.0)
        if self.max_error is not None:
            return float(self.max_error)
        if self.max_error_rel is not None:
            return float(self.max_error_rel) * span
        assert self.psnr is not None
        return span * 10.0 ** (-float(self.psnr) / 20.0)


PSNR_TRIES = 4  # codings after the guaranteed bound when --psnr searches the largest bound reaching it


def code_for_psnr(source, valid, pred, fragile, target_db: float, value_range, fill_value=None, device=None) -> tuple[Residual, dict, dict]:
    """The residual of the largest bound whose decode reaches ``target_db`` on the full grid: from
    the bound that guarantees it (E = range 10^(-P/20): MSE <= E^2) up to sqrt(3) x 2 that (a
    uniform error has MSE E^2 / 3), bisected in log E over :data:`PSNR_TRIES` codings.
    Returns (residual, coding facts, measured check) of the largest that reached it."""
    lo, hi = value_range
    e0 = Bound(psnr=target_db).absolute(lo, hi)
    res, facts = code_residual(source, valid, pred, fragile, e0, value_range, fill_value=fill_value, device=device)
    best = (res, facts, verify(res, pred, source, valid, value_range, device))
    low, high = math.log(e0), math.log(e0 * 2.0 * math.sqrt(3.0))
    tried = [e0]
    for _ in range(PSNR_TRIES):
        mid = 0.5 * (low + high)
        e = math.exp(mid)
        res, facts = code_residual(source, valid, pred, fragile, e, value_range, fill_value=fill_value, device=device)
        check = verify(res, pred, source, valid, value_range, device)
        tried.append(e)
        if check["psnr_db"] >= target_db:
            best, low = (res, facts, check), mid
        else:
            high = mid
    best[2]["psnr_search"] = {"target_db": target_db, "bounds_tried": tried, "chosen": best[0].info["bound"]}
    return best


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


# -- the quantiser ------------------------------------------------------------------------------
def prediction(model, device: str | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(P, fragile): the model in float64 source units at every voxel of its grid, clamped to the
    source's range, and the voxels where readers could disagree (see :mod:`warpgauss.kernels.predict`)."""
    from ..field.gaussians import GaussianField

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
    device: str | None = None,
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
        device: Where the interpolation passes run as Warp kernels (the same bytes; None: numpy).

    Returns:
        (the residual, facts for the report: sizes of every predictor tried, literals, seconds).
    """
    dtype = np.dtype(source.dtype)
    if dtype.name not in DTYPES:
        raise WarpgaussError(f"a bounded residual takes integer or float32/float64 volumes, not {dtype.name}")
    if not (math.isfinite(bound) and bound > 0):
        raise WarpgaussError(f"the error bound must be a positive finite number, got {bound!r}")
    bound = float(bound)
    lo, hi = float(value_range[0]), float(value_range[1])
    span = hi - lo if hi > lo else max(abs(lo), 1.0)  # a constant volume: its magnitude
    margin = MARGIN_REL * span + 1e-14 * max(abs(lo), abs(hi))  # and float64 rounding at the values' magnitude
    step, integer, out_dtype = quantiser(bound, margin, dtype)
    coder = Coder(source, valid, pred, fragile, bound, margin, step, integer, out_dtype, device)
    facts: dict = {"sizes": {}}
    size, name, streams, literal, best_width, best_u = coder.best(predictors, facts["sizes"])
    t0 = time.perf_counter()
    streams["symbols"], codec, layout = final_symbols(best_u)
    coder.seconds["final"] = time.perf_counter() - t0
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
        "symbols_codec": codec,
        "axes": coder.axes,
        "levels": list(coder.levelwise.get(_parts(name)[1], FLAT)),
        "layout": layout,
        "streams": {s: len(streams[s]) for s in STREAMS},
        "literals": int(literal.sum()),
        "masked": 0 if valid is None else int((~valid).sum()),
        "masked_value": None if fill_value is None else float(fill_value),
        "margin": margin,
        "payload_bytes": len(data),
        "sha256": hashlib.sha256(data).hexdigest(),
    }
    facts.update(
        predictor=name,
        axes=coder.axes,
        levels=info["levels"],
        layout=layout,
        literals=info["literals"],
        fragile=int((coder.ok & fragile).sum()),
        bytes=len(data),
        seconds=coder.seconds,
    )
    return Residual(info, data), facts


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
    if info.get("symbols_codec") not in CODECS:
        return f"residual symbols codec {info.get('symbols_codec')!r} is not one of {', '.join(CODECS)}"
    for key in ("axes", "layout"):
        if info.get(key, AXES) not in ORDERS:
            return f"residual {key} {info.get(key)!r} is not one of {', '.join(ORDERS)}"
    lv = info.get("levels", list(FLAT))
    if not (
        isinstance(lv, list)
        and len(lv) == 2
        and all(isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in lv)
        and 1 <= lv[0] <= 4
        and 1 <= lv[1] <= 64
    ):
        return f"residual levels {lv!r} are not [alpha, beta] with 1 <= alpha <= 4 and 1 <= beta <= 64"
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
    return _claims(info)


def _claims(info: dict) -> str | None:
    """What in a residual's description (its simple fields checked) claims more than its other
    fields hold: the bound it states must follow from its step, margin and lattice as
    :func:`quantiser` made them (the finest level's step is the widest), its decoded dtype must be
    one its lattice gives, its relative bound a positive number, and its streams as long as its
    counts need (a frame of nothing is 9 bytes and more)."""
    bound, step, margin = float(info["bound"]), float(info["step"]), float(info["margin"])
    dtype = np.dtype(info["dtype"])
    rel = info.get("bound_rel")
    if isinstance(rel, bool) or not isinstance(rel, (int, float)) or not math.isfinite(rel) or rel <= 0:
        return f"residual relative bound {rel!r} is not a positive finite number"
    src = info.get("source_dtype", info["dtype"])
    if src not in DTYPES:
        return f"residual source dtype {src!r} is not one of {', '.join(DTYPES)}"
    if info["lattice"] == "integer":
        if dtype.kind not in "iu" or src != info["dtype"]:
            return f"an integer-lattice residual decodes to its source's integers, not {info['dtype']} from {src}"
        if int(step) % 2 != 1 or (int(step) - 1) // 2 > bound:
            return f"residual integer step {step:g} does not hold its bound {bound:g} (an odd step of at most 2 x bound + 1)"
    else:
        if dtype.kind != "f":
            return f"a float-lattice residual decodes to floats, not {info['dtype']}"
        if not margin < bound or step > 2.0 * (bound - margin):
            return f"residual step {step:g} and margin {margin:g} do not hold its bound {bound:g} (step <= 2 x (bound - margin))"
    streams = info["streams"]
    need = {"symbols": True, "positions": info["literals"] > 0, "values": info["literals"] > 0, "mask": info["masked"] > 0}
    for name, needed in need.items():
        if needed and streams[name] < MIN_FRAME_BYTES:
            return f"residual {name} stream of {streams[name]} bytes cannot hold what its counts say"
    return None


def _count(v) -> bool:
    return not isinstance(v, bool) and isinstance(v, int) and v >= 0


def apply_residual(res: Residual, pred: np.ndarray, device: str | None = None) -> np.ndarray:
    """The bounded decode: the prediction (:func:`prediction`) plus the residual, in the source's
    dtype (the interpolation passes as Warp kernels on ``device``, the same bits; None: numpy)."""
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
    u = from_planes(decompress(frames["symbols"], n * width, "symbols", info["symbols_codec"]), n, width)
    layout = [int(c) for c in info.get("layout", AXES)]
    q = unzigzag(u).reshape(tuple(shape[a] for a in layout)).transpose(np.argsort(layout))
    name = info["predictor"]
    gauss, kind = _parts(name)
    levels = info.get("levels", list(FLAT))
    dec = decoded(q, step, integer, kind, info.get("axes", AXES), (float(levels[0]), float(levels[1])), device)
    if not gauss:  # + 0.0 as the coder's zero base adds: -0.0 decodes to +0.0
        out = cast(dec if integer else dec + 0.0, dtype).ravel()
    else:  # what _base gives the coder: the prediction, rounded on the integer lattice
        out = cast((np.rint(pred).astype(np.int64) if integer else pred) + dec, dtype).ravel()
    count = int(info["literals"])
    gaps = from_planes(decompress(frames["positions"], 8 * count, "literal positions"), count, 8).view(np.int64)
    pos = np.cumsum(gaps)
    if count and (pos.min() < 0 or pos.max() >= n):
        raise WarpgaussError("the residual's literal positions fall outside the grid; the file is damaged")
    values = np.frombuffer(decompress(frames["values"], count * dtype.itemsize, "literal values"), dtype.newbyteorder("<"))
    out[pos] = values
    if info["masked"]:
        raw = decompress(frames["mask"], (n + 7) // 8, "mask")
        masked = np.unpackbits(np.frombuffer(raw, np.uint8), count=n).astype(bool)
        if int(masked.sum()) != info["masked"]:
            raise WarpgaussError("the residual's mask does not hold the masked voxels its header counts; the file is damaged")
        mv = info["masked_value"]
        if mv is None:
            mv = math.nan if dtype.kind == "f" else 0
        out[masked] = mv
    return out.reshape(shape)


def verify(res: Residual, pred: np.ndarray, source: np.ndarray, valid: np.ndarray | None, value_range, device: str | None = None) -> dict:
    """Decode as a reader does (the passes on ``device``: the same bits) and check every valid
    voxel against the bound (a violation is a bug, raised, never a warning). Returns the measured maximum error (source units, and as a share of
    the range) and the PSNRs, by :func:`warpgauss.evaluate.score_decode` as ``warpgauss eval``
    scores the file."""
    from ..field.evaluate import score_decode

    s = score_decode(apply_residual(res, pred, device), source, valid, value_range)
    worst, bound = s["max_abs_error"], float(res.info["bound"])
    if not worst <= bound:
        raise WarpgaussError(
            f"internal error: the residual decodes {worst:.6g} from the source, beyond its bound {bound:.6g}; please report this"
        )
    return {k: s[k] for k in ("max_abs_error", "max_abs_error_normalised", "psnr_db", "psnr_occupied_db")}
