"""Layout 2 of the ``coded`` payload: the centres as a sorted set of Morton keys, the other
attributes as top-aligned byte planes, each column stored as is or as the residual of a
prediction from its neighbours along the curve, whichever codes smaller; one Zstandard frame
(``.wgs`` format version 3).

The codes are those of layout 1 (:mod:`warpgauss.format.coded`: the same grids, the same canonical turns,
the same storage order), so the accuracy is the same; only their representation differs::

    centres     the Morton key of each centre code (offset to the per-axis minimum, 21 bits an axis),
                in storage order (ascending), as gaps from the previous key (the first from 0);
                each gap g > 0 of e = bit_length(g) bits is one symbol byte 2 e + (g's bit below
                the leading one; 0 where e = 1) and its e - 2 bits below that, raw (Elias-gamma-
                like): a byte plane of n symbols and a packed bit string (most significant first)
    attributes  the nine other columns, each either its values or its residuals after
                :func:`lift` (position i, an odd multiple of 2^L, predicted by the mean of the
                positions 2^L before and after it, which a decoder has from the coarser levels:
                every level is one vectorised step both ways); as its offset from its minimum in
                w bits (w = 0: a constant column, nothing stored), top-aligned into ceil(w / 8)
                bytes, byte planes from the most significant: the top plane holds a value's top
                8 bits, whose distribution is peaked, the lower ones its nearly uniform low bits

Frame contents in order: a 2-byte little-endian mask of the columns stored as residuals (bit k:
column k of :data:`CODED_COLUMNS`, 3-11 only), the n gap symbols (one block with
the mask), the packed bits (a block), then for each group of :data:`GROUPS` its columns' first
planes, then their second planes, ... (a block each: a group shares a literal table). Levels as
:data:`warpgauss.format.coded.ZSTD_LEVELS`, the smaller frame kept. The description in the header holds
the bit depths, per column ``[offset, width in bits]`` (the centre columns: the axis minimum and
the bit length of the axis span) and ``"layout": 2``; no raw size: the frame declares it, and a
reader checks it against what the columns make before it decompresses.

Why this and not context models (measured on 21 refined H200 models, three head MRIs at CR
10-1000 and the vortex and interface fields at 256^3, ``benchmarks/accuracy/coded_context.py``,
``benchmarks/results/accuracy/coded_context_cpu.json``): once a Gaussian's canonical turn and the
absolute grids fix its codes, its log-scales, turn, value and weight are close to independent of
its neighbours' and of one another on the MRIs: a residual from the mean of its 4 nearest coded
neighbours had a larger order-0 entropy than the log-scales, turn and weight themselves on every
MRI model, and the value's fell by 0.3 bits at most; an adaptive count model conditioned on that
mean (8 buckets) saved at most 0.4 % of the file at CR 100-1000 and cost up to 2 % at small N
(what it must learn), 0.3-1.9 % at CR 10-30, 2.3-5.3 % on the interface field (its log-scales
follow the neighbours'): not worth a sequential adaptive coder in numpy. The centres are where the
bytes were: layout 1 stored three per-axis deltas along the Morton order, about 3 bits a Gaussian
above the entropy of the set (the order of N centres carries no information: log2 N! bits), which
the key gaps recover (Hilbert keys' gaps take 0.03-0.08 bits a Gaussian less, 0.1 % of the file:
not worth a second curve). The value is smooth along the curve on the fields (vortex: 11.3 ->
9.2-10.0 bits as residuals), hence the per-column choice. The top-aligned planes recover what
splitting a 9-12 bit column at its lowest byte lost (up to 0.5 bits a value).

Decoding checks every declared width and offset against the header before it allocates,
decompresses into at most what the columns can make, checks the mask, the symbols, the bit count
and its padding, that the keys ascend without overflow and the centres stay within their declared
spans, and rejects codes outside their ranges; no pickle.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from ..errors import WarpgaussError

LAYOUT = 2
CODED_COLUMNS = ("mu_x", "mu_y", "mu_z", "log_sx", "log_sy", "log_sz", "q_index", "q_0", "q_1", "q_2", "a", "w")  # both layouts'
_MAX_CODE = 1 << 52  # |code| bound: every code and difference is exact in float64 and int64
KEY_AXIS_BITS = 21  # Morton keys of 3 x 21 bits: a wider centre range is stored in layout 1
_MAX_E = 63  # a gap's bit length: keys are below 2^63
_LIFTABLE = sum(1 << k for k in range(3, 12))  # the columns that may be stored as lift() residuals


def _bit_length(v: np.ndarray) -> np.ndarray:
    """Bit lengths (int64) of uint64 values: the binary exponent of their float64 values, exact
    below 2^53 (the rare larger values by shifts)."""
    e = np.frexp(v.astype(np.float64))[1].astype(np.int64)
    big = v >= np.uint64(1 << 53)
    if big.any():
        e[big] = _bit_length_shifts(v[big])
    return e


def _bit_length_shifts(v: np.ndarray) -> np.ndarray:
    """Bit lengths (int64) of uint64 values, by halving (any value)."""
    e = np.zeros(len(v), np.int64)
    g = v.copy()
    for sh in (32, 16, 8, 4, 2, 1):
        big = g >= np.uint64(1 << sh)
        e += big * sh
        g = np.where(big, g >> np.uint64(sh), g)
    return e + (g > 0)


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


def _compact1by2(v: np.ndarray) -> np.ndarray:
    """Every third bit of v gathered into the low 21 bits (inverse of the Morton spread)."""
    v = v & np.uint64(0x1249249249249249)
    for shift, mask in (
        (2, 0x10C30C30C30C30C3),
        (4, 0x100F00F00F00F00F),
        (8, 0x1F0000FF0000FF),
        (16, 0x1F00000000FFFF),
        (32, 0x1FFFFF),
    ):
        v = (v | (v >> np.uint64(shift))) & np.uint64(mask)
    return v


def centre_keys(mu: np.ndarray) -> np.ndarray | None:
    """Morton keys (uint64) of centre codes ``mu`` (n, 3) offset to their minimum, or None where an
    axis spans 2^21 codes or more."""
    if len(mu) == 0:
        return np.zeros(0, np.uint64)
    m = mu - mu.min(0)
    if int(m.max()) >= 1 << KEY_AXIS_BITS:
        return None
    return _part1by2(m[:, 0]) | (_part1by2(m[:, 1]) << np.uint64(1)) | (_part1by2(m[:, 2]) << np.uint64(2))


def coded_order(codes: np.ndarray) -> np.ndarray:
    """The storage order: by Morton code of the centre codes (offset to 0), ties by every code; a
    centre range wider than 2^21 codes on an axis falls back to z, y, x order.

    Equal to ``np.lexsort`` over (every code, then the key), computed as one sort of the key and
    a lexsort of the rows whose key is shared (a few, where centres share a grid cell).
    """
    return _order_and_keys(codes)[0]


def _order_and_keys(codes: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
    """:func:`coded_order` and the rows' Morton keys (None where it falls back): in storage order
    the keys are :func:`centre_keys` of the stored centres (the same
    offsets: a permutation has the same minimum)."""
    sorted_keys = _sorted_keys(codes)
    return _resolve_ties(codes, sorted_keys), sorted_keys["key"]


def _sorted_keys(codes: np.ndarray) -> dict:
    """What of the storage order depends on the centre codes alone: the Morton keys (None where an
    axis spans 2^21 codes or more), the rows sorted by key and the positions whose key is shared."""
    key = centre_keys(codes[:, 0:3])
    if key is None:
        return {"key": None}
    # any sort of the keys: rows of a unique key land where a stable sort puts them, and the rows
    # sharing a key are put in full-lexsort order by _resolve_ties whatever order they came in
    order = np.argsort(key)
    ks = key[order]
    tie = np.zeros(len(ks), bool)
    if len(ks) > 1:
        same = ks[1:] == ks[:-1]
        tie[1:] |= same
        tie[:-1] |= same
    return {"key": key, "order": order, "ties": np.flatnonzero(tie)}


def _resolve_ties(codes: np.ndarray, sorted_keys: dict) -> np.ndarray:
    """The storage order from :func:`_sorted_keys` and every code: rows sharing a key in
    full-lexsort order (every code, then the original order); without keys, z, y, x order."""
    key = sorted_keys["key"]
    mu = codes[:, 0:3] - codes[:, 0:3].min(0) if len(codes) else codes[:, 0:3]
    if key is None:
        keys = [codes[:, k] for k in range(11, 2, -1)]  # least significant first for lexsort
        return np.lexsort([*keys, mu[:, 0], mu[:, 1], mu[:, 2]])
    order = sorted_keys["order"].copy()
    pos = sorted_keys["ties"]
    if len(pos):  # rows sharing a key: their positions, filled in full-lexsort order
        rows = np.sort(order[pos])  # original order, so the lexsort's ties resolve as the full one's
        sub = codes[rows]
        smu = mu[rows]
        sub_order = np.lexsort([*[sub[:, k] for k in range(11, 2, -1)], smu[:, 0], smu[:, 1], smu[:, 2], key[rows]])
        order[pos] = rows[sub_order]
    return order


def gap_streams(keys: np.ndarray) -> tuple[bytes, bytes, int]:
    """(symbol plane, packed remainder bits, bit count) of ascending keys."""
    gap = np.diff(keys, prepend=np.uint64(0))
    e = _bit_length(gap)
    top = np.where(e >= 2, (gap >> np.maximum(e - 2, 0).astype(np.uint64)) & np.uint64(1), 0).astype(np.int64)
    sym = (2 * e + top).astype(np.uint8)
    r = np.maximum(e - 2, 0)  # raw bits below the leading one and the symbol's bit
    rest = gap & ((np.uint64(1) << r.astype(np.uint64)) - np.uint64(1))
    packed, total = pack_fields(rest, r)
    return sym.tobytes(), packed, total


def pack_fields(v: np.ndarray, r: np.ndarray) -> tuple[bytes, int]:
    """Values ``v`` (uint64, each below 2^r) as fields of ``r`` (0-61) bits, most significant bit
    first, one after the other; (bytes, bit count), the last byte padded with 0 bits. Word by word
    (a field spans at most two 64-bit words), not bit by bit."""
    total = int(r.sum())
    if total == 0:
        return b"", 0
    keep = r > 0
    v, r = v[keep], r[keep]
    s = np.cumsum(r) - r  # each field's first bit
    w, off = s >> 6, s & 63
    end = off + r
    fits = end <= 64
    words = np.zeros((total + 63) // 64 + 1, np.uint64)
    first = np.where(fits, v << np.where(fits, 64 - end, 0).astype(np.uint64), v >> np.where(fits, 0, end - 64).astype(np.uint64))
    np.bitwise_or.at(words, w, first)
    over = ~fits
    np.bitwise_or.at(words, w[over] + 1, v[over] << (128 - end[over]).astype(np.uint64))
    return words.astype(">u8").tobytes()[: (total + 7) // 8], total


def unpack_fields(data: bytes, r: np.ndarray) -> np.ndarray:
    """The uint64 fields of widths ``r`` (0-61) that :func:`pack_fields` packed into ``data``
    (its bit count checked by the caller)."""
    out = np.zeros(len(r), np.uint64)
    keep = np.flatnonzero(r)
    if len(keep) == 0:
        return out
    rk = r[keep]
    s = np.cumsum(rk) - rk
    w, off = s >> 6, (s & 63).astype(np.uint64)
    words = np.frombuffer(bytes(data) + bytes(16 - len(data) % 8), ">u8").astype(np.uint64)
    hi = words[w] << off
    lo = np.where(off > 0, words[w + 1] >> (np.uint64(64) - np.where(off > 0, off, np.uint64(1))), np.uint64(0))
    out[keep] = (hi | lo) >> (64 - rk).astype(np.uint64)
    return out


def _planes(v: np.ndarray, w: int) -> list[bytes]:
    """Top-aligned byte planes (most significant first) of values below 2^w."""
    nb = (w + 7) // 8
    if nb == 0:
        return []
    aligned = (v.astype(np.uint64) << np.uint64(8 * nb - w)).astype(">u8")  # big-endian: the top byte first
    rows = np.ascontiguousarray(aligned.view(np.uint8).reshape(-1, 8)[:, 8 - nb :].T)
    return [r.tobytes() for r in rows]


def _predicted(c: np.ndarray, s: int) -> np.ndarray:
    """The predictions of positions s, 3s, 5s, ... of ``c`` (along the last axis) from positions
    i - s and i + s: their mean, rounded down (i - s alone where i + s is past the end)."""
    n = c.shape[-1]
    left = c[..., 0 : n - s : 2 * s]
    right = c[..., 2 * s :: 2 * s]
    if right.shape[-1] < left.shape[-1]:
        right = np.concatenate([right, left[..., right.shape[-1] :]], axis=-1)
    return (left + right) >> 1


def lift(c: np.ndarray) -> np.ndarray:
    """Residuals of int64 values ``c`` (storage order, along the last axis: a column, or one
    column a row of a (k, n) array) after predicting each from the two nearest of a coarser
    level: position i, an odd multiple of s = 2^L, from the mean (rounded down) of positions
    i - s and i + s (i - s alone past the end); position 0 is its own residual. Each level is one
    vectorised step."""
    r = c.copy()
    s = 1
    while s < c.shape[-1]:
        r[..., s :: 2 * s] = c[..., s :: 2 * s] - _predicted(c, s)
        s *= 2
    return r


def unlift(r: np.ndarray) -> np.ndarray:
    """The values whose :func:`lift` residuals are ``r`` (the coarsest level first)."""
    c = r.copy()
    n = r.shape[-1]
    s = 1
    while 2 * s < n:
        s *= 2
    while s >= 1 and n > 1:
        c[..., s :: 2 * s] = r[..., s :: 2 * s] + _predicted(c, s)
        s //= 2
    return c


def _column(c: np.ndarray) -> tuple[int, int, list[bytes]]:
    """(offset, width in bits, top-aligned planes) of an int64 column."""
    off = int(c.min()) if len(c) else 0
    v = c - off
    w = int(v.max()).bit_length() if len(c) else 0
    return off, w, _planes(v, w)


def _zstd_size(planes: list[bytes]) -> int:
    """Bytes of Zstandard level 1 frames of each plane (to compare two forms of a column)."""
    import zstandard  # a dependency of the package (warpgauss.format.coded.zstandard_module says so where it is missing)

    co = zstandard.ZstdCompressor(level=1)
    return sum(len(co.compress(p)) for p in planes)


def _plane_bits(planes: list[bytes]) -> float:
    """Order-0 entropy (bits) of byte planes, each alone: what a literal table per plane costs."""
    total = 0.0
    for p in planes:
        counts = np.bincount(np.frombuffer(p, np.uint8), minlength=256)
        counts = counts[counts > 0]
        total -= float((counts * np.log2(counts / counts.sum())).sum())
    return total


# the attribute columns whose planes share a Zstandard block (a literal table): the three
# log-scales, the rotation index, the three rotation components, the value, the weight. Columns of
# one distribution gain nothing from tables of their own, and at small N a table is a share of the
# file: 1.4 % at N 767 (mni_icbm152 CR 1000), 0.6-1.0 % at 2,000-3,400, +-0.1 % from 10,000
GROUPS = ((3, 4, 5), (6,), (7, 8, 9), (10,), (11,))


# a coding's column work (quantising, lifting, choosing each column's form) runs on up to this many
# threads where a model has at least PARALLEL_MIN_ROWS primitives: numpy releases the GIL in its
# loops, and every step is row by row or column by column, so the bytes are those of one thread.
# Measured on one H200 host (16 cores): a coding of 1.1M Gaussians took 2-3 s on one thread
# (benchmarks/results/speed/host_profile_interface512_h200.json)
CODING_THREADS = 0  # 0: the host's cores, at most 8
PARALLEL_MIN_ROWS = 1 << 16


def coding_threads() -> int:
    """Threads a coding's column work may use (:data:`CODING_THREADS`)."""
    return int(CODING_THREADS) if CODING_THREADS > 0 else min(8, os.cpu_count() or 1)


