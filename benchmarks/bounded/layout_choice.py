"""Does bzip2 on Zstandard's best two layouts find the smallest frame the full search finds?

For each head MRI of ../shared/data (the .npy volumes benchmarks/README.md makes), bounds 1e-2 and
1e-3 of the range, linear and cubic interpolation (no Gaussians): the residual's q's coded by
``warpgauss.format.residual_coding.final_symbols`` (six layouts with Zstandard, bzip2 on the best
BZIP2_LAYOUTS) against all twelve (layout, codec) codings. Prints a table, writes JSON.

    python benchmarks/bounded/layout_choice.py --volume-dir benchmarks/build/vol --out results/bounded/layout_choice_cpu.json
"""

from __future__ import annotations

import argparse
import bz2
import json
import time
from pathlib import Path

import numpy as np

from warpgauss.encoding.bench import result_header
from warpgauss.format import interpolation as I
from warpgauss.format import planes as P
from warpgauss.format import residual as R
from warpgauss.format.residual_coding import final_symbols


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--volume-dir", default="benchmarks/build/vol")
    ap.add_argument("--volumes", default="mean_reg2mean,mni_icbm152,inia19")
    ap.add_argument("--out", required=True)
    args = ap.parse_args(argv)
    res = {**result_header("bzip2 layouts of the bounded residual", __file__, argv, "cpu"), "rows": []}
    print("| volume | bound | interpolation | all twelve: bytes, layout, codec | chosen | chosen s |")
    print("|---|---|---|---|---|---|")
    for name in args.volumes.split(","):
        src = np.load(Path(args.volume_dir) / f"{name}.npy")
        lo, hi = float(src.min()), float(src.max())
        for rel in (1e-2, 1e-3):
            step, integer, _ = I.quantiser(rel * (hi - lo), R.MARGIN_REL * (hi - lo), src.dtype)
            t = src.astype(np.int64) if integer else src.astype(np.float64)
            for kind in ("linear", "cubic"):
                q, _ = I.feedback(t, np.zeros(src.shape, bool), step, integer, kind, I.AXES, I.FLAT, "cpu")
                u = P.zigzag(q.ravel())
                w = P.byte_width(u)
                u = u.astype(f"<u{w}").reshape(q.shape)
                full = []
                for layout in R.ORDERS:
                    raw = P.byte_planes(np.ascontiguousarray(u.transpose([int(c) for c in layout])).ravel(), w)
                    full += [(len(P.compress(raw)), layout, "zstd"), (len(bz2.compress(raw, 9)), layout, "bzip2")]
                best = min(full)
                t0 = time.perf_counter()
                frame, codec, layout = final_symbols(u)
                dt = time.perf_counter() - t0
                row = {
                    "volume": name,
                    "bound_rel": rel,
                    "interp": kind,
                    "all": list(best),
                    "chosen": [len(frame), layout, codec],
                    "chosen_s": dt,
                }
                res["rows"].append(row)
                print(f"| {name} | {rel:g} | {kind} | {best[0]:,} {best[1]} {best[2]} | {len(frame):,} {layout} {codec} | {dt:.2f} |")
    res["same_everywhere"] = all(r["all"][0] == r["chosen"][0] for r in res["rows"])
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(res, indent=1))
    return res


if __name__ == "__main__":
    main()
