"""How many bytes a Gaussian a coder with context could save over the coded layout (issue #53
part 1, "a coder with context"), on refined models: host only, no device.

For each model (a ``.npz`` of the encoder's float32 ``params`` and the ``bits_*`` depths its rate
control chose, and its ``.wgs`` beside it for the file as written):

* bytes a Gaussian now: the ``.wgs`` file, its header and its payload (the layout it was written
  in), and the payload :func:`warpgauss.format.coded.encode_coded` writes today (layout 2);
* codes and storage order from the coder itself (:func:`coded.quantise`, :func:`coded.coded_order`,
  :func:`coded_keys.encode_keys` for the columns layout 2 stores as lifted residuals), checked equal
  to the codes of the ``.wgs`` file's parameters; per column, the order-0 entropy of what layout 2
  stores (centres: the key-gap symbols plus their raw bits; every other column its values, or the
  lift residuals where the coder chose them), and of its Zstandard blocks' bytes;
* every attribute column (log-scales, rotation index and components, value a, weight w) coded in
  storage order, predicted from already-coded primitives: the previous one; the median and the
  rounded mean of the k = 4 and 8 nearest *earlier* primitives by centre code (exact causal
  neighbours: the nearest among all by cKDTree, the earlier kept; rows with fewer than k earlier
  among the 64 nearest are searched among all earlier ones); a least-squares joint predictor from
  the neighbours' mean and the Gaussian's own already-coded columns (log-scale y from x, z from
  x and y, a from the log-scales, w from a); and context models: the value given a bucket of the
  neighbours' mean, of its own coded columns, or both, the residual given a bucket of the
  neighbours' spread (LOCO-I/CALIC activity);
* the centres: the key gaps as stored, an adaptive gap symbol given the previous one, and an
  octree of occupancy bits (G-PCC style: each child bit coded adaptively given its level, the
  parent's occupied face neighbours and the siblings coded so far), against the set bound
  log2 C(V, N) / N of N cells uniform in their box and a density bound (:func:`density_bound`);
* a side figure, not a context model: the rotation bits on Gaussians with two equal log-scale
  codes, one of whose three rotation components is free.

Each candidate gets two figures: the empirical (conditional) entropy H(X | C), a bound that at
small N and many contexts is optimistic (it does not pay for learning the distributions), and the
code length of an adaptive count model (Krichevsky-Trofimov counts per context, learning cost
included; for wide alphabets also a binarised form: the residual's bit length adaptive, the next
bit adaptive, the rest raw), which is what a sequential adaptive arithmetic coder would write.
The estimates: sum over columns of the best entropy x (1 + OVERHEAD) (a coder's 3-5 %), and the sum
of the best adaptive code lengths (a model picked per column by its length).

    python benchmarks/format/context_entropy.py /work/models/*.npz \\
        --out benchmarks/results/format/context_entropy_cpu.json
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from warpgauss.encoding.bench import result_header
from warpgauss.format import coded, coded_keys
from warpgauss.format.coded_keys import CODED_COLUMNS
from warpgauss.format.wgs import read_wgs

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "accuracy"))
from coded_context import adaptive_bits  # noqa: E402  (the adaptive count model, one copy)

MRI = ("inia19", "mean_reg2mean", "mni_icbm152")
ATTRS = tuple(range(3, 12))  # log_sx .. w
OVERHEAD = 0.04  # a practical arithmetic/rANS coder over the entropy (3-5 %: table or model precision)
KS = (4, 8)
NEAREST = 64  # nearest among all queried per row; rows with fewer than k earlier ones are searched exactly
GROUP_NAMES = {"mu": (0, 1, 2), "log_s": (3, 4, 5), "q": (6, 7, 8, 9), "a": (10,), "w": (11,)}


# -- code lengths ---------------------------------------------------------------------------------


def entropy_bits(x: np.ndarray, ctx: np.ndarray | None = None) -> float:
    """Empirical entropy, total bits, of integer symbols ``x`` (given ``ctx``: H(X, C) - H(C))."""

    def h(v: np.ndarray) -> float:
        _, counts = np.unique(v, return_counts=True)
        return float(-(counts * np.log2(counts / counts.sum())).sum())

    x = np.asarray(x, np.int64)
    if len(x) == 0:
        return 0.0
    if ctx is None:
        return h(x)
    c = np.unique(np.asarray(ctx, np.int64), return_inverse=True)[1].reshape(-1)
    xs = np.unique(x, return_inverse=True)[1].reshape(-1)
    return h(c * (int(xs.max()) + 1) + xs) - h(c)


def binned_bits(res: np.ndarray, ctx: np.ndarray | None = None) -> float:
    """Code length of integer residuals binarised as a coder with few parameters would: the bit
    length e of the zigzagged residual adaptive (given ``ctx``), the bit below its leading one
    adaptive given (ctx, e), the e - 2 bits below that raw."""
    r = np.asarray(res, np.int64)
    z = ((r << 1) ^ (r >> 63)).astype(np.uint64)
    e = coded_keys._bit_length(z)
    c = np.zeros(len(r), np.int64) if ctx is None else np.unique(np.asarray(ctx, np.int64), return_inverse=True)[1].reshape(-1)
    top = np.where(e >= 2, (z >> np.maximum(e - 2, 0).astype(np.uint64)) & np.uint64(1), 0).astype(np.int64)
    two = e >= 2
    bits = adaptive_bits(e, c) + float(np.maximum(e - 2, 0).sum())
    if two.any():
        bits += adaptive_bits(top[two], (c * 64 + e)[two])
    return bits


def code_lengths(res: np.ndarray, ctx: np.ndarray | None) -> dict:
    """The two figures of a candidate (total bits): entropy and the better adaptive model."""
    return {"entropy": entropy_bits(res, ctx), "adaptive": min(adaptive_bits(res, ctx), binned_bits(res, ctx))}


def buckets(v: np.ndarray, nb: int) -> np.ndarray:
    """Quantile buckets (0 .. nb - 1) of a context variable (the edges: a few header numbers)."""
    edges = np.unique(np.quantile(v, np.linspace(0.0, 1.0, nb + 1)[1:-1]))
    return np.searchsorted(edges, v, side="right")


# -- causal neighbours ----------------------------------------------------------------------------


def causal_knn(pts: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """The k nearest *earlier* rows of each row of ``pts`` (storage order) by Euclidean distance:
    (indices (n, k), valid (n, k)); rows with fewer than k earlier rows have the rest invalid."""
    n = len(pts)
    idx = np.zeros((n, k), np.int64)
    valid = np.zeros((n, k), bool)
    if n < 2:
        return idx, valid
    tree = cKDTree(pts)
    rows = np.arange(n)
    todo = rows
    for big in (NEAREST, 16 * NEAREST):
        kk = min(big, n)
        _, near = tree.query(pts[todo], k=kk)
        earlier = near < todo[:, None]
        first = np.argsort((~earlier).view(np.uint8), axis=1, kind="stable")[:, :k]  # earlier ones, nearest first
        got = np.take_along_axis(earlier, first, 1)
        done = got.all(1) | (kk == n)
        idx[todo[done]] = np.take_along_axis(near, first, 1)[done]
        valid[todo[done]] = got[done]
        todo = todo[~done]
        if len(todo) == 0:
            break
    for i in todo:  # the few left: every earlier row
        d = ((pts[:i] - pts[i]) ** 2).sum(1)
        sel = np.argsort(d, kind="stable")[:k]
        idx[i, : len(sel)] = sel
        valid[i, : len(sel)] = True
    return idx, valid


def neighbour_stats(c: np.ndarray, idx: np.ndarray, valid: np.ndarray, fallback: int) -> dict:
    """The neighbours' median and rounded mean of column ``c`` (``fallback`` with no neighbour)
    and their spread (mean absolute deviation from the mean)."""
    vals = np.where(valid, c[idx], 0).astype(np.float64)
    cnt = valid.sum(1)
    mean = vals.sum(1) / np.maximum(cnt, 1)
    masked = np.where(valid, vals, np.nan)
    with np.errstate(all="ignore"):
        med = np.nanmedian(np.where(cnt[:, None] > 0, masked, 0.0), axis=1)
    spread = np.where(valid, np.abs(vals - mean[:, None]), 0.0).sum(1) / np.maximum(cnt, 1)
    none = cnt == 0
    mean_i = np.where(none, fallback, np.rint(mean)).astype(np.int64)
    med_i = np.where(none, fallback, np.rint(med)).astype(np.int64)
    return {"mean": mean_i, "median": med_i, "mean_f": np.where(none, fallback, mean), "spread": spread}


# -- the attribute columns ------------------------------------------------------------------------


def own_features(codes: np.ndarray, k: int, mid_q: int) -> tuple[list[np.ndarray], np.ndarray | None]:
    """What a Gaussian's own earlier-coded columns (coding order: log-scales, rotation, a, w) offer
    column ``k``: (linear features, one scalar to bucket as context)."""
    s = codes[:, 3:6].astype(np.float64)
    q = np.abs(codes[:, 7:10] - mid_q).astype(np.float64)
    table = {
        4: ([s[:, 0]], s[:, 0]),
        5: ([s[:, 0], s[:, 1]], (s[:, 0] + s[:, 1]) / 2),
        7: ([], s.max(1) - s.min(1)),  # the first component given the anisotropy
        8: ([], q[:, 0]),
        9: ([], q[:, 0] + q[:, 1]),  # the truncated cube: the rest bounds the last
        10: ([s[:, 0], s[:, 1], s[:, 2]], s.mean(1)),
        11: ([codes[:, 10].astype(np.float64), s.mean(1)], codes[:, 10].astype(np.float64)),
    }
    return table.get(k, ([], None))


def column_candidates(codes: np.ndarray, k: int, nbrs: dict, lifted: np.ndarray, mid_q: int) -> dict:
    """Every candidate coding of attribute column ``k``: name -> (symbols, context or None)."""
    c = codes[:, k]
    off = int(c.min())
    cand: dict[str, tuple] = {"value": (c, None), "previous": (np.diff(c, prepend=c[:1]), None), "lift": (lifted, None)}
    stats = {kn: neighbour_stats(c, *nbrs[kn], off) for kn in KS}
    for kn in KS:
        cand[f"knn{kn}_median"] = (c - stats[kn]["median"], None)
        cand[f"knn{kn}_mean"] = (c - stats[kn]["mean"], None)
    s8 = stats[8]
    cand["value|nbr8"] = (c, buckets(s8["mean_f"], 8))
    spread = buckets(s8["spread"], 6)
    cand["knn8_mean|spread"] = (c - s8["mean"], spread)
    feats, own = own_features(codes, k, mid_q)
    x = np.stack([np.ones(len(c)), s8["mean_f"], *feats], 1)
    coef, *_ = np.linalg.lstsq(x, c.astype(np.float64), rcond=None)
    joint = c - np.rint(x @ coef).astype(np.int64)
    cand["joint"] = (joint, None)
    cand["joint|spread"] = (joint, spread)
    if own is not None:
        ob = buckets(own, 8)
        cand["value|own"] = (c, ob)
        cand["value|nbr8,own"] = (c, buckets(s8["mean_f"], 4) * 4 + buckets(own, 4))
        cand["knn8_mean|own"] = (c - s8["mean"], ob)
    return cand


def attribute_rows(codes: np.ndarray, mask: int, b: dict) -> dict:
    """Per attribute column: layout 2's stored form's entropy and every candidate's figures."""
    n = len(codes)
    pts = codes[:, 0:3].astype(np.float64)
    idx, valid = causal_knn(pts, max(KS))  # nearest first: the k nearest are the first k columns
    nbrs = {kn: (idx[:, :kn], valid[:, :kn]) for kn in KS}
    lifted = coded_keys.lift(np.ascontiguousarray(codes[:, 3:12].T)) if n > 2 else codes[:, 3:12].T.copy()
    mid_q = coded._q_levels(b["q"]) // 2
    out = {}
    for k in ATTRS:
        stored = lifted[k - 3] if mask >> k & 1 else codes[:, k]
        col = {"stored": "lift" if mask >> k & 1 else "value", "stored_entropy": entropy_bits(stored) / n}
        if np.all(codes[:, k] == codes[0, k]):  # a constant column (the rotation index): nothing stored
            col.update(best_entropy=("value", 0.0), best_adaptive=("value", 0.0), candidates={})
            out[CODED_COLUMNS[k]] = col
            continue
        figures = {}
        for name, (sym, ctx) in column_candidates(codes, k, nbrs, lifted[k - 3], mid_q).items():
            figures[name] = {key: v / n for key, v in code_lengths(sym, ctx).items()}
        col["candidates"] = figures
        col["best_entropy"] = min(((nm, f["entropy"]) for nm, f in figures.items()), key=lambda t: t[1])
        col["best_adaptive"] = min(((nm, f["adaptive"]) for nm, f in figures.items()), key=lambda t: t[1])
        out[CODED_COLUMNS[k]] = col
    return out


