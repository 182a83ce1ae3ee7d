"""The compact96 model format: 96 bits a primitive (centres on 13-bit grids over the primitives'
bounding box, log-scales on 7, the rotation as its largest component's index and the other three
on 6 bits each over +-1/sqrt2, amplitude and weight on 8), each field's range in the header's
``quant`` so that the file describes itself (:mod:`warpgauss.format.wgs` writes and reads the file)."""

from __future__ import annotations

import math

import numpy as np

from ..errors import WarpgaussError
from .coded import Q_RANGE, from_smallest_three, smallest_three  # the three smaller components lie in +-1/sqrt2

# compact96 bit allocation (sums to 96); stored in the header's "quant" so the file describes itself
COMPACT_BITS: dict[str, int] = {"mu": 13, "log_s": 7, "q_index": 2, "q": 6, "a": 8, "w": 8}


def _widths() -> list[int]:
    """Bit widths of the 12 packed fields: mu x3, log_s x3, quaternion index, 3 small components, a, w."""
    b = COMPACT_BITS
    return [b["mu"]] * 3 + [b["log_s"]] * 3 + [b["q_index"]] + [b["q"]] * 3 + [b["a"], b["w"]]


def _check_bits(bits) -> None:
    if not isinstance(bits, dict) or bits != COMPACT_BITS:
        raise WarpgaussError(
            f"unsupported compact96 bit allocation {bits!r} (this version reads {COMPACT_BITS}); "
            "the file is damaged or was written by another warpgauss version"
        )


def _levels(bits: int, centred: bool) -> int:
    """Intervals between the levels: 2**bits levels, or 2**bits - 1 (odd, so the midpoint is a level)."""
    return (1 << bits) - (2 if centred else 1)


def _quantise(x, lo, hi, bits: int, centred: bool = False) -> np.ndarray:
    """Code of the nearest level on [lo, hi] (a degenerate range maps everything to code 0)."""
    levels = _levels(bits, centred)
    span = np.asarray(hi, np.float64) - np.asarray(lo, np.float64)
    safe = np.where(span > 0, span, 1.0)
    t = np.where(span > 0, (np.asarray(x, np.float64) - lo) / safe, 0.0)
    return np.clip(np.rint(t * levels), 0, levels).astype(np.uint64)


def _dequantise(code: np.ndarray, lo, hi, bits: int, centred: bool = False) -> np.ndarray:
    levels = _levels(bits, centred)
    lo = np.asarray(lo, np.float64)
    hi = np.asarray(hi, np.float64)
    v = lo + code.astype(np.float64) * ((hi - lo) / levels)
    return np.clip(v, lo, hi)  # the top level lands on hi up to round-off; never leave the range


def _pack(codes: np.ndarray, widths: list[int]) -> np.ndarray:
    """(n, F) uint64 codes -> (n, 3) uint32 words, fields laid out LSB-first across the 96 bits."""
    words = np.zeros((codes.shape[0], 3), np.uint64)
    off = 0
    for f, b in enumerate(widths):
        k, sh = divmod(off, 32)
        v = codes[:, f] << np.uint64(sh)
        words[:, k] |= v & np.uint64(0xFFFFFFFF)
        if sh + b > 32:
            words[:, k + 1] |= v >> np.uint64(32)
        off += b
    assert off == 96
    return words.astype(np.uint32)


def _unpack(words: np.ndarray, widths: list[int]) -> np.ndarray:
    w = words.astype(np.uint64)
    codes = np.empty((w.shape[0], len(widths)), np.uint64)
    off = 0
    for f, b in enumerate(widths):
        k, sh = divmod(off, 32)
        v = w[:, k] >> np.uint64(sh)
        if sh + b > 32:
            v |= w[:, k + 1] << np.uint64(32 - sh)
        codes[:, f] = v & np.uint64((1 << b) - 1)
        off += b
    return codes


