"""The re-plan's cut by each order (issue #53): a coded encode with ``replan.CUT_ORDER`` "weight"
(least weight x sigma volume first, the order before) and "left-out" (the default: least change
at its own centre first, ``ratefit.importance_left_out``), same seed and settings; per row the re-plan's iteration
and cut, the sample PSNR just before and after it, and the final PSNR of the coded model.

    python benchmarks/accuracy/cut_order.py --volumes vortex@48,interface@48,bubbles@48 --ratio 10 \\
        --iterations 400 --samples 8192 --device cpu --out benchmarks/results/accuracy/cut_order48_cpu.json

A volume is NAME@SIZE (a built-in example field) or a path (``--stride`` applies to files).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

import warpgauss
from warpgauss.encoding.bench import result_header
from warpgauss.encoding.driver import replan
from warpgauss.readers.synthetic import generate

ORDERS = ("weight", "left-out")


def _source(vol: str, stride: int):
    if "@" in vol and not Path(vol).exists():
        name, size = vol.split("@")
        return generate(name, int(size), seed=0)
    from warpgauss.readers import read_volume

    return vol if stride == 1 else np.ascontiguousarray(read_volume(vol, stride=stride).data)


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--volumes", default="vortex@48,interface@48,bubbles@48")
    ap.add_argument("--ratio", type=float, default=10.0)
    ap.add_argument("--iterations", type=int, default=None, help="default: the encode's")
    ap.add_argument("--samples", type=int, default=None, help="default: the encode's rule")
    ap.add_argument("--stride", type=int, default=1)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--device", default=None)
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    res = {**result_header("the re-plan's cut by each order", __file__, argv, args.device), "rows": []}
    saved = replan.CUT_ORDER
    try:
        for vol in args.volumes.split(","):
            src = _source(vol, args.stride)
            for order in ORDERS:
                replan.CUT_ORDER = order
                t = time.perf_counter()
                kw = {k: v for k, v in (("iterations", args.iterations), ("samples", args.samples)) if v is not None}
                m = warpgauss.encode(src, ratio=args.ratio, device=args.device, seed=args.seed, self_test=False, **kw)
                seconds = time.perf_counter() - t
                rp = m.report["budget"]["coded_replan"]
                hist = {int(h["iteration"]): h["sample_psnr_db"] for h in m.report["refinement"]["loss_history"]}
                at = int(rp["iteration"])
                after = min((k for k in hist if k > at), default=None)
                row = {
                    "volume": Path(vol).name,
                    "order": order,
                    "n": int(m.n),
                    "psnr_db": m.report["psnr_db"],
                    "replan_iteration": at,
                    "n_before": rp["n_before"],
                    "n_after": rp["n_after"],
                    "cut_share": 1.0 - rp["n_after"] / rp["n_before"],
                    "sample_psnr_db_before_cut": hist.get(at),
                    "sample_psnr_db_after_cut": None if after is None else hist[after],
                    "seconds": seconds,
                }
                res["rows"].append(row)
                print(
                    f"{row['volume']} {order:9s} cut {row['cut_share']:.0%} at {at}: sample PSNR {row['sample_psnr_db_before_cut']} -> "
                    f"{row['sample_psnr_db_after_cut']}, final {row['psnr_db']:.2f} dB, N {m.n}, {seconds:.1f} s",
                    flush=True,
                )
                args.out.write_text(json.dumps(res, indent=1, default=float))
    finally:
        replan.CUT_ORDER = saved
    by = {(r["volume"], r["order"]): r["psnr_db"] for r in res["rows"]}
    res["left_out_minus_weight_db"] = {v: by[(v, "left-out")] - by[(v, "weight")] for v, o in by if o == "weight" and (v, "left-out") in by}
    args.out.write_text(json.dumps(res, indent=1, default=float))
    print(json.dumps(res["left_out_minus_weight_db"], indent=1))
    return res


if __name__ == "__main__":
    main()