# -- the centres ----------------------------------------------------------------------------------


def octree_bits(keys: np.ndarray, axis_bits: int) -> dict:
    """Occupancy-octree code of the sorted Morton keys (duplicates: a count each): every child
    bit of every occupied node, level by level, coded adaptively given (level, the parent's
    occupied face neighbours at its level 0-6, the child's index, siblings already occupied)."""
    uk, mult = np.unique(keys, return_counts=True)
    syms, ctxs = [], []
    for level in range(axis_bits):
        shift = np.uint64(3 * (axis_bits - level))
        parents = np.unique(uk >> shift)  # nodes at this level, each gets 8 child bits
        children = np.unique(uk >> (shift - np.uint64(3)))
        occ = np.zeros((len(parents), 8), np.int64)
        occ[np.searchsorted(parents, children >> np.uint64(3)), (children & np.uint64(7)).astype(np.int64)] = 1
        xyz = [coded_keys._compact1by2(parents >> np.uint64(a)).astype(np.int64) for a in range(3)]
        nb = np.zeros(len(parents), np.int64)
        for a in range(3):
            for step in (-1, 1):
                moved = [xyz[j] + (step if j == a else 0) for j in range(3)]
                inside = moved[a] >= 0
                m = [np.maximum(v, 0) for v in moved]
                key = (
                    coded_keys._part1by2(m[0]) | (coded_keys._part1by2(m[1]) << np.uint64(1)) | (coded_keys._part1by2(m[2]) << np.uint64(2))
                )
                pos = np.minimum(np.searchsorted(parents, key), len(parents) - 1)
                nb += inside & (parents[pos] == key)
        before = np.cumsum(occ, 1) - occ  # siblings occupied before each child
        ctx = ((min(level, 15) * 7 + nb[:, None]) * 8 + np.arange(8)[None, :]) * 8 + np.minimum(before, 7)
        syms.append(occ.reshape(-1))
        ctxs.append(ctx.reshape(-1))
    sym, ctx = np.concatenate(syms), np.concatenate(ctxs)
    dup = mult - 1
    return {
        "entropy": entropy_bits(sym, ctx) + entropy_bits(dup),
        "adaptive": adaptive_bits(sym, ctx) + min(adaptive_bits(dup), binned_bits(dup)),
    }