def coding_map(fn, items: list, rows: int) -> list:
    """``[fn(x) for x in items]``, on threads (at most :func:`coding_threads`) where ``rows`` is
    at least :data:`PARALLEL_MIN_ROWS`; exceptions raised as the loop would raise them."""
    threads = coding_threads()
    if rows < PARALLEL_MIN_ROWS or len(items) < 2 or threads < 2:
        return [fn(x) for x in items]
    with ThreadPoolExecutor(max_workers=min(threads, len(items))) as ex:
        return list(ex.map(fn, items))


def row_chunks(n: int) -> list[slice]:
    """Row ranges of ``n`` rows for :func:`coding_map`: one a thread, each of at least
    :data:`PARALLEL_MIN_ROWS` / 2 rows (one range below :data:`PARALLEL_MIN_ROWS`)."""
    k = max(1, min(coding_threads(), 2 * n // PARALLEL_MIN_ROWS)) if n >= PARALLEL_MIN_ROWS else 1
    return [slice(i * n // k, (i + 1) * n // k) for i in range(k)]


def by_rows(fn, x: np.ndarray, *args) -> np.ndarray:
    """``fn(x, *args)`` for a row-by-row ``fn`` (each output row depends on its input row alone),
    computed by chunks of rows on threads and stacked."""
    chunks = row_chunks(len(x))
    if len(chunks) == 1:
        return fn(x, *args)
    return np.concatenate(coding_map(lambda s: fn(x[s], *args), chunks, len(x)))


# the attribute (its bit depth's name) of each stored column after the centres, from the one column table
_ATTRIBUTE_OF = {k: next(a for a in ("log_s", "q", "a", "w") if name.startswith(a)) for k, name in enumerate(CODED_COLUMNS) if k >= 3}


def encode_keys(
    codes: np.ndarray, keys: np.ndarray, bits: dict[str, int], gaps: tuple | None = None, forms: dict | None = None
) -> tuple[list[bytes], dict]:
    """Layout-2 frame blocks (the frame's contents, each to end a Zstandard block) and description
    of (n, 12) codes in storage order whose centre keys ``keys`` (:func:`centre_keys`) ascend
    (``gaps``: their :func:`gap_streams`, where the caller has them; ``forms``: each attribute
    column's stored form by column, kept by a fit for the codings of one storage order, so that a
    coding that changes one attribute's depth works out that attribute's columns alone)."""
    n = len(codes)
    sym, packed, nbits = gap_streams(keys) if gaps is None else gaps
    columns: list[list[int]] = []
    mu_min = codes[:, 0:3].min(0) if n else np.zeros(3, np.int64)
    for k in range(3):
        span = int(codes[:, k].max() - mu_min[k]) if n else 0
        columns.append([int(mu_min[k]), span.bit_length()])
    mask = 0
    col_planes: dict[int, list[bytes]] = {}

    def form(k: int) -> tuple[tuple[int, int, list[bytes]], bool]:
        # the column contiguous (reductions over strided columns of the (n, 12) codes took most
        # of a coding's column work), and its residuals after lift
        values = np.ascontiguousarray(codes[:, k])
        col = _column(values)
        if col[1] and n > 2:  # a stored column: its residuals may code smaller;
            # they are kept where their planes' order-0 entropy is smaller and one Zstandard
            # compression each confirms it (the entropy alone misjudged a width crossing 8 bits)
            lifted = _column(lift(values))
            if abs(lifted[0]) <= 1 << 52 and lifted[1] <= 53 and _plane_bits(lifted[2]) < _plane_bits(col[2]):
                if _zstd_size(lifted[2]) < _zstd_size(col[2]):
                    return lifted, True
        return col, False

    # a copy first (one C call under the GIL): a fit's trials on threads share ``forms``
    known = {} if forms is None else {k: f[1] for k, f in dict(forms).items() if f[0] == bits[_ATTRIBUTE_OF[k]]}
    todo = [k for k in range(3, 12) if k not in known]
    known.update(zip(todo, coding_map(form, todo, n)))
    if forms is not None:
        forms.update({k: (bits[_ATTRIBUTE_OF[k]], known[k]) for k in todo})
    for k in range(3, 12):
        col, is_lifted = known[k]
        if is_lifted:
            mask |= 1 << k
        columns.append([col[0], col[1]])
        col_planes[k] = col[2]
    blocks = [mask.to_bytes(2, "little") + sym, packed]
    for group in GROUPS:
        for j in range(max(len(col_planes[k]) for k in group)):
            blocks.append(b"".join(col_planes[k][j] for k in group if j < len(col_planes[k])))
    assert len(packed) == (nbits + 7) // 8
    # no raw size: the frame declares it (checked against the columns before it is decompressed),
    # so the description is no wider than layout 1's and a header reserved for either holds both
    return blocks, {"bits": bits, "columns": columns, "layout": LAYOUT}


def check_keys(quant: dict, n: int, offset_check) -> tuple[list[int], list[int], int, int]:
    """(offsets, widths, least and most frame bytes) of a layout-2 description of ``n`` primitives,
    every field checked (``offset_check(name, v)`` validates a declared offset) before anything
    is allocated or decompressed."""
    cols = quant.get("columns")
    if not isinstance(cols, list) or len(cols) != len(CODED_COLUMNS) or not all(isinstance(c, list) and len(c) == 2 for c in cols):
        raise WarpgaussError(f"the coded column list must hold {len(CODED_COLUMNS)} (offset, bits) pairs; the file is damaged")
    offsets, widths = [], []
    for k, ((off, w), name) in enumerate(zip(cols, CODED_COLUMNS)):
        hi = KEY_AXIS_BITS if k < 3 else 53
        if isinstance(w, bool) or not isinstance(w, int) or not 0 <= w <= hi:
            raise WarpgaussError(f"coded column {name} width {w!r} is not 0..{hi} bits; the file is damaged")
        offsets.append(offset_check(name, off))
        widths.append(w)
    nplanes = sum((w + 7) // 8 for w in widths[3:])
    fixed = 2 + n + nplanes * n
    return offsets, widths, fixed, fixed + (n * (_MAX_E - 2) + 7) // 8  # at most: every gap of 63 bits


def decode_keys(blob: bytes, n: int, offsets: list[int], widths: list[int]) -> np.ndarray:
    """(n, 12) int64 codes of a layout-2 frame's contents ``blob`` (in the file's order), its
    description checked by :func:`check_keys`. Raises :class:`WarpgaussError` on anything
    inconsistent."""
    raw = len(blob)
    fixed = 2 + n + sum((w + 7) // 8 for w in widths[3:]) * n
    if raw < fixed:
        raise WarpgaussError(f"coded payload holds {raw} bytes, its columns make {fixed} at least; the file is damaged")
    mask = int.from_bytes(blob[:2], "little")
    if mask & ~_LIFTABLE:
        raise WarpgaussError(f"coded payload marks columns {mask:#x} as predicted, only {_LIFTABLE:#x} can be; the file is damaged")
    buf = np.frombuffer(blob, np.uint8)[2:]
    sym = buf[:n].astype(np.int64)
    e, top = sym >> 1, sym & 1
    if np.any(e > _MAX_E) or np.any((e < 2) & (top != 0)):
        raise WarpgaussError("coded centre gaps hold symbols outside their range; the file is damaged")
    r = np.maximum(e - 2, 0)
    nbits = int(r.sum())
    npacked = raw - fixed
    if npacked != (nbits + 7) // 8:
        raise WarpgaussError(f"coded centre gaps need {(nbits + 7) // 8} bytes of bits, the payload holds {npacked}; the file is damaged")
    gap = np.where(e > 0, np.uint64(1) << np.maximum(e - 1, 0).astype(np.uint64), np.uint64(0))
    gap |= top.astype(np.uint64) << r.astype(np.uint64)
    if nbits:
        if int(buf[n + npacked - 1]) & ((1 << (8 * npacked - nbits)) - 1):
            raise WarpgaussError("coded centre gaps end in padding bits that are not 0; the file is damaged")
        gap |= unpack_fields(buf[n : n + npacked].tobytes(), r)
    keys = np.cumsum(gap, dtype=np.uint64)
    if n and (np.any(keys[1:] < keys[:-1]) or keys[-1] >= np.uint64(1 << 63)):
        raise WarpgaussError("coded centre keys overflow; the file is damaged")
    codes = np.empty((n, 12), np.int64)
    for k in range(3):
        c = _compact1by2(keys >> np.uint64(k)).astype(np.int64)
        if np.any(c >= 1 << widths[k]):
            raise WarpgaussError(
                f"coded column {CODED_COLUMNS[k]} holds a centre beyond its declared {widths[k]} bits; the file is damaged"
            )
        codes[:, k] = offsets[k] + c
    at = n + npacked
    aligned = {k: np.zeros(n, np.uint64) for k in range(3, 12)}
    for group in GROUPS:  # the encoder's order: a group's first planes, then its second, ...
        for j in range(max((widths[k] + 7) // 8 for k in group)):
            for k in group:
                if j < (widths[k] + 7) // 8:
                    aligned[k] = (aligned[k] << np.uint64(8)) | buf[at : at + n].astype(np.uint64)
                    at += n
    for k in range(3, 12):
        w = widths[k]
        nb = (w + 7) // 8
        pad = np.uint64(8 * nb - w)
        if nb and np.any(aligned[k] & ((np.uint64(1) << pad) - np.uint64(1))):
            raise WarpgaussError(f"coded column {CODED_COLUMNS[k]} holds padding bits that are not 0; the file is damaged")
        v = offsets[k] + (aligned[k] >> pad).astype(np.int64)
        codes[:, k] = unlift(v) if mask >> k & 1 else v
    if np.any(np.abs(codes) > _MAX_CODE):
        raise WarpgaussError("coded columns decode beyond 2^52; the file is damaged")
    return codes
