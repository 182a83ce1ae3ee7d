"""Bytes a Gaussian of the coded payload, layout 1 against layout 2, and what context could still
buy (issue #53 part 1), on refined models saved as ``.npz`` (arrays only: ``params`` (N, 12)
float32 as the encoder had them before coding, ``bits_mu``, ``bits_log_s``, ``bits_q``, ``bits_a``,
``bits_w``: the depths the rate control chose).

For each model: the payload of each layout (bytes a Gaussian, the best of a few codings' time,
decoding time); the order-0 entropy of every column as layout 1 stores it; how well
already-decoded neighbours predict each attribute: the residual's order-0 entropy after
predicting from the previous Gaussian in coding order and from the mean of the 4 nearest (by
centre) among the 16 before it, and the adaptive code length (a count-based model per context,
learning cost included) of the values alone and conditioned on that 4-neighbour mean in 8
quantile buckets; the centres: layout 1's per-axis deltas, the set bound log2 C(V, N) / N for N
centres among the V cells of their box, and the adaptive length of Morton and Hilbert key gaps
(bit-length symbol adaptive, the bits below raw).

    python benchmarks/accuracy/coded_context.py MODEL.npz [MODEL.npz ...] --out OUT.json
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

from warpgauss.encoding.bench import result_header
from warpgauss.format import coded, coded_keys

ATTRS = {"log_s": [3, 4, 5], "q": [7, 8, 9], "a": [10], "w": [11]}
MRI = ("inia19", "mean_reg2mean", "mni_icbm152")


def entropy_bits(x: np.ndarray) -> float:
    """Order-0 entropy, total bits, of integer values."""
    if len(x) == 0:
        return 0.0
    _, counts = np.unique(np.asarray(x, np.int64), return_counts=True)
    p = counts / counts.sum()
    return float(-(counts * np.log2(p)).sum())


def seen_before(key: np.ndarray) -> np.ndarray:
    """For each position, how often its key occurred earlier in the sequence."""
    n = len(key)
    if n and int(key.min()) >= 0 and int(key.max()) < 1 << 16:
        key = key.astype(np.uint16)  # a stable sort of 16-bit keys is a radix sort
    order = np.argsort(key, kind="stable")
    ks = key[order]
    start = np.r_[0, np.flatnonzero(ks[1:] != ks[:-1]) + 1]
    first = np.repeat(start, np.diff(np.r_[start, n]))
    out = np.empty(n, np.int64)
    out[order] = np.arange(n) - first
    return out


def adaptive_bits(sym: np.ndarray, ctx: np.ndarray | None = None, alpha: float = 0.5) -> float:
    """Total code length (bits) of ``sym`` under an adaptive count model per context (each symbol
    coded with (count so far + alpha) / (context count so far + alpha K), K the alphabet seen: the
    symbols the column takes, the alphabet a header would declare)."""
    sym = np.asarray(sym, np.int64)
    n = len(sym)
    if n == 0:
        return 0.0
    s = np.unique(sym, return_inverse=True)[1].reshape(-1)
    k = int(s.max()) + 1
    if k == 1:
        return 0.0
    c = np.zeros(n, np.int64) if ctx is None else np.unique(np.asarray(ctx, np.int64), return_inverse=True)[1].reshape(-1)
    return float(np.sum(np.log2((seen_before(c) + alpha * k) / (seen_before(c * k + s) + alpha))))


def hilbert_keys(m: np.ndarray, b: int) -> np.ndarray:
    """Hilbert keys (uint64) of non-negative (n, 3) integer coordinates below 2^b (Skilling)."""
    x = [m[:, i].astype(np.int64).copy() for i in range(3)]
    q = 1 << (b - 1)
    while q > 1:
        p = q - 1
        for i in range(3):
            hit = (x[i] & q) != 0
            t = (x[0] ^ x[i]) & p
            x0 = np.where(hit, x[0] ^ p, x[0] ^ t)
            if i:
                x[i] = np.where(hit, x[i], x[i] ^ t)
            x[0] = x0
        q >>= 1
    for i in (1, 2):
        x[i] ^= x[i - 1]
    t = np.zeros_like(x[0])
    q = 1 << (b - 1)
    while q > 1:
        t ^= np.where((x[2] & q) != 0, q - 1, 0)
        q >>= 1
    key = np.zeros(len(m), np.uint64)
    for bit in range(b - 1, -1, -1):
        for i in range(3):
            key = (key << np.uint64(1)) | (((x[i] ^ t) >> bit) & 1).astype(np.uint64)
    return key


def gap_bits(keys: np.ndarray) -> float:
    """Adaptive length of ascending key gaps: bit length adaptive, the bits below it raw."""
    gap = np.diff(np.sort(keys), prepend=np.uint64(0))
    e = coded_keys._bit_length(gap)
    return adaptive_bits(e) + float(np.maximum(e - 1, 0).sum())


def best_ms(fn, reps: int) -> tuple[float, object]:
    best, out = math.inf, None
    for _ in range(reps):
        t = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t)
    return best * 1e3, out


def analyse(path: Path, reps: int) -> dict:
    with np.load(path) as d:
        params = np.asarray(d["params"], np.float32)
        bits = {k[5:]: int(d[k]) for k in d.files if k.startswith("bits_")}
    n = len(params)
    row: dict = {"model": path.stem, "n": n, "bits": bits}
    for layout in (1, 2):
        ms, (payload, quant, _) = best_ms(lambda layout=layout: coded.encode_coded(params, bits, layout=layout), reps)
        dec_ms, decoded = best_ms(lambda p=payload, q=quant: coded.decode_coded(p, n, q), reps)
        row[f"layout{layout}"] = {"bytes": len(payload), "bytes_per_gaussian": len(payload) / n, "encode_ms": ms, "decode_ms": dec_ms}
        row.setdefault("_decoded", []).append(decoded)
    a, b = row.pop("_decoded")
    row["lossless_same_model"] = bool(np.array_equal(a, b))
    row["change_percent"] = 100.0 * (row["layout2"]["bytes"] / row["layout1"]["bytes"] - 1.0)

    codes = coded.quantise(params, bits)
    codes = codes[coded.coded_order(codes)]
    mu = codes[:, 0:3]
    d = np.diff(mu, axis=0, prepend=mu[:1])
    zz = (d << 1) ^ (d >> 63)
    order0 = {"mu_delta": sum(entropy_bits(zz[:, k]) for k in range(3)) / n}
    for name, cols in ATTRS.items():
        order0[name] = sum(entropy_bits(codes[:, k]) for k in cols) / n
    order0["q_index"] = entropy_bits(codes[:, 6]) / n
    row["order0_bits"] = order0
    row["order0_bytes_per_gaussian"] = sum(order0.values()) / 8

    # neighbours: the 4 nearest by centre among the 16 before each Gaussian in coding order
    win = 16
    idx = np.arange(n)[:, None] - np.arange(1, win + 1)[None, :]
    valid = idx >= 0
    idx = np.maximum(idx, 0)
    dist = ((mu[idx] - mu[:, None, :]).astype(np.float64) ** 2).sum(2)
    dist[~valid] = np.inf
    near = np.take_along_axis(idx, np.argsort(dist, axis=1, kind="stable")[:, :4], 1)
    has = np.isfinite(np.sort(dist, axis=1)[:, :4])
    predict = {}
    for name, cols in ATTRS.items():
        plain = prev = knn = adapt = ctx = 0.0
        for k in cols:
            c = codes[:, k]
            vals = np.where(has, c[near], 0).astype(np.float64)
            mean = np.where(has.any(1), np.rint(vals.sum(1) / np.maximum(has.sum(1), 1)), c.mean()).astype(np.int64)
            plain += entropy_bits(c)
            prev += entropy_bits(np.diff(c, prepend=c[:1]))
            knn += entropy_bits(c - mean)
            adapt += adaptive_bits(c)
            edges = np.unique(np.quantile(mean, np.linspace(0, 1, 9)[1:-1]))
            ctx += adaptive_bits(c, np.searchsorted(edges, mean))
        predict[name] = {
            "order0": plain / n,
            "previous_residual": prev / n,
            "knn4_residual": knn / n,
            "adaptive": adapt / n,
            "adaptive_knn4_context": ctx / n,
        }
    row["prediction_bits"] = predict

    m = mu - mu.min(0)
    ext = (m.max(0) + 1).astype(np.float64)
    cells = float(np.prod(ext))
    bound = (math.lgamma(cells + 1) - math.lgamma(n + 1) - math.lgamma(cells - n + 1)) / math.log(2) if n else 0.0
    axis_bits = max(1, int(m.max()).bit_length())
    morton = coded_keys.centre_keys(mu)
    row["centre_bits"] = {
        "layout1_deltas_order0": order0["mu_delta"],
        "set_bound": bound / n,
        "morton_gaps_adaptive": gap_bits(morton) / n if morton is not None else None,
        "hilbert_gaps_adaptive": gap_bits(hilbert_keys(m, axis_bits)) / n,
    }
    return row


def _table(rows: list[dict]) -> str:
    head = "| model | N | layout 1 B/G | layout 2 B/G | change | order-0 B/G | centres l1 / sorted set / Morton / Hilbert (bits) | encode ms l1 / l2 | decode ms l1 / l2 |"
    lines = [head, "|" + "---|" * 9]
    for r in rows:
        c = r["centre_bits"]
        lines.append(
            f"| {r['model']} | {r['n']:,} | {r['layout1']['bytes_per_gaussian']:.3f} | {r['layout2']['bytes_per_gaussian']:.3f} | "
            f"{r['change_percent']:+.1f} % | {r['order0_bytes_per_gaussian']:.3f} | {c['layout1_deltas_order0']:.2f} / {c['set_bound']:.2f} / "
            f"{c['morton_gaps_adaptive']:.2f} / {c['hilbert_gaps_adaptive']:.2f} | {r['layout1']['encode_ms']:.1f} / "
            f"{r['layout2']['encode_ms']:.1f} | {r['layout1']['decode_ms']:.1f} / {r['layout2']['decode_ms']:.1f} |"
        )
    return "\n".join(lines)


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("models", nargs="+", type=Path)
    ap.add_argument("--reps", type=int, default=3, help="codings timed per model and layout (the best kept)")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    rows = []
    for path in sorted(args.models):
        rows.append(analyse(path, args.reps))
        print(
            f"{path.stem}: {rows[-1]['layout1']['bytes_per_gaussian']:.3f} -> {rows[-1]['layout2']['bytes_per_gaussian']:.3f} B/G",
            file=sys.stderr,
        )
    mri = [r for r in rows if r["model"].rsplit("_cr", 1)[0] in MRI]
    summary = {}
    for layout in (1, 2):
        for name, group in (("mri", mri), ("all", rows)):
            if group:
                summary[f"median_{name}_layout{layout}_bytes_per_gaussian"] = statistics.median(
                    r[f"layout{layout}"]["bytes_per_gaussian"] for r in group
                )
    out = {**result_header("coded payload: layouts and context", __file__, argv, "cpu"), "summary": summary, "rows": rows}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(out, indent=1) + "\n")
    print(_table(rows))
    print(json.dumps(summary, indent=1))
    return out


if __name__ == "__main__":
    main()
