"""The ``coded`` payload of a ``.wgs`` file: quantised primitives, ordered along a Morton curve,
columns delta- or offset-coded, byte planes compressed with Zstandard.

Quantisation (absolute grids, so a primitive's stored value depends on nothing but itself, which
lets refinement project onto the same grid during its last iterations, see
:func:`project_coded`)::

    centre      mu  -> round(mu * 2^b_mu)             (b_mu fractional bits of a voxel)
    log-scale   s   -> round(s * 2^b_s)
    rotation    q   -> smallest three: index of the largest |component| (made positive) and the
                       other three on 2^b_q - 1 levels over [-1/sqrt2, 1/sqrt2] (0 exact)
    value       a   -> round(a * 2^b_a)
    weight      w   -> max(round(w * 2^b_w), 1)        (a weight never quantises to 0)

The primitives are sorted by the Morton code of their centre codes (ties by every other code), so
neighbours along the file are neighbours in space: the centre columns are stored as differences
from the previous primitive (zigzag), every other column as its offset from the column's minimum.
Each column takes the fewest whole bytes its values need; the columns' byte planes (all lowest
bytes first) are concatenated into one Zstandard frame, each plane ended as a block of its own so
that each gets its own literal (Huffman) table: one table for all planes mixed, as a single
compression of the concatenation gives at small N, cost 7-10 % (refined models of 2,900-3,800
Gaussians: mni_icbm152 at CR 300 9.35 -> 8.47 B a Gaussian, interface 96^3 at CR 100 8.89 ->
7.97; 1 % at 75,000, inia19 at CR 30, 7.79 -> 7.70; the order-0 entropy of the columns' values is
8.02 / 7.64 / 7.50). The frame is coded at :data:`ZSTD_LEVELS` and the smaller kept (matches
across the planes buy little: level 19 codes them larger than level 1 and takes 80x as long).
Zstandard rather than a range coder of our own: a well-kept, fast, bounded-memory library with a
frame checksum and a declared content size; an adaptive model-based coder would save the 2-5 %
that separate the frame from the order-0 entropy, more with contexts between columns (not
measured). A reader of any warpgauss version decodes either layout: it is one frame either way.

Decoding checks every declared width, offset and length against the header before it allocates,
decompresses into at most the declared size, and rejects codes outside their ranges; no pickle.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from .errors import WarpgaussError
from .export import quat_to_matrix

# measured on four real volumes (benchmarks/results/rate_distortion/coded_loss_mri_cpu.json): every bit here costs less
# PSNR than the primitives its bytes would buy (about 0.4 dB a byte at these budgets)
CODED_BITS: dict[str, int] = {"mu": 2, "log_s": 4, "q": 5, "a": 7, "w": 5}
# the frame of planes is coded at each level and the smaller kept: level 1 was the smaller on three
# refined models of four, level 9 on the fourth (mni_icbm152 at CR 1000, 688 Gaussians: 9.67 and
# 9.31 B a Gaussian); both take 2-11 ms a megabyte of planes, where level 19 took 135
ZSTD_LEVELS = (1, 9)
# CODED_BITS keep the quantisation noise below the error of 30-42 dB models; a more accurate model
# needs finer grids: one bit on every attribute per this many dB above BITS_REFERENCE_DB (each bit
# halves the noise). Measured: a 51.2 dB vortex model lost 2.07 dB at CODED_BITS, 0.14 dB at +2.
BITS_REFERENCE_DB = 40.0
DB_PER_BIT = 6.0
Q_RANGE = 1.0 / math.sqrt(2.0)
CODED_COLUMNS = ("mu_x", "mu_y", "mu_z", "log_sx", "log_sy", "log_sz", "q_index", "q_0", "q_1", "q_2", "a", "w")
_DELTA = ("mu_x", "mu_y", "mu_z")
_MAX_CODE = 1 << 52  # |code| bound: every code and difference is exact in float64 and int64


# The least payload a coded primitive may take. Real models take more: 5.7-6.4 bytes a Gaussian at
# the coarsest depths bits_for_psnr gives (10 dB) and 2.2-3.4 at the least the rate control ever
# keeps (_MIN_BITS), on the analytic models of the four 48^3 examples at N 2,000-4,000; 6.9-14.0
# refined (README's table); the same row repeated 20,000 times codes to 0.0015. A file claiming more primitives than its payload could hold at this floor (a small
# frame of zeros claiming millions) is refused before anything is decompressed or allocated, and
# no file is written that this check would refuse.
MIN_PAYLOAD_PER_PRIMITIVE = 1.0


def check_claim(payload_bytes: int, n: int) -> None:
    """Refuse a coded payload of ``payload_bytes`` that claims ``n`` primitives, more than
    :data:`MIN_PAYLOAD_PER_PRIMITIVE` allows (before it is decompressed)."""
    if n > payload_bytes / MIN_PAYLOAD_PER_PRIMITIVE:
        raise WarpgaussError(
            f"the coded payload of {payload_bytes:,} bytes claims {n:,} primitives ({payload_bytes / max(n, 1):.3g} bytes each; "
            f"real models take more than 2, this reader refuses below {MIN_PAYLOAD_PER_PRIMITIVE:g}): the file is damaged or crafted"
        )


def zstandard_module():
    try:
        import zstandard
    except ImportError:  # pragma: no cover - a dependency of the package
        raise WarpgaussError("the coded model format needs the 'zstandard' package: pip install zstandard") from None
    return zstandard


def check_bits(bits) -> dict[str, int]:
    if not isinstance(bits, dict) or set(bits) != set(CODED_BITS):
        raise WarpgaussError(f"coded bit depths must name {sorted(CODED_BITS)}, got {bits!r}")
    out = {}
    for k, v in bits.items():
        hi = 16 if k == "q" else 24
        if isinstance(v, bool) or not isinstance(v, int) or not (2 if k == "q" else 0) <= v <= hi:
            raise WarpgaussError(f"coded bit depth '{k}' must be an integer from {2 if k == 'q' else 0} to {hi}, got {v!r}")
        out[k] = int(v)
    return out


def _octahedral() -> tuple[np.ndarray, np.ndarray]:
    """The 24 rotations that map a box's axes onto themselves, as quaternions (x, y, z, w), the
    identity first, and for each the old axis each new axis is (``perm[k, i]``)."""
    r = 1.0 / math.sqrt(2.0)
    g: list[tuple[float, ...]] = [(0.0, 0.0, 0.0, 1.0)]
    for i in range(3):  # half turns about an axis
        g.append(tuple(1.0 if j == i else 0.0 for j in range(4)))
    for i in range(3):  # quarter turns about an axis
        for sgn in (1.0, -1.0):
            g.append(tuple(sgn * r if j == i else r if j == 3 else 0.0 for j in range(4)))
    for i, j in ((0, 1), (0, 2), (1, 2)):  # half turns about a face diagonal
        for sgn in (1.0, -1.0):
            g.append(tuple(r if k == i else sgn * r if k == j else 0.0 for k in range(4)))
    for sx in (0.5, -0.5):  # third turns about a body diagonal
        for sy in (0.5, -0.5):
            for sz in (0.5, -0.5):
                g.append((sx, sy, sz, 0.5))
    q = np.array(g, np.float64)
    return q, np.abs(np.rint(quat_to_matrix(q))).argmax(axis=1).astype(np.intp)


# A Gaussian is the same after any of these rotations of its axes (scales moved along): the coded
# format stores the one whose quaternion is nearest the identity (largest |w|), so the three
# smaller components lie within +-(sqrt2 - 1) w instead of +-1/sqrt2 and the index is always w's:
# log2(24) = 4.6 bits a Gaussian less to code on the same grids (refined CPU models: mni_icbm152
# CR 300 8.47 -> 7.96 B a Gaussian, CR 1000 9.31 -> 8.75, interface 96^3 CR 100 7.97 -> 7.45,
# inia19 CR 30 7.70 -> 7.28), the covariances equal to 1e-15
OCTAHEDRAL_Q, OCTAHEDRAL_AXES = _octahedral()
# a stored quaternion must be nearest the identity by this relative margin, so that a decoded model
# (float32) is stored again as the same codes and the refiner's float32 projection agrees
CANONICAL_MARGIN = 1e-5
_TAN_EIGHTH = math.sqrt(2.0) - 1.0  # tan(pi / 8): a quarter turn about an axis ties beyond it
_W_AFTER = np.stack([-OCTAHEDRAL_Q[:, 0], -OCTAHEDRAL_Q[:, 1], -OCTAHEDRAL_Q[:, 2], OCTAHEDRAL_Q[:, 3]])  # q @ this: the w of each q g


def _hamilton(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Quaternion products a b of (n, 4) arrays in (x, y, z, w) order."""
    ax, ay, az, aw = a.T
    bx, by, bz, bw = b.T
    return np.stack(
        [
            aw * bx + bw * ax + ay * bz - az * by,
            aw * by + bw * ay + az * bx - ax * bz,
            aw * bz + bw * az + ax * by - ay * bx,
            aw * bw - ax * bx - ay * by - az * bz,
        ],
        1,
    )


