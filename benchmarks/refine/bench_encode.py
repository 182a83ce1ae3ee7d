"""Benchmark the encoder's stages (analytic allocation + evaluation) on the built-in example fields.

Prints a table and writes JSON (device name, Warp version, date, per-stage seconds and peak
memory, PSNR) to --out. A warm-up encode runs first so that kernel compilation is reported
separately and kept out of the timings.

    python benchmarks/refine/bench_encode.py --fields vortex,bubbles --sizes 128,256 --budgets 20000
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import time
from pathlib import Path

import numpy as np

import warpgauss
from warpgauss.core.warp import device_name, resolve_device, warp
from warpgauss.readers.synthetic import generate


def _ints(text: str) -> list[int]:
    return [int(x) for x in text.split(",") if x]


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--fields", default="vortex,bubbles,turbulence,interface")
    ap.add_argument("--sizes", default="64")
    ap.add_argument("--budgets", default="4000")
    ap.add_argument("--device", default=None)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default="benchmarks/results/refine/bench_encode.json")
    args = ap.parse_args(argv)

    wp = warp()
    dev = resolve_device(args.device)
    t0 = time.perf_counter()
    warpgauss.encode(generate("vortex", 16), budget=50, device=dev)  # compiles every kernel module
    compile_s = time.perf_counter() - t0

    rows = []
    for size in _ints(args.sizes):
        for name in args.fields.split(","):
            t = time.perf_counter()
            vol = generate(name, size, seed=0)
            gen_s = time.perf_counter() - t
            for n in _ints(args.budgets):
                try:
                    m = warpgauss.encode(vol, budget=n, seed=args.seed, device=dev)
                except warpgauss.WarpgaussError as e:
                    rows.append({"field": name, "size": size, "n": n, "refused": str(e)})
                    print(f"{name:11s} {size:5d} {n:8d}  refused: {e}")
                    continue
                r = m.report
                stages = {s["stage"]: s["seconds"] for s in r["stages"]}
                ev = r["evaluation"]["final"]
                row = {
                    "field": name,
                    "size": size,
                    "n": n,
                    "generate_seconds": gen_s,
                    "stages": r["stages"],
                    "analysis_seconds": sum(v for k, v in stages.items() if k.startswith("S1")),
                    "eval_seconds": stages.get("EV", 0.0),
                    "total_seconds": r["total_seconds"],
                    "psnr_db": ev["psnr_db"],
                    "psnr_occupied_db": ev["psnr_occupied_db"],
                    "eval_mode": ev["mode"],
                    "bytes": r["budget"]["bytes"],
                    "compression_ratio": r["budget"]["compression_ratio"],
                    "structure": r["structure"],
                    "peak_host_bytes": r["peak_host_bytes"],
                    "peak_device_bytes": r["peak_device_bytes"],
                }
                rows.append(row)
                print(
                    f"{name:11s} {size:5d} {n:8d}  S1 {row['analysis_seconds']:7.3f} s  EV {row['eval_seconds']:7.3f} s  "
                    f"total {row['total_seconds']:7.3f} s  PSNR {row['psnr_db']:6.2f} dB  CR {row['compression_ratio']:8.2f}",
                    flush=True,
                )
    result = {
        "benchmark": "encode (analytic allocation + evaluation)",
        "device": dev,
        "device_name": device_name(dev),
        "warp_version": wp.config.version,
        "numpy_version": np.__version__,
        "date": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
        "cold_compile_and_warmup_seconds": compile_s,
        "rows": rows,
    }
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2, default=str) + "\n")
    print(f"\n{result['device_name']}, Warp {result['warp_version']}, warm-up {compile_s:.1f} s -> {out}")
    return result


if __name__ == "__main__":
    main()