def density_bound(mu: np.ndarray, k: int = 4) -> float:
    """Bits a centre for a set of N cells drawn independently from the points' own density (known
    to the coder): the Kozachenko-Leonenko estimate of its differential entropy in code cells
    (k-th nearest distances; each centre moved uniformly within its cell, a fixed seed) less
    log2(N!) / N. What density contexts could reach at best; the points' regularity (they keep
    apart) is not counted."""
    from scipy.special import digamma

    n = len(mu)
    if n <= k + 1:
        return math.nan
    x = mu.astype(np.float64) + np.random.default_rng(0).uniform(-0.5, 0.5, mu.shape)
    eps = cKDTree(x).query(x, k=k + 1)[0][:, k]
    h = digamma(n) - digamma(k) + math.log(4.0 / 3.0 * math.pi) + 3.0 * float(np.mean(np.log(eps)))
    return (h - math.lgamma(n + 1) / n) / math.log(2)


def centre_rows(codes: np.ndarray) -> dict:
    """The centres as layout 2 stores them (gap symbols + raw bits) and with context."""
    n = len(codes)
    mu = codes[:, 0:3]
    keys = coded_keys.centre_keys(mu)
    sym_b, _, nbits = coded_keys.gap_streams(keys)
    sym = np.frombuffer(sym_b, np.uint8).astype(np.int64)
    prev = np.r_[0, sym[:-1]]
    m = mu - mu.min(0)
    cells = float(np.prod(m.max(0) + 1))
    bound = (math.lgamma(cells + 1) - math.lgamma(n + 1) - math.lgamma(cells - n + 1)) / math.log(2)
    axis_bits = max(1, int(m.max()).bit_length())
    cand = {
        "gaps": {"entropy": entropy_bits(sym) + nbits, "adaptive": adaptive_bits(sym) + nbits},
        "gaps|previous": {"entropy": entropy_bits(sym, prev) + nbits, "adaptive": adaptive_bits(sym, prev) + nbits},
        "octree": octree_bits(keys, axis_bits),
    }
    out = {"stored_entropy": cand["gaps"]["entropy"] / n, "raw_bits": nbits / n, "set_bound": bound / n, "density_bound": density_bound(mu)}
    out["candidates"] = {nm: {k: v / n for k, v in f.items()} for nm, f in cand.items()}
    out["best_entropy"] = min(((nm, f["entropy"] / n) for nm, f in cand.items()), key=lambda t: t[1])
    out["best_adaptive"] = min(((nm, f["adaptive"] / n) for nm, f in cand.items()), key=lambda t: t[1])
    return out