def encode_compact(params: np.ndarray) -> tuple[bytes, dict]:
    """Quantise (N, 12) parameters to the ``compact96`` payload (12 bytes per primitive).

    Args:
        params: (N, 12) finite parameters (see :data:`PARAM_NAMES`).

    Returns:
        ``(payload, quant)``: the ``12 N`` payload bytes and the JSON-ready ranges and bit
        allocation that :func:`decode_compact` needs.
    """
    p = np.ascontiguousarray(params, dtype=np.float32)  # validated by the writer (warpgauss.format.wgs)
    b = COMPACT_BITS
    p64 = p.astype(np.float64)
    mu, s, q, a, w = p64[:, 0:3], p64[:, 3:6], p64[:, 6:10], p64[:, 10], p64[:, 11]
    # ranges are float32 values of the data, so their JSON text round-trips exactly
    mu_lo, mu_hi = p[:, 0:3].min(0), p[:, 0:3].max(0)
    s_lo, s_hi = p[:, 3:6].min(), p[:, 3:6].max()
    a_lo, a_hi = p[:, 10].min(), p[:, 10].max()
    w_lo, w_hi = p[:, 11].min(), p[:, 11].max()

    qi, small = smallest_three(q)

    codes = np.concatenate(
        [
            _quantise(mu, mu_lo.astype(np.float64), mu_hi.astype(np.float64), b["mu"]),
            _quantise(s, float(s_lo), float(s_hi), b["log_s"]),
            qi.astype(np.uint64)[:, None],
            _quantise(small, -Q_RANGE, Q_RANGE, b["q"], centred=True),
            _quantise(a, float(a_lo), float(a_hi), b["a"])[:, None],
            _quantise(w, float(w_lo), float(w_hi), b["w"])[:, None],
        ],
        axis=1,
    )
    words = _pack(codes, _widths())
    quant = quant_dict(mu_lo, mu_hi, s_lo, s_hi, a_lo, a_hi, w_lo, w_hi)
    return words.astype("<u4").tobytes(), quant


def _q_number(quant: dict, key: str) -> float:
    v = quant.get(key)
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise WarpgaussError(f"compact96 quantisation field '{key}' must be a finite number; the file is damaged")
    return float(v)


def _q_vector(quant: dict, key: str) -> np.ndarray:
    v = quant.get(key)
    if not isinstance(v, list) or len(v) != 3:
        raise WarpgaussError(f"compact96 quantisation field '{key}' must be a list of 3 numbers; the file is damaged")
    return np.array([_q_number({key: x}, key) for x in v], np.float64)


def decode_compact(payload: bytes, n: int, quant: dict) -> np.ndarray:
    """Dequantise a ``compact96`` payload.

    Args:
        payload: Exactly ``12 n`` bytes.
        n: Number of primitives.
        quant: The ranges and bit allocation written by :func:`encode_compact`.

    Returns:
        (n, 12) float32 parameters with unit quaternions.
    """
    if len(payload) != 12 * n:
        raise WarpgaussError(f"compact96 payload holds {len(payload)} bytes, expected 12 x {n}; the file is damaged")
    if not isinstance(quant, dict):
        raise WarpgaussError("compact96 quantisation ranges are missing from the header; the file is damaged")
    _check_bits(quant.get("bits"))
    mu_lo, mu_hi = _q_vector(quant, "mu_lo"), _q_vector(quant, "mu_hi")
    s_lo, s_hi = _q_number(quant, "log_s_lo"), _q_number(quant, "log_s_hi")
    a_lo, a_hi = _q_number(quant, "a_lo"), _q_number(quant, "a_hi")
    w_lo, w_hi = _q_number(quant, "w_lo"), _q_number(quant, "w_hi")
    if np.any(mu_lo > mu_hi) or s_lo > s_hi or a_lo > a_hi or w_lo > w_hi:
        raise WarpgaussError("compact96 quantisation ranges have lo > hi; the file is damaged")

    b = COMPACT_BITS
    words = np.frombuffer(payload, dtype="<u4").reshape(n, 3)
    c = _unpack(words, _widths())
    out = np.empty((n, 12), np.float64)
    out[:, 0:3] = _dequantise(c[:, 0:3], mu_lo, mu_hi, b["mu"])
    out[:, 3:6] = _dequantise(c[:, 3:6], s_lo, s_hi, b["log_s"])
    out[:, 6:10] = from_smallest_three(c[:, 6], _dequantise(c[:, 7:10], -Q_RANGE, Q_RANGE, b["q"], centred=True))
    out[:, 10] = _dequantise(c[:, 10], a_lo, a_hi, b["a"])
    out[:, 11] = _dequantise(c[:, 11], w_lo, w_hi, b["w"])
    return out.astype(np.float32)


def quant_dict(mu_lo, mu_hi, s_lo, s_hi, a_lo, a_hi, w_lo, w_hi) -> dict:
    """The header's ``quant`` of a compact96 payload: the bit allocation and every field's range."""
    return {
        "bits": dict(COMPACT_BITS),
        "mu_lo": [float(v) for v in mu_lo],
        "mu_hi": [float(v) for v in mu_hi],
        "log_s_lo": float(s_lo),
        "log_s_hi": float(s_hi),
        "a_lo": float(a_lo),
        "a_hi": float(a_hi),
        "w_lo": float(w_lo),
        "w_hi": float(w_hi),
    }
