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

That is layout 1, the layout of ``.wgs`` format versions 1 and 2. New files are written in layout
2 (:mod:`warpgauss.coded_keys`, format version 3: the same codes and order, the centres as sorted
Morton key gaps, 4-9 % smaller on refined models), or in layout 1 where a centre axis spans 2^21
codes or more; :func:`decode_coded` reads both, and :func:`encode_coded` writes either.
"""

from __future__ import annotations

import math
import threading
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from ..errors import WarpgaussError
from .coded_keys import (
    _MAX_CODE,
    CODED_COLUMNS,
    KEY_AXIS_BITS,
    _order_and_keys,
    _resolve_ties,
    _sorted_keys,
    by_rows,
    check_keys,
    coded_order,
    decode_keys,
    encode_keys,
    gap_streams,
)
from .coded_keys import LAYOUT as LAYOUT_KEYS
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
_DELTA = ("mu_x", "mu_y", "mu_z")


# The least payload a coded primitive may take. Real models take more: 5.7-6.4 bytes a Gaussian at
# the coarsest depths bits_for_psnr gives (10 dB) and 2.2-3.4 at the least the rate control ever
# keeps (_MIN_BITS), on the analytic models of the four 48^3 examples at N 2,000-4,000; 6.9-14.0
# refined (README's table); in layout 2 2.1-2.7 at _MIN_BITS (N 3,000: bubbles 2.07, vortex 2.60)
# and 6.4-12.8 refined; the same row repeated 20,000 times codes to 0.0015. A file claiming more primitives than its payload could hold at this floor (a small
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
    log-scales moved with its axes (the first such rotation where several tie). Row by row (on
    threads for a large model)."""
    return by_rows(_canonical, np.asarray(params))


def _canonical(params: np.ndarray) -> np.ndarray:
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
            col = by_rows(make, p[:, cols], b[name])  # row by row: on threads for a large model
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
        self.orders: dict[tuple[int, int], dict] = {}  # (array id, centre depth) -> _sorted_keys and gap streams

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

    def order_entry(self, params, mu_bits: int) -> dict | None:
        """The storage-order entry of one of this fit's arrays at a centre depth (None for any
        other array), filled by :func:`_storage_order`."""
        entry = self.arrays.get(id(params))
        if entry is None or entry[0] is not params:
            return None
        return self.orders.setdefault((id(params), int(mu_bits)), {})

    def __enter__(self):  # the fit outside it kept by thread: several threads may enter one fit
        _FIT.outer = [*getattr(_FIT, "outer", []), getattr(_FIT, "codes", None)]
        _FIT.codes = self
        return self

    def __exit__(self, *exc):
        _FIT.codes = _FIT.outer.pop()

    def in_thread(self, fn):
        """``fn`` run with this fit active in the thread that calls it (trials on threads)."""

        def run(*args):
            with self:
                return fn(*args)

        return run


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


def _storage_order(
    params: np.ndarray, codes: np.ndarray, b: dict[str, int]
) -> tuple[np.ndarray, np.ndarray | None, tuple | None, dict | None]:
    """(storage order, Morton keys, their gap streams or None, the attribute columns' forms or
    None) of ``codes``: in a fit (:class:`_FitCodes`) what depends on the centre codes alone is
    kept by rows and centre depth, so a coding that changes other depths sorts and codes the
    centres once, and each attribute column's stored form is kept while the order stays the
    same (rows sharing a key are ordered by every code: a depth may change their order)."""
    fit = getattr(_FIT, "codes", None)
    entry = None if fit is None else fit.order_entry(params, b["mu"])
    if entry is None:
        order, key = _order_and_keys(codes)
        return order, key, None, None
    if "key" not in entry:
        entry.update(_sorted_keys(codes))
    order = _resolve_ties(codes, entry)
    key = entry["key"]
    if key is not None and "gaps" not in entry:
        entry["gaps"] = gap_streams(key[order])  # tied rows share a key: the same in any tie order
    if "forms_order" not in entry or not np.array_equal(entry["forms_order"], order):
        entry["forms_order"], entry["forms"] = order, {}
    return order, key, entry.get("gaps"), entry["forms"]