def canonical(params: np.ndarray) -> np.ndarray:
    """(N, 12) float64 parameters of the same Gaussians, each turned by the axis rotation (of
    :data:`OCTAHEDRAL_Q`) that brings its unit quaternion nearest the identity, ``w`` >= 0, its
    log-scales moved with its axes (the first such rotation where several tie)."""
    p = np.array(params, np.float64)
    q = p[:, 6:10]
    norm = np.sqrt(np.einsum("ij,ij->i", q, q))[:, None]
    if np.all(norm > 0):
        q = q / norm
    else:
        q = np.where(norm > 0, q / np.where(norm > 0, norm, 1.0), np.array([0.0, 0.0, 0.0, 1.0]))
    k = np.zeros(len(q), np.intp)
    rest = np.flatnonzero(_outside_canonical(q, 1e-3))  # the others are nearest the identity by far
    if len(rest):
        w_after = q[rest] @ _W_AFTER  # the w of q g for each turn g
        k[rest] = np.argmax(np.abs(w_after, out=w_after), axis=1)
    turned = np.flatnonzero(k)
    if len(turned):
        q[turned] = _hamilton(q[turned], OCTAHEDRAL_Q[k[turned]])
        p[turned, 3:6] = np.take_along_axis(p[turned, 3:6], OCTAHEDRAL_AXES[k[turned]], axis=1)
    q[q[:, 3] < 0] *= -1.0
    p[:, 6:10] = q
    return p


def _outside_canonical(q: np.ndarray, margin: float = CANONICAL_MARGIN) -> np.ndarray:
    """Rows of (n, 4) unit quaternions not nearest the identity among their 24 turns by a relative
    ``margin`` (|x|, |y|, |z| <= tan(pi/8) w and |x| + |y| + |z| <= w, with w the
    largest: the truncated cube around the identity)."""
    a = np.abs(q)  # column by column: reductions along a row of three are slow in numpy
    w = a[:, 3] * (1.0 - margin)
    top = np.maximum(np.maximum(a[:, 0], a[:, 1]), a[:, 2])
    return (top > _TAN_EIGHTH * w) | (a[:, 0] + a[:, 1] + a[:, 2] > w)