# -- one model ------------------------------------------------------------------------------------


def load(path: Path) -> tuple[np.ndarray, dict, dict]:
    """(params, bits, the .wgs file's figures) of a model's ``.npz`` and the ``.wgs`` beside it."""
    with np.load(path) as d:
        params = np.asarray(d["params"], np.float32)
        bits = {k[5:]: int(d[k]) for k in d.files if k.startswith("bits_")}
    wgs = path.with_suffix(".wgs")
    filed: dict = {}
    if wgs.exists():
        wparams, header = read_wgs(wgs)
        filed = {"file_bytes": wgs.stat().st_size, "payload_bytes": int(header["payload"]["payload_bytes"])}
        filed["layout"] = coded.coded_layout(header["payload"]["quant"])
        filed["same_codes"] = bool(np.array_equal(coded.quantise(wparams, bits), _stored(params, bits)))
        zstd = coded.zstandard_module()
        filed["header_json_zstd_bytes"] = len(zstd.ZstdCompressor(level=19).compress(json.dumps(header, separators=(",", ":")).encode()))
    return params, bits, filed


def _stored(params: np.ndarray, bits: dict) -> np.ndarray:
    """The codes in storage order, from the coder's own functions."""
    codes = coded.quantise(params, bits)
    return codes[coded.coded_order(codes)]