def _width(max_value: int) -> int:
    return max(1, (int(max_value).bit_length() + 7) // 8)


def encode_coded(params: np.ndarray, bits: dict[str, int] | None = None, layout: int | None = None) -> tuple[bytes, dict, np.ndarray]:
    """Code (N, 12) finite parameters, in ``layout`` (None: :data:`LAYOUT_KEYS`, the centres as
    sorted Morton key gaps (:mod:`warpgauss.coded_keys`), where every axis spans fewer than 2^21
    codes, else layout 1; 1: per-axis centre deltas and low-aligned byte planes, as warpgauss wrote
    before format version 3).

    Returns:
        ``(payload, quant, order)``: the compressed bytes, the JSON-ready description the decoder
        needs (bit depths, per-column coding, offset and byte width, raw size), and the
        permutation of ``params`` rows the file stores them in.
    """
    b = check_bits(dict(CODED_BITS if bits is None else bits))
    if layout not in (None, 1, LAYOUT_KEYS):
        raise WarpgaussError(f"unknown coded layout {layout!r}; this warpgauss writes layouts 1 and {LAYOUT_KEYS}")
    codes = quantise(params, b)
    order, key, gaps, forms = _storage_order(params, codes, b)
    codes = codes[order]
    if layout != 1:
        keys = None if key is None else key[order]  # centre_keys(codes[:, 0:3]), already computed
        if keys is not None:
            blocks, quant = encode_keys(codes, keys, b, gaps, forms)
            return _compress_planes(blocks, sum(len(p) for p in blocks)), quant, order
        if layout == LAYOUT_KEYS:
            raise WarpgaussError(
                f"centres spanning 2^{KEY_AXIS_BITS} codes or more on an axis have no layout {LAYOUT_KEYS}; write layout 1"
            )
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
    layout = coded_layout(quant)
    check_claim(len(payload), n)
    if layout == LAYOUT_KEYS:
        offsets, widths, least, most = check_keys(quant, n, _offset)
        codes = decode_keys(_decompress(payload, least, most), n, offsets, widths)
    else:
        codes = _decode_layout1(payload, n, quant)
    lev = _q_levels(b["q"])
    if np.any((codes[:, 6] < 0) | (codes[:, 6] > 3)) or np.any((codes[:, 7:10] < 0) | (codes[:, 7:10] > lev)):
        raise WarpgaussError("coded rotations hold codes outside their range; the file is damaged")
    if np.any(codes[:, 11] < 1):
        raise WarpgaussError("coded weights hold codes below 1; the file is damaged")
    return dequantise(codes, b)


def _decompress(payload: bytes, least: int, most: int) -> bytes:
    """The contents of a Zstandard frame that declares from ``least`` to ``most`` bytes (checked
    before it is decompressed, into at most that)."""
    zstd = zstandard_module()
    try:
        raw = zstd.get_frame_parameters(payload).content_size
        if not least <= raw <= most:
            raise WarpgaussError(f"coded payload frame holds {raw} bytes, its columns make {least} to {most}; the file is damaged")
        blob = zstd.ZstdDecompressor().decompress(payload, max_output_size=raw)
    except zstd.ZstdError as e:
        raise WarpgaussError(f"coded payload does not decompress ({e}); the file is damaged") from None
    if len(blob) != raw:
        raise WarpgaussError(f"coded payload decompresses to {len(blob)} bytes, expected {raw}; the file is damaged")
    return blob


def coded_layout(quant: dict) -> int:
    """The layout of a coded payload description: 1 (no ``layout`` key) or :data:`LAYOUT_KEYS`."""
    layout = quant.get("layout", 1) if isinstance(quant, dict) else None
    if isinstance(layout, bool) or layout not in (1, LAYOUT_KEYS):
        raise WarpgaussError(
            f"unknown coded layout {layout!r} (this warpgauss reads 1 and {LAYOUT_KEYS}); upgrade warpgauss or the file is damaged"
        )
    return int(layout)


def _decode_layout1(payload: bytes, n: int, quant: dict) -> np.ndarray:
    """(n, 12) int64 codes of a layout-1 payload."""
    cols = quant.get("columns")
    if not isinstance(cols, list) or len(cols) != len(CODED_COLUMNS) or not all(isinstance(c, list) and len(c) == 2 for c in cols):
        raise WarpgaussError(f"the coded column list must hold {len(CODED_COLUMNS)} (offset, bytes) pairs; the file is damaged")
    widths, offsets = [], []
    for (off, w), name in zip(cols, CODED_COLUMNS):
        if isinstance(w, bool) or not isinstance(w, int) or not 1 <= w <= 8:
            raise WarpgaussError(f"coded column {name} width {w!r} is not 1..8 bytes; the file is damaged")
        widths.append(w)
        offsets.append(_offset(name, off))
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
    return codes
