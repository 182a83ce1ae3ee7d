"""Benchmark refinement (S2): PSNR before/after and seconds per stage, per preset and sample count.

Prints a table and writes JSON (device name, Warp version, date). A warm-up encode compiles every
kernel module first. ``--sweep`` adds a samples-per-iteration sweep (to choose the quality preset)
and ``--repeat`` encodes the first field twice with the same seed to measure run-to-run spread.

    python benchmarks/refine/bench_refine.py --size 128 --budget 20000 --presets paper,fast --sweep 3072,65536
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


def _row(name, size, n, label, m) -> dict:
    r = m.report
    ev = r["evaluation"]
    ref = r["refinement"]
    return {
        "field": name,
        "size": size,
        "n": n,
        "run": label,
        "iterations": ref.get("iterations", 0),
        "samples": ref.get("samples"),
        "psnr_analytic_db": ev["analytic"]["psnr_db"],
        "psnr_final_db": ev["final"]["psnr_db"],
        "gain_db": ev["gain_db"],
        "refine_seconds": ref.get("seconds"),
        "ms_per_iteration": ref.get("ms_per_iteration"),
        "stages": {s["stage"]: s["seconds"] for s in r["stages"]},
        "total_seconds": r["total_seconds"],
        "peak_device_bytes": r["peak_device_bytes"],
    }


def _print(row: dict) -> None:
    print(
        f"{row['field']:11s} {row['size']:4d} {row['n']:8d} {row['run']:>14s} it {row['iterations']:5d} x "
        f"{row['samples'] or 0:7d}  PSNR {row['psnr_analytic_db']:6.2f} -> {row['psnr_final_db']:6.2f} dB  "
        f"S2 {row['refine_seconds'] or 0:8.3f} s ({row['ms_per_iteration'] or 0:7.3f} ms/it)  total {row['total_seconds']:8.3f} s",
        flush=True,
    )


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--fields", default="vortex,bubbles,turbulence,interface")
    ap.add_argument("--size", type=int, default=64)
    ap.add_argument("--budget", type=int, default=4000)
    ap.add_argument("--presets", default="paper,fast")
    ap.add_argument("--sweep", default="", help="samples per iteration to try at 1,500 iterations")
    ap.add_argument("--grid", default="", help="ITERATIONSxSAMPLES runs, e.g. 750x6144,375x12288")
    ap.add_argument("--sweep-fields", default="vortex,interface")
    ap.add_argument("--repeat", action="store_true", help="same seed twice on the first field: spread")
    ap.add_argument("--device", default=None)
    ap.add_argument("--out", default="benchmarks/results/refine/bench_refine.json")
    args = ap.parse_args(argv)

    wp = warp()
    dev = resolve_device(args.device)
    t0 = time.perf_counter()
    warpgauss.encode(generate("vortex", 16), budget=50, device=dev, iterations=2, samples=64)
    warm = time.perf_counter() - t0
    fields = args.fields.split(",")
    vols = {f: generate(f, args.size, seed=0) for f in set(fields) | set(args.sweep_fields.split(","))}
    rows = []
    for preset in [p for p in args.presets.split(",") if p]:
        for name in fields:
            m = warpgauss.encode(vols[name], budget=args.budget, device=dev, preset=preset)
            rows.append(_row(name, args.size, args.budget, preset, m))
            _print(rows[-1])
    for samples in [int(s) for s in args.sweep.split(",") if s]:
        for name in args.sweep_fields.split(","):
            m = warpgauss.encode(vols[name], budget=args.budget, device=dev, iterations=1500, samples=samples)
            rows.append(_row(name, args.size, args.budget, f"samples={samples}", m))
            _print(rows[-1])
    for spec in [g for g in args.grid.split(",") if g]:
        its, samples = (int(x) for x in spec.split("x"))
        for name in args.sweep_fields.split(","):
            m = warpgauss.encode(vols[name], budget=args.budget, device=dev, iterations=its, samples=samples)
            rows.append(_row(name, args.size, args.budget, spec, m))
            _print(rows[-1])
    spread = None
    if args.repeat:
        name = fields[0]
        a = warpgauss.encode(vols[name], budget=args.budget, device=dev, preset="paper", seed=0)
        b = warpgauss.encode(vols[name], budget=args.budget, device=dev, preset="paper", seed=0)
        c = warpgauss.encode(vols[name], budget=args.budget, device=dev, preset="paper", seed=1)
        pa, pb, pc = (x.report["psnr_db"] for x in (a, b, c))
        spread = {
            "field": name,
            "same_seed_psnr_db": [pa, pb],
            "same_seed_bit_identical": a.params.tobytes() == b.params.tobytes(),
            "same_seed_max_param_diff": float(np.abs(a.params - b.params).max()),
            "other_seed_psnr_db": pc,
        }
        print("spread:", spread)
    result = {
        "benchmark": "refinement (S2) per preset",
        "device": dev,
        "device_name": device_name(dev),
        "warp_version": wp.config.version,
        "date": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
        "warmup_seconds": warm,
        "rows": rows,
        "spread": spread,
    }
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2, default=str) + "\n")
    print(f"\n{result['device_name']}, Warp {result['warp_version']} -> {out}")
    return result


if __name__ == "__main__":
    main()