def analyse(path: Path) -> dict:
    t0 = time.perf_counter()
    params, bits, filed = load(path)
    n = len(params)
    b = coded.check_bits(bits)
    codes = _stored(params, b)
    payload, quant, _ = coded.encode_coded(params, b)
    keys = coded_keys.centre_keys(codes[:, 0:3])
    if keys is None:
        raise SystemExit(f"{path}: a centre axis spans 2^{coded_keys.KEY_AXIS_BITS} codes or more (layout 1 only); not measured here")
    blocks, _ = coded_keys.encode_keys(codes, keys, b)
    mask = int.from_bytes(blocks[0][:2], "little")
    row: dict = {"model": path.stem, "n": n, "bits": b, **filed}
    if filed:
        row["file_bpg"] = filed["file_bytes"] / n
        row["header_bpg"] = (filed["file_bytes"] - filed["payload_bytes"]) / n
        row["payload_written_bpg"] = filed["payload_bytes"] / n
    row["payload_layout2_bpg"] = len(payload) / n
    row["layout2_written_now"] = coded.coded_layout(quant) == coded_keys.LAYOUT
    row["blocks_order0_bpg"] = sum(coded_keys._plane_bits([blk]) for blk in blocks) / 8 / n
    row["centres"] = centre_rows(codes)
    row["columns"] = attribute_rows(codes, mask, b)
    cols = [row["centres"], *row["columns"].values()]
    row["order0_bpg"] = sum(c["stored_entropy"] for c in cols) / 8
    row["best_entropy_bpg"] = sum(c["best_entropy"][1] for c in cols) / 8
    row["estimate_entropy_bpg"] = row["best_entropy_bpg"] * (1 + OVERHEAD)
    row["estimate_entropy_range_bpg"] = [row["best_entropy_bpg"] * 1.03, row["best_entropy_bpg"] * 1.05]
    row["estimate_adaptive_bpg"] = sum(c["best_adaptive"][1] for c in cols) / 8
    row["saving_adaptive_bpg"] = row["payload_layout2_bpg"] - row["estimate_adaptive_bpg"]
    row["saving_entropy_bpg"] = row["payload_layout2_bpg"] - row["estimate_entropy_bpg"]
    groups = {}
    for g, ks in GROUP_NAMES.items():
        parts = [row["centres"]] if g == "mu" else [row["columns"][CODED_COLUMNS[k]] for k in ks]
        groups[g] = {
            key: sum(p[key] if key == "stored_entropy" else p[key][1] for p in parts)
            for key in ("stored_entropy", "best_entropy", "best_adaptive")
        }
    row["group_bits"] = groups
    s = codes[:, 3:6]
    two = (s[:, 0] == s[:, 1]) | (s[:, 1] == s[:, 2]) | (s[:, 0] == s[:, 2])
    # a Gaussian with two equal log-scale codes is the same under any turn about the third axis:
    # one of its three rotation components is free (a re-canonicalisation, not a context model)
    row["two_equal_scales_share"] = float(two.mean())
    row["free_rotation_bits"] = float(two.mean()) * groups["q"]["stored_entropy"] / 3
    row["seconds"] = time.perf_counter() - t0
    return row


