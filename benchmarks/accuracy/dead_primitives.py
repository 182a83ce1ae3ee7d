"""How many primitives of refined models carry (almost) nothing: candidates for relocation at
fixed N (issue #53 part 2).

For each model file: the share of primitives whose weight is below 0.01 / 0.05 / 0.1, and whose
contribution w x sigma_x sigma_y sigma_z is below 1 % / 10 % of the model's median. The models are
default encodes (one H200, `warpgauss encode VOLUME --ratio R`) of the three head MRIs of
../shared/data at CR 10-1000 and the vortex and interface fields at 256^3, CR 30-300.

    python benchmarks/accuracy/dead_primitives.py /work/models/*.wgs --out results/accuracy/dead_primitives.json
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

import warpgauss
from warpgauss.encoding.bench import result_header


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("models", nargs="+")
    ap.add_argument("--out", required=True)
    args = ap.parse_args(argv)
    res = {**result_header("primitives that carry almost nothing", __file__, argv, "cpu"), "rows": []}
    print("| model | N | w < 0.01 | w < 0.05 | w < 0.1 | contribution < 1 % of median | < 10 % |")
    print("|---|---|---|---|---|---|---|")
    for path in args.models:
        p = warpgauss.Model.load(path).params.astype(np.float64)
        w = p[:, 11]
        c = w * np.exp(p[:, 3:6].sum(1))
        med = float(np.median(c))
        row = {
            "model": Path(path).name,
            "n": int(len(p)),
            "w_below": {str(t): float((w < t).mean()) for t in (0.01, 0.05, 0.1)},
            "contribution_below_median_share": {str(t): float((c < t * med).mean()) for t in (0.01, 0.1)},
        }
        res["rows"].append(row)
        wb, cb = row["w_below"], row["contribution_below_median_share"]
        print(
            f"| {row['model']} | {row['n']:,} | {wb['0.01']:.4f} | {wb['0.05']:.4f} | {wb['0.1']:.4f} | {cb['0.01']:.4f} | {cb['0.1']:.4f} |"
        )
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(res, indent=1))
    return res


if __name__ == "__main__":
    main()