def smallest_three(q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(index of the largest |component|, the other three) of (n, 4) quaternions, normalised
    (zero: the identity) and signed so that the largest is positive (q and -q are one rotation).
    The other three then lie in [-1/sqrt2, 1/sqrt2]."""
    q = np.asarray(q, np.float64)
    n = q.shape[0]
    norm = np.linalg.norm(q, axis=1, keepdims=True)
    q = np.where(norm > 0, q / np.where(norm > 0, norm, 1.0), np.array([0.0, 0.0, 0.0, 1.0]))
    qi = np.argmax(np.abs(q), axis=1)
    rows = np.arange(n)
    q = q * np.where(q[rows, qi] < 0, -1.0, 1.0)[:, None]
    keep = np.ones((n, 4), bool)
    keep[rows, qi] = False
    return qi, q[keep].reshape(n, 3)


def from_smallest_three(qi: np.ndarray, small: np.ndarray) -> np.ndarray:
    """Unit quaternions (n, 4) from :func:`smallest_three`'s index and (dequantised) three."""
    n = small.shape[0]
    qi = np.asarray(qi, np.intp)
    largest = np.sqrt(np.maximum(0.0, 1.0 - np.sum(small * small, axis=1)))
    rows = np.arange(n)
    keep = np.ones((n, 4), bool)
    keep[rows, qi] = False
    q = np.empty((n, 4), np.float64)
    q[keep] = small.reshape(-1)
    q[rows, qi] = largest
    return q / np.linalg.norm(q, axis=1, keepdims=True)  # never zero: largest = 1 when the rest are 0


def _q_levels(b: int) -> int:
    return (1 << b) - 2  # intervals: 2^b - 1 levels, odd, so 0 is a level


def _grid(x: np.ndarray, k: int) -> np.ndarray:
    c = np.rint(x * float(1 << k))
    if np.any(np.abs(c) > _MAX_CODE):
        raise WarpgaussError("a parameter is too large for the coded format (|value| x 2^bits > 2^52); use --format full")
    return c.astype(np.int64)


def _quaternion_codes(q: np.ndarray, qb: int) -> np.ndarray:
    """(n, 4) codes of canonical turns (n, 4): the largest component's index, the other three on a
    grid of 2^qb - 1 levels."""
    n = q.shape[0]
    qi, small = smallest_three(q)
    lev = _q_levels(qb)
    sc = np.clip(np.rint((small + Q_RANGE) / (2 * Q_RANGE) * lev), 0, lev).astype(np.int64)
    # the rounded rotation must stay nearest the identity (w the largest component, canonical),
    # else a decoded model would turn to another of its 24 forms (and drift by a step when saved
    # again): near the edges, move the largest small component one level towards 0 until it is
    mid = lev // 2
    rows = np.arange(n)  # the rows still to check: only those moved are checked again
    for _ in range(4 * lev):
        sv = sc[rows] * (2 * Q_RANGE / lev) - Q_RANGE
        av = np.abs(sv)
        largest = np.sqrt(np.maximum(0.0, 1.0 - (av[:, 0] ** 2 + av[:, 1] ** 2 + av[:, 2] ** 2)))
        bad = np.maximum(np.maximum(av[:, 0], av[:, 1]), av[:, 2]) >= largest * (1.0 - 1e-9)
        bad |= _outside_canonical(from_smallest_three(qi[rows], sv))
        if not bad.any():
            break
        rows = rows[bad]
        k = np.argmax(av[bad], axis=1)
        sc[rows, k] -= np.sign(sc[rows, k] - mid)
    return np.concatenate([qi[:, None].astype(np.int64), sc], axis=1)


# each attribute's code columns, from canonical float64 parameters and its bit depth: row by row,
# so the codes of a subset of rows are those rows of the whole set's codes
_ATTRIBUTE_CODES = (
    ("mu", slice(0, 3), _grid),
    ("log_s", slice(3, 6), _grid),
    ("q", slice(6, 10), _quaternion_codes),
    ("a", slice(10, 11), _grid),
    ("w", slice(11, 12), lambda x, k: np.maximum(_grid(x, k), 1)),
)


def _codes(p: np.ndarray, b: dict[str, int], columns: dict | None = None) -> np.ndarray:
    """(N, 12) codes of canonical float64 parameters ``p``, each attribute's columns taken from
    (and kept in) ``columns`` by (attribute, bit depth) where given."""
    codes = np.empty((p.shape[0], 12), np.int64)
    for name, cols, make in _ATTRIBUTE_CODES:
        key = (name, b[name])
        col = None if columns is None else columns.get(key)
        if col is None:
            col = make(p[:, cols], b[name])
            if columns is not None:
                columns[key] = col
        codes[:, cols] = col
    return codes


def quantise(params: np.ndarray, bits: dict[str, int] | None = None) -> np.ndarray:
    """(N, 12) integer codes (int64) of ``params`` on the coded grids (columns as :data:`CODED_COLUMNS`)."""
    b = check_bits(dict(CODED_BITS if bits is None else bits))
    cached = _cached_codes(params, b)
    return cached if cached is not None else _codes(canonical(params), b)


_FIT = threading.local()  # the fit coding in this thread (:class:`_FitCodes`), if any


class _FitCodes:
    """A fit's code columns by attribute and bit depth, for its parameters and the row subsets it
    codes (pruned models): its codings differ in a few depths and rows, and each attribute's
    columns are quantised once per depth instead of at every coding (the same codes: quantisation
    is row by row). Active in the thread that enters it (the export choice's alternatives code on
    threads of their own)."""

    def __init__(self, p: np.ndarray):
        self.base, self.c64 = p, canonical(p)
        self.columns: dict[tuple[str, int], np.ndarray] = {}
        self.arrays: dict[int, tuple[np.ndarray, np.ndarray | None]] = {id(p): (p, None)}  # arrays kept alive: ids stay theirs

    def subset(self, rows: np.ndarray) -> np.ndarray:
        """The base's ``rows`` (a new array whose codes are known)."""
        q = self.base[rows]
        self.arrays[id(q)] = (q, rows)
        return q

    def codes(self, params, b: dict[str, int]) -> np.ndarray | None:
        entry = self.arrays.get(id(params))
        if entry is None or entry[0] is not params:
            return None
        out = _codes(self.c64, b, self.columns)
        rows = entry[1]
        return out if rows is None else out[rows]

    def __enter__(self):
        self._outer = getattr(_FIT, "codes", None)
        _FIT.codes = self
        return self

    def __exit__(self, *exc):
        _FIT.codes = self._outer


def _cached_codes(params, b: dict[str, int]) -> np.ndarray | None:
    fit = getattr(_FIT, "codes", None)
    return None if fit is None else fit.codes(params, b)


def dequantise(codes: np.ndarray, bits: dict[str, int] | None = None) -> np.ndarray:
    """(N, 12) float32 parameters of integer codes (unit quaternions)."""
    b = check_bits(dict(CODED_BITS if bits is None else bits))
    c = np.asarray(codes, np.int64)
    n = c.shape[0]
    out = np.empty((n, 12), np.float64)
    out[:, 0:3] = c[:, 0:3] / float(1 << b["mu"])
    out[:, 3:6] = c[:, 3:6] / float(1 << b["log_s"])
    lev = _q_levels(b["q"])
    out[:, 6:10] = from_smallest_three(c[:, 6], c[:, 7:10] * (2 * Q_RANGE / lev) - Q_RANGE)
    out[:, 10] = c[:, 10] / float(1 << b["a"])
    out[:, 11] = c[:, 11] / float(1 << b["w"])
    return out.astype(np.float32)


def project_coded(params: np.ndarray, bits: dict[str, int] | None = None) -> np.ndarray:
    """``params`` as the coded format stores them (same order): what a decoder will read back."""
    return dequantise(quantise(params, bits), bits)


def as_stored(params: np.ndarray, bits: dict[str, int] | None = None) -> np.ndarray:
    """``params`` exactly as a coded file of them reads back: projected, in the file's order."""
    codes = quantise(params, bits)
    return dequantise(codes[coded_order(codes)], bits)


def _part1by2(v: np.ndarray) -> np.ndarray:
    """Spread the low 21 bits of v to every third bit (Morton interleave of one axis)."""
    v = v.astype(np.uint64) & np.uint64(0x1FFFFF)
    for shift, mask in (
        (32, 0x1F00000000FFFF),
        (16, 0x1F0000FF0000FF),
        (8, 0x100F00F00F00F00F),
        (4, 0x10C30C30C30C30C3),
        (2, 0x1249249249249249),
    ):
        v = (v | (v << np.uint64(shift))) & np.uint64(mask)
    return v


def coded_order(codes: np.ndarray) -> np.ndarray:
    """The storage order: by Morton code of the centre codes (offset to 0), ties by every code; a
    centre range wider than 2^21 codes on an axis falls back to z, y, x order.

    Equal to ``np.lexsort`` over (every code, then the key), computed as one sort of the key and
    a lexsort of the rows whose key is shared (a few, where centres share a grid cell).
    """
    mu = codes[:, 0:3] - codes[:, 0:3].min(0)
    if int(mu.max(initial=0)) < (1 << 21):
        key = _part1by2(mu[:, 0]) | (_part1by2(mu[:, 1]) << np.uint64(1)) | (_part1by2(mu[:, 2]) << np.uint64(2))
    else:
        key = None
    if key is None:
        keys = [codes[:, k] for k in range(11, 2, -1)]  # least significant first for lexsort
        return np.lexsort([*keys, mu[:, 0], mu[:, 1], mu[:, 2]])
    order = np.argsort(key, kind="stable")
    ks = key[order]
    tie = np.zeros(len(ks), bool)
    if len(ks) > 1:
        same = ks[1:] == ks[:-1]
        tie[1:] |= same
        tie[:-1] |= same
    if tie.any():  # rows sharing a key: their positions, filled in full-lexsort order
        pos = np.flatnonzero(tie)
        rows = np.sort(order[pos])  # original order, so the lexsort's ties resolve as the full one's
        sub = codes[rows]
        smu = mu[rows]
        sub_order = np.lexsort([*[sub[:, k] for k in range(11, 2, -1)], smu[:, 0], smu[:, 1], smu[:, 2], key[rows]])
        order[pos] = rows[sub_order]
    return order


def _width(max_value: int) -> int:
    return max(1, (int(max_value).bit_length() + 7) // 8)


def encode_coded(params: np.ndarray, bits: dict[str, int] | None = None) -> tuple[bytes, dict, np.ndarray]:
    """Code (N, 12) finite parameters.

    Returns:
        ``(payload, quant, order)``: the compressed bytes, the JSON-ready description the decoder
        needs (bit depths, per-column coding, offset and byte width, raw size), and the
        permutation of ``params`` rows the file stores them in.
    """
    b = check_bits(dict(CODED_BITS if bits is None else bits))
    codes = quantise(params, b)
    order = coded_order(codes)
    codes = codes[order]
    columns, planes, raw = [], [], 0
    for k, name in enumerate(CODED_COLUMNS):
        col = codes[:, k]
        if name in _DELTA:
            off = int(col[0])
            d = np.diff(col, prepend=col[:1])  # first difference 0; the first value is the offset
            v = ((d << 1) ^ (d >> 63)).astype(np.uint64)  # zigzag
        else:
            off = int(col.min())
            v = (col - off).astype(np.uint64)
        w = _width(int(v.max()))
        columns.append([off, w])
        planes.append(v.astype("<u8").view(np.uint8).reshape(-1, 8)[:, :w].T.copy())  # (w, n) planes
        raw += w * len(v)
    payload = _compress_planes([r.tobytes() for p in planes for r in p], raw)
    # columns: [offset, bytes] in CODED_COLUMNS order (centres delta-coded from the offset, the rest
    # offset-coded), kept terse: at high compression ratios the header is part of the budget
    quant = {"bits": b, "columns": columns, "raw_bytes": raw}
    return payload, quant, order


PARALLEL_MIN_BYTES = 1 << 18  # raw planes from which the Zstandard levels run on threads


def _compress_planes(planes: list[bytes], raw: int) -> bytes:
    """One Zstandard frame of ``planes`` (``raw`` bytes in all), a block ended after each plane, at
    each of :data:`ZSTD_LEVELS`; the smallest (the first of equals)."""
    zstd = zstandard_module()

    def frame(level: int) -> bytes:
        co = zstd.ZstdCompressor(level=level, write_checksum=True).compressobj(size=raw)
        out = []
        for plane in planes:
            out.append(co.compress(plane))
            out.append(co.flush(zstd.COMPRESSOBJ_FLUSH_BLOCK))
        out.append(co.flush())
        return b"".join(out)

    # the levels on threads of their own (Zstandard releases the GIL): the same frames, in parallel
    if raw >= PARALLEL_MIN_BYTES and len(ZSTD_LEVELS) > 1:
        with ThreadPoolExecutor(max_workers=len(ZSTD_LEVELS)) as ex:
            frames = list(ex.map(frame, ZSTD_LEVELS))
    else:
        frames = [frame(level) for level in ZSTD_LEVELS]
    return min(frames, key=len)  # the first of equals


def _offset(name: str, v) -> int:
    if isinstance(v, bool) or not isinstance(v, int) or abs(v) > _MAX_CODE:
        raise WarpgaussError(f"coded column {name} offset must be an integer of at most 2^52, got {v!r}; the file is damaged")
    return v


def decode_coded(payload: bytes, n: int, quant: dict) -> np.ndarray:
    """(n, 12) float32 parameters of a ``coded`` payload (in the file's order)."""
    if not isinstance(quant, dict):
        raise WarpgaussError("the coded payload description ('quant') is missing; the file is damaged")
    try:
        b = check_bits(quant.get("bits"))
    except WarpgaussError as e:
        raise WarpgaussError(f"{e}; the file is damaged or was written by another warpgauss version") from None
    cols = quant.get("columns")
    if not isinstance(cols, list) or len(cols) != len(CODED_COLUMNS) or not all(isinstance(c, list) and len(c) == 2 for c in cols):
        raise WarpgaussError(f"the coded column list must hold {len(CODED_COLUMNS)} (offset, bytes) pairs; the file is damaged")
    widths, offsets = [], []
    for (off, w), name in zip(cols, CODED_COLUMNS):
        if isinstance(w, bool) or not isinstance(w, int) or not 1 <= w <= 8:
            raise WarpgaussError(f"coded column {name} width {w!r} is not 1..8 bytes; the file is damaged")
        widths.append(w)
        offsets.append(_offset(name, off))
    check_claim(len(payload), n)
    raw = sum(widths) * n
    if quant.get("raw_bytes") != raw:
        raise WarpgaussError(f"coded payload declares {quant.get('raw_bytes')!r} raw bytes, its columns make {raw}; the file is damaged")
    zstd = zstandard_module()
    try:
        params = zstd.get_frame_parameters(payload)
        if params.content_size != raw:
            raise WarpgaussError(f"coded payload frame holds {params.content_size} bytes, expected {raw}; the file is damaged")
        blob = zstd.ZstdDecompressor().decompress(payload, max_output_size=raw)
    except zstd.ZstdError as e:
        raise WarpgaussError(f"coded payload does not decompress ({e}); the file is damaged") from None
    if len(blob) != raw:
        raise WarpgaussError(f"coded payload decompresses to {len(blob)} bytes, expected {raw}; the file is damaged")
    codes = np.empty((n, 12), np.int64)
    at = 0
    for k, (off, w) in enumerate(zip(offsets, widths)):
        planes = np.frombuffer(blob, np.uint8, count=w * n, offset=at).reshape(w, n)
        at += w * n
        full = np.zeros((n, 8), np.uint8)
        full[:, :w] = planes.T
        v = full.view("<u8").reshape(n)
        if CODED_COLUMNS[k] in _DELTA:
            if np.any(v > np.uint64(2 * _MAX_CODE)):
                raise WarpgaussError(f"coded column {CODED_COLUMNS[k]} holds a difference beyond 2^52; the file is damaged")
            d = (v >> np.uint64(1)).astype(np.int64) ^ -(v & np.uint64(1)).astype(np.int64)
            col = off + np.cumsum(d)
        else:
            if np.any(v > np.uint64(_MAX_CODE)):
                raise WarpgaussError(f"coded column {CODED_COLUMNS[k]} holds a code beyond 2^52; the file is damaged")
            col = off + v.astype(np.int64)
        if np.any(np.abs(col) > _MAX_CODE):
            raise WarpgaussError(f"coded column {CODED_COLUMNS[k]} decodes beyond 2^52; the file is damaged")
        codes[:, k] = col
    lev = _q_levels(b["q"])
    if np.any((codes[:, 6] < 0) | (codes[:, 6] > 3)) or np.any((codes[:, 7:10] < 0) | (codes[:, 7:10] > lev)):
        raise WarpgaussError("coded rotations hold codes outside their range; the file is damaged")
    if np.any(codes[:, 11] < 1):
        raise WarpgaussError("coded weights hold codes below 1; the file is damaged")
    return dequantise(codes, b)


# rate control: one bit at a time, in the order of PSNR lost (or gained) per byte measured on four
# real volumes (benchmarks/results/rate_distortion/coded_loss_mri_cpu.json): dropping w, mu and a bits costs least,
# adding rotation and log-scale bits gains most
SHRINK_ORDER = ("w", "mu", "a", "log_s", "q")
GROW_ORDER = ("q", "log_s", "a", "mu", "w")
_MIN_BITS = {"mu": 0, "log_s": 1, "q": 3, "a": 3, "w": 2}
_MAX_BITS = {"mu": 8, "log_s": 8, "q": 10, "a": 12, "w": 10}
# an excess up to this share of the budget is pruned (the least important primitives), beyond it
# bits are dropped first, unless the caller can score the fits (fit_bytes' score; the encode can),
# which then also tries CHOICE_SHARES. Measured on an H100 before importance ranked by weight
# (benchmarks/results/accuracy/sweep_mri_vortex256_h100.json): pruning up to a 10 % excess by
# weight x |value| x volume lost 0.6-2.7 dB on the MRIs and 21.7 dB on vortex at 300; that ranking
# took the Gaussians of value 0 first (benchmarks/results/accuracy/prune_order_*_cpu.json)
PRUNE_SHARE = 0.03
FILL_SHARE = 0.002  # the prune search stops once the model is within this share under the budget
SEARCH_CODINGS = 12  # codings the prune search may spend after the first fit (to within one primitive)
GROW_MARGIN = 0.5  # a bit is tried when half its predicted bytes fit (its lowest bits may compress)
_BIT_COLUMNS = {"mu": 3, "log_s": 3, "q": 3, "a": 1, "w": 1}  # stored values per primitive and bit


def importance(params: np.ndarray) -> np.ndarray:
    """What a primitive adds to the model, for pruning: weight x sigma volume, its share of the
    blend's denominator around it. Not its value: the model is a normalised blend, so a
    primitive of value 0 holds its neighbourhood at 0 as much as any other holds its value.
    Measured (CPU, 400 iterations, float32 models, ``benchmarks/results/accuracy/prune_order_*_cpu.json``):
    pruning 3 / 10 % by weight x sigma volume cost 0.0-0.1 / 0.0-1.4 dB on vortex and interface
    96^3 and two head MRIs, where weight x |value| x volume (before) cost 0.3-9.1 / 1.9-12.9 dB
    (on the fields, worse than a random choice)."""
    p = np.asarray(params, np.float64)
    return np.abs(p[:, 11]) * np.exp(np.clip(p[:, 3:6].sum(1), -60.0, 60.0))


def _bit_bytes(n: int, k: str) -> float:
    """Predicted bytes one more (or one fewer) bit of attribute ``k`` costs ``n`` primitives: a
    grid's lowest bit is close to noise, so about one bit per stored value (its columns)."""
    return n * _BIT_COLUMNS[k] / 8.0


# which attribute's bits are worth most depends on the volume: on the head MRIs a bit of mu costs
# least (the orders above), on the interface field (96^3, benchmarks/results/accuracy/
# prune_order_fields_cpu.json) it costs 4x more PSNR per byte than any other. With
# MEASURE_BIT_WORTH and a score (fit_bytes'), each attribute's bit is measured on the model itself:
# one bit more and one fewer on it alone, projected (no coding) and scored; a bit's worth is taken
# to fall 4x with each bit beyond (its noise power quarters). Off: measured, it does not pay. On
# float32 CPU models at equal bytes (benchmarks/results/accuracy/bit_order_*_cpu.json) it gained
# 0.00-0.10 dB over the scored choice alone; in the encode on an H200
# (sweep_interface512_worth_h200.json, sweep_mri300_worth_h200.json) the interface at 512^3 gained
# 0.18 dB at CR 100 and lost 0.45 at CR 300 (one bit's worth, measured alone, did not predict the
# drops together), the MRIs at CR 300 were unchanged, and the eleven scores cost 0.4-0.6 s on the
# MRIs and 2.8 / 8.5 s at 180,000 / 575,000 Gaussians
BIT_WORTH_DECAY = 4.0
MEASURE_BIT_WORTH = False
BitWorth = dict[str, tuple[float | None, float | None]]  # per attribute: (gain, loss) per byte of a bit


def bit_worth(params: np.ndarray, bits: dict[str, int], score) -> BitWorth:
    """Per attribute, the PSNR one bit more gains and one bit fewer loses, per predicted byte
    (:func:`_bit_bytes`), measured by ``score(projected, bits)`` on the model projected onto those
    grids (:func:`project_coded`: the stored values in the model's own order; None where the depth
    is at its bound): ``{k: (gain, loss)}``."""
    p = np.asarray(params, np.float32)
    b = check_bits(dict(bits))
    base = float(score(project_coded(p, b), b))
    out: BitWorth = {}
    for k in SHRINK_ORDER:
        per = max(_bit_bytes(len(p), k), 1e-9)
        more = {**b, k: b[k] + 1}
        fewer = {**b, k: b[k] - 1}
        gain = (float(score(project_coded(p, more), more)) - base) / per if b[k] < _MAX_BITS[k] else None
        loss = (base - float(score(project_coded(p, fewer), fewer))) / per if b[k] > _MIN_BITS[k] else None
        out[k] = (gain, loss)
    return out


def _next_drop(b: dict[str, int], start: dict[str, int], worth: BitWorth | None, turn: int) -> tuple[str | None, int]:
    """The attribute whose bit to drop next: the least loss per byte (falling 4x a bit dropped)
    with ``worth``, else :data:`SHRINK_ORDER` in turn; and the next turn."""
    if worth is None:
        for _ in range(len(SHRINK_ORDER)):
            k = SHRINK_ORDER[turn % len(SHRINK_ORDER)]
            turn += 1
            if b[k] > _MIN_BITS[k]:
                return k, turn
        return None, turn
    loss = {k: v for k, (_, v) in worth.items() if v is not None and b[k] > _MIN_BITS[k]}
    if not loss:
        return None, turn
    order = len(SHRINK_ORDER)  # ties go in turn, as without worth
    k = min(loss, key=lambda k: (loss[k] * BIT_WORTH_DECAY ** (start[k] - b[k]), (SHRINK_ORDER.index(k) - turn) % order))
    return k, SHRINK_ORDER.index(k) + 1


def _grow_order(b: dict[str, int], start: dict[str, int], worth: BitWorth | None) -> list[str]:
    """Attributes to try a bit more on, best first: :data:`GROW_ORDER` without ``worth``, else by
    gain per byte (falling 4x with each bit above ``start``; the budget is filled either way)."""
    if worth is None:
        return list(GROW_ORDER)
    gain = {k: g for k, (g, _) in worth.items() if g is not None}
    grown = {k: max(0, b[k] - start[k]) for k in gain}  # ties: the fewest bits grown first, then GROW_ORDER
    return sorted(gain, key=lambda k: (-gain[k] / BIT_WORTH_DECAY ** grown[k], grown[k], GROW_ORDER.index(k)))


# where a caller can measure a fitted model's accuracy (fit_bytes' score), the rate control fits at
# each of these prune shares (an excess up to the share pruned, beyond it bits dropped first; 1.0:
# pruning alone up to twice the budget) and keeps the one that scores best. Measured with the
# weight ranking (benchmarks/results/accuracy/prune_order_*_cpu.json): which pays depends on the
# volume and the excess, so it is measured per model rather than fixed. 0.0: bits alone, nothing
# pruned: the interface at 512^3, CR 1000, pruned 949 of 53,338 (1.8 %) beside three bits dropped
# and scored 6.5 dB under float32 of its N, where 8 % pruned cost 13 dB (H200,
# accuracy/sweep_fields512_float2_h200.json). On float32 CPU models at 0.85 / 0.92 / 0.97 of the
# bytes their accuracy asks for (interface and vortex 96^3 N 20,000, mni_icbm152 and inia19 N
# 10,000, 400 iterations) it was chosen twice in twelve (vortex 58.70 -> 58.74, inia19 41.91 ->
# 41.92 dB) and, being scored, lost nothing elsewhere (the interface and mni keep pruning: 49.33-
# 49.82 and 30.98-31.09 dB against 48.06-49.43 and 30.70-30.99 by bits alone). Not yet on a GPU
CHOICE_SHARES = (PRUNE_SHARE, 0.0, 0.15, 1.0)
# prune-search codings of an alternative before it is scored (a winner is fitted again in full):
# the choice cost 1.5-5.3 s of coding on 200,000-570,000-Gaussian models with the whole search
CHOICE_SEARCH_CODINGS = 1


def fit_bytes(
    params: np.ndarray,
    budget: int,
    bits: dict[str, int] | None = None,
    size_of=None,
    prune_share: float | None = None,
    score: Callable[[np.ndarray, dict[str, int]], float] | None = None,
) -> tuple[np.ndarray, dict, dict]:
    """The coded model that fits ``budget`` bytes, as :func:`fit_at_share` fits it; with ``score``
    (and no ``prune_share``) at each of :data:`CHOICE_SHARES` where the first fit had to drop bits,
    keeping the fit that ``score(stored, bits)`` (a PSNR) rates best. The info then holds
    ``choice``: each fit's share, steps, pruned count and score, and ``chosen``: its index."""

    def drops_bits(fit: tuple) -> bool:
        return any(step.endswith("-1") for step in fit[2]["steps"])

    t0 = time.perf_counter()
    worth = None if score is None or not MEASURE_BIT_WORTH else bit_worth(params, dict(CODED_BITS if bits is None else bits), score)
    facts = {}
    if worth is not None:
        facts = {"bit_worth": {k: {"gain": g, "loss": v} for k, (g, v) in worth.items()}, "bit_worth_seconds": time.perf_counter() - t0}
    first = fit_at_share(params, budget, bits, size_of, prune_share, worth=worth)
    if score is None or prune_share is not None or not drops_bits(first):
        return first[0], first[1], {**first[2], **facts}
    tried = [first]
    # the alternatives with a short prune search (a little less full), each on a thread of its own
    # (the codings are numpy and Zstandard work, which release the GIL); kept up to the first that
    # fits by pruning alone, since a larger share fits the same way: what a serial search keeps
    alternatives = CHOICE_SHARES[1:]
    with ThreadPoolExecutor(max_workers=len(alternatives)) as ex:
        futures = [ex.submit(fit_at_share, params, budget, bits, size_of, share, CHOICE_SEARCH_CODINGS, worth) for share in alternatives]
        for fut in futures:
            tried.append(fut.result())
            if not drops_bits(tried[-1]):
                break
    scores = [float(score(stored, b)) for stored, b, _ in tried]
    best = int(np.argmax(scores))
    codings = sum(t[2]["codings"] for t in tried)
    choice = [
        {"prune_share": t[2]["prune_share"], "steps": t[2]["steps"], "pruned": t[2]["pruned"], "psnr_db": sc}
        for t, sc in zip(tried, scores)
    ]
    if best > 0:  # the winner fitted again with the whole search, to fill the budget
        tried[best] = fit_at_share(params, budget, bits, size_of, tried[best][2]["prune_share"], worth=worth)
        codings += tried[best][2]["codings"]
    stored, b, info = tried[best]
    return stored, b, {**info, **facts, "codings": codings, "choice": choice, "chosen": best}


def fit_at_share(
    params: np.ndarray,
    budget: int,
    bits: dict[str, int] | None = None,
    size_of=None,
    prune_share: float | None = None,
    search: int = SEARCH_CODINGS,
    worth: BitWorth | None = None,
) -> tuple[np.ndarray, dict, dict]:
    """The coded model that fits ``budget`` bytes, as closely as bit depths and primitives allow.

    From ``bits`` (default :data:`CODED_BITS`): while the size exceeds the budget by more than
    ``prune_share`` (default :data:`PRUNE_SHARE`), drop bits of the attributes in :data:`SHRINK_ORDER` in turn; then prune
    the primitives that add least (:func:`importance`) until it fits (a primitive is the finest
    step there is, about 8 bytes). Then add bits in :data:`GROW_ORDER` while they still fit, so
    the budget buys precision when the primitives alone leave it unspent.

    Every size that decides is a real coding, but the steps between codings are predicted (a bit
    costs about one bit per stored value, a primitive the model's mean size), so a 900,000-
    primitive model is fitted in a handful of codings rather than dozens: bits are dropped as
    many at a time as the predicted excess needs, the prune count is found by interpolation
    (regula falsi) to within one primitive or :data:`FILL_SHARE` of the budget, and a bit is only
    tried when it is predicted to fit.

    Args:
        params: (N, 12) parameters.
        budget: Bytes the result may take, as ``size_of`` counts them.
        bits: Starting bit depths.
        size_of: ``size_of(params, bits)`` -> bytes (default: the coded payload alone; a model
            passes its whole file, header included).
        prune_share: See above.
        search: Codings the prune search may spend after the first fit.
        worth: :func:`bit_worth` of the model at ``bits``: bits are then dropped where they lose
            least and added where they gain most per byte, rather than in the fixed orders.

    Returns:
        ``(stored, bits, info)``: the parameters as the file will hold them (projected, Morton
        order), the bit depths, and what was done (steps, pruned count, bytes, codings, the size
        at the starting depths as ``first_bytes``, and ``kept``: the rows of ``params`` kept, in
        their order, for a refit of the pruned model).
    """
    with _FitCodes(canonical(params).astype(np.float32)) as fit:  # turned once: every coding finds the turns at once
        return _fit_at_share(fit, params, budget, bits, size_of, prune_share, search, worth)


def _fit_at_share(fit: _FitCodes, params, budget, bits, size_of, prune_share, search, worth) -> tuple[np.ndarray, dict, dict]:
    """:func:`fit_at_share`'s search, its codings' columns kept in ``fit``."""
    b = check_bits(dict(CODED_BITS if bits is None else bits))
    p = fit.base
    share = PRUNE_SHARE if prune_share is None else float(prune_share)
    keep = np.arange(len(p))
    codings = 0

    def size(pp, bb) -> int:
        nonlocal codings
        codings += 1
        return (size_of or (lambda q, c: len(encode_coded(q, c)[0])))(pp, bb)

    steps: list[str] = []
    cur = first = size(p, b)
    turn = 0
    pred: float  # the predicted size: less a bit's (fractional) bytes at each drop
    start = dict(b)
    while cur > budget * (1.0 + share):
        pred, dropped = cur, 0
        while pred > budget * (1.0 + share):
            k, turn = _next_drop(b, start, worth, turn)
            if k is None:
                break  # every depth at its least: pruning does the rest
            b[k] -= 1
            steps.append(f"{k}-1")
            pred -= _bit_bytes(len(p), k)
            dropped += 1
        if not dropped:
            break
        cur = size(p, b)
    pruned = 0
    if cur > budget:
        rank = np.argsort(-importance(p), kind="stable")  # most important first

        def kept(k: int) -> np.ndarray:
            return fit.subset(np.sort(rank[: len(p) - k]))

        lo, lo_size = 0, cur  # lo prunes too few (over budget); hi the fewest found that fit
        hi = hi_size = None
        cut = 0
        while hi is None:  # step out by the estimated excess (and 0.2 % more) until it fits
            per = cur / (len(p) - cut)
            cut = min(len(p) - 1, cut + max(1, int(np.ceil((cur - budget * (1.0 - FILL_SHARE / 2)) / per))))
            cur = size(kept(cut), b)
            if cur <= budget:
                hi, hi_size = cut, cur
            elif cut == len(p) - 1:
                raise WarpgaussError(f"no coded model of one primitive fits {budget} bytes; give a larger byte budget")
            else:
                lo, lo_size = cut, cur
        assert hi is not None and hi_size is not None  # the loop ends only where a size fits
        # then fewer pruned while more fit: interpolate between the two, halving when that stalls
        for _ in range(search):
            if hi - lo <= 1 or budget - hi_size <= FILL_SHARE * budget:
                break
            t = (lo_size - budget) / max(lo_size - hi_size, 1)
            mid = min(hi - 1, max(lo + 1, lo + int(round(t * (hi - lo)))))
            s = size(kept(mid), b)
            if s <= budget:
                hi, hi_size = mid, s
            else:
                lo, lo_size = mid, s
        p, pruned, cur = kept(hi), hi, hi_size
        keep = np.sort(rank[: len(rank) - hi])
    grown = True
    while grown:
        grown = False
        for k in _grow_order(b, start, worth):
            if b[k] < _MAX_BITS[k] and cur + _bit_bytes(len(p), k) * GROW_MARGIN <= budget:
                trial = {**b, k: b[k] + 1}
                t = size(p, trial)
                if t <= budget:
                    b, cur, grown = trial, t, True
                    steps.append(f"{k}+1")
                    if worth is not None:
                        break  # the order changes with each bit added
    info = {"steps": steps, "pruned": pruned, "bytes": cur, "first_bytes": first, "codings": codings, "prune_share": share, "kept": keep}
    return as_stored(p, b), b, info


def bits_for_psnr(psnr_db: float | None) -> tuple[dict[str, int], int]:
    """Bit depths for a model of about ``psnr_db`` (None: :data:`CODED_BITS`) and the bits added."""
    if psnr_db is None or not math.isfinite(psnr_db):
        return dict(CODED_BITS), 0
    extra = int(min(4, max(0, round((psnr_db - BITS_REFERENCE_DB) / DB_PER_BIT))))
    return {k: min(v + extra, _MAX_BITS[k]) for k, v in CODED_BITS.items()}, extra