# -- report ---------------------------------------------------------------------------------------

SHORT = {"log_sx": "sx", "log_sy": "sy", "log_sz": "sz", "q_0": "q0", "q_1": "q1", "q_2": "q2", "a": "a", "w": "w"}


def winners(r: dict, key: str) -> str:
    parts = [f"mu:{r['centres'][key][0]}"]
    for name, col in r["columns"].items():
        if name in SHORT:
            parts.append(f"{SHORT[name]}:{col[key][0]}")
    return " ".join(parts)


def table(rows: list[dict]) -> str:
    head = "| model | N | file B/G | header B/G | written payload | layout 2 now | order-0 of layout 2 | best H + 4 % | best adaptive | header + adaptive |"
    lines = [head, "|" + "---|" * 10]
    for r in rows:
        lines.append(
            f"| {r['model']} | {r['n']:,} | {r.get('file_bpg', math.nan):.2f} | {r.get('header_bpg', math.nan):.2f} | "
            f"{r.get('payload_written_bpg', math.nan):.2f} | {r['payload_layout2_bpg']:.2f} | {r['order0_bpg']:.2f} | "
            f"{r['estimate_entropy_bpg']:.2f} | {r['estimate_adaptive_bpg']:.2f} | {r.get('header_bpg', 0.0) + r['estimate_adaptive_bpg']:.2f} |"
        )
    lines += [
        "",
        "| model | bits a Gaussian: now (order-0 stored) / best entropy / best adaptive, by group | winners (adaptive) |",
        "|---|---|---|",
    ]
    for r in rows:
        g = "  ".join(f"{k} {v['stored_entropy']:.1f}/{v['best_entropy']:.1f}/{v['best_adaptive']:.1f}" for k, v in r["group_bits"].items())
        lines.append(f"| {r['model']} | {g} | {winners(r, 'best_adaptive')} |")
    return "\n".join(lines)


