"""How well already-coded neighbours predict a coded model's attributes (issue #53 part 1, a first
measurement): for each column group of a coded ``.wgs``, the order-0 entropy of what the coder
stores today (centres as deltas along the Morton order, the rest as values), and of the residual
after predicting each value from the previous Gaussian in Morton order and from the median of the
previous four; the log-scales predicted from the spacing of the three nearest centres (an affine
fit of log distance, two numbers a file would store) and the value and weight from the nearest
centre's; plus the bytes a Gaussian takes in the file and a sorted set's bound for the centres.

    python benchmarks/accuracy/context_entropy.py MODEL.wgs [MODEL.wgs ...] --out OUT.json
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np

from warpgauss.encoding.bench import result_header
from warpgauss.format import coded
from warpgauss.format.wgs import read_wgs

GROUPS = {"mu": [0, 1, 2], "log_s": [3, 4, 5], "q": [6, 7, 8, 9], "a": [10], "w": [11]}


def entropy_bits(x: np.ndarray) -> float:
    """Order-0 entropy (bits a value) of integer values."""
    _, counts = np.unique(np.asarray(x, np.int64), return_counts=True)
    p = counts / counts.sum()
    return float(-(p * np.log2(p)).sum())


def previous(c: np.ndarray) -> np.ndarray:
    """Each value less the previous one in storage order (the first less itself)."""
    return np.diff(c, prepend=c[:1])


def median_of_four(c: np.ndarray) -> np.ndarray:
    """Each value less the median of up to four before it in storage order."""
    n = len(c)
    pad = np.concatenate([np.repeat(c[:1], 4), c])
    window = np.stack([pad[4 - k : 4 - k + n] for k in range(1, 5)], axis=1)
    return c - np.rint(np.median(window, axis=1)).astype(np.int64)


def analyse(path: Path) -> dict:
    params, header = read_wgs(path)
    n = len(params)
    bits = header["payload"]["quant"]["bits"]
    codes = coded.quantise(params, bits)  # the file's order already (Morton)
    row: dict = {"model": path.name, "n": n, "bits": bits, "bytes_per_gaussian": header["payload"]["payload_bytes"] / n, "groups": {}}
    total_now = total_prev = total_med = 0.0
    for name, cols in GROUPS.items():
        now = prev = med = 0.0
        for k in cols:
            c = codes[:, k]
            stored = previous(c) if name == "mu" else c
            now += entropy_bits(stored)
            prev += entropy_bits(previous(c))
            med += entropy_bits(median_of_four(c))
        row["groups"][name] = {"stored_bits": now, "previous_bits": prev, "median4_bits": med, "best_bits": min(now, prev, med)}
        total_now += now
        total_prev += min(now, prev)
        total_med += min(now, prev, med)
    from scipy.spatial import cKDTree

    mu = params[:, :3].astype(np.float64)
    dist, near = cKDTree(mu).query(mu, k=4)
    spacing = np.stack([np.ones(n), np.log(np.maximum(dist[:, 1:].mean(1), 1e-6))], axis=1)
    spaced = 0.0
    for k in GROUPS["log_s"]:
        coef, *_ = np.linalg.lstsq(spacing, codes[:, k].astype(np.float64), rcond=None)
        spaced += entropy_bits(codes[:, k] - np.rint(spacing @ coef).astype(np.int64))
    row["groups"]["log_s"]["spacing_bits"] = spaced
    for name in ("a", "w"):
        k = GROUPS[name][0]
        row["groups"][name]["nearest_bits"] = entropy_bits(codes[:, k] - codes[near[:, 1], k])
    cells = float(np.prod(header["grid"]["shape_xyz"])) * 8.0 ** bits["mu"]
    row["centre_set_bound_bits"] = math.log2(math.e * cells / n) if cells > n else 0.0
    row["order0_stored_bytes"] = total_now / 8
    row["order0_best_of_previous_bytes"] = total_prev / 8
    row["order0_best_of_all_bytes"] = total_med / 8
    return row


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("models", nargs="+", type=Path)
    ap.add_argument("--out", required=True)
    args = ap.parse_args(argv)
    res = {**result_header("context entropy of coded models", __file__, argv, "cpu"), "rows": [analyse(p) for p in args.models]}
    for r in res["rows"]:
        print(
            f"{r['model']}: N {r['n']}, file {r['bytes_per_gaussian']:.2f} B a Gaussian; order-0 stored {r['order0_stored_bytes']:.2f} B, "
            f"best with the previous {r['order0_best_of_previous_bytes']:.2f}, with the median of four {r['order0_best_of_all_bytes']:.2f}; "
            f"centres {r['groups']['mu']['stored_bits']:.1f} bits stored, set bound {r['centre_set_bound_bits']:.1f}"
        )
        for g, v in r["groups"].items():
            more = "".join(f"  {k.replace('_bits', '')} {x:6.2f}" for k, x in v.items() if k in ("spacing_bits", "nearest_bits"))
            print(
                f"   {g:6s} stored {v['stored_bits']:6.2f}  previous {v['previous_bits']:6.2f}  median4 {v['median4_bits']:6.2f}{more} bits"
            )
    Path(args.out).write_text(json.dumps(res, indent=1) + "\n")
    return res


if __name__ == "__main__":
    main()