SUMMARY_KEYS = (
    "file_bpg",
    "header_bpg",
    "payload_written_bpg",
    "payload_layout2_bpg",
    "blocks_order0_bpg",
    "order0_bpg",
    "estimate_entropy_bpg",
    "estimate_adaptive_bpg",
    "saving_entropy_bpg",
    "saving_adaptive_bpg",
    "free_rotation_bits",
)


def summarise(rows: list[dict]) -> dict:
    out: dict = {}
    mri = [r for r in rows if r["model"].rsplit("_cr", 1)[0] in MRI]
    for name, group in (("mri", mri), ("all", rows)):
        if not group:
            continue
        s = {k: statistics.median(r[k] for r in group) for k in SUMMARY_KEYS if all(k in r for r in group)}
        if all("header_bpg" in r for r in group):
            s["file_estimate_adaptive_bpg"] = statistics.median(r["header_bpg"] + r["estimate_adaptive_bpg"] for r in group)
            s["file_estimate_entropy_bpg"] = statistics.median(r["header_bpg"] + r["estimate_entropy_bpg"] for r in group)
        s["group_bits"] = {
            g: {
                key: statistics.median(r["group_bits"][g][key] for r in group)
                for key in ("stored_entropy", "best_entropy", "best_adaptive")
            }
            for g in GROUP_NAMES
        }
        tally: dict = {}
        for r in group:
            for col, v in [("mu", r["centres"]), *r["columns"].items()]:
                tally.setdefault(col, {}).setdefault(v["best_adaptive"][0], 0)
                tally[col][v["best_adaptive"][0]] += 1
        s["adaptive_winners"] = tally
        s["models"] = len(group)
        out[name] = s
    return out


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("models", nargs="+", type=Path, help="refined models as .npz (params, bits_*), the .wgs beside each")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    rows = []
    for path in sorted(args.models):
        rows.append(analyse(path))
        r = rows[-1]
        print(
            f"{r['model']}: {r['payload_layout2_bpg']:.2f} -> {r['estimate_adaptive_bpg']:.2f} B/G ({r['seconds']:.1f} s)", file=sys.stderr
        )
    out = {
        **result_header("context coder bound of coded models", __file__, argv, "cpu"),
        "overhead": OVERHEAD,
        "summary": summarise(rows),
        "rows": rows,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(out, indent=1) + "\n")
    print(table(rows))
    print(
        json.dumps(
            {k: {kk: vv for kk, vv in v.items() if kk not in ("group_bits", "adaptive_winners")} for k, v in out["summary"].items()},
            indent=1,
        )
    )
    return out


if __name__ == "__main__":
    main()
