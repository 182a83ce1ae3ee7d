"""Bricked (2x2x2, in one process on one GPU) against the monolithic encode at the same N and
settings (issue #20 target: PSNR within 0.2 dB, time within 1.3x), full-grid PSNR, and the PSNR
on voxels within 2 voxels of an inner brick face against the rest.

    python benchmarks/bricked/bricked_vs_mono.py --size 512 --budget 400000 --fields vortex,interface --out $OUT/bricked_h100.json
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
from warpgauss.encoding.allocate import AllocationConfig
from warpgauss.encoding.scale.plan import face_band, parse_bricks, plan_bricks
from warpgauss.field.analysis import normalise
from warpgauss.readers.synthetic import generate


def psnr(sse: float, n: int) -> float:
    return float(10 * np.log10(n / max(sse, 1e-30)))


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--budget", type=int, default=400_000)
    ap.add_argument("--fields", default="vortex,interface")
    ap.add_argument("--bricks", default="2x2x2")
    ap.add_argument("--halo", default="default", help="halos to try, comma separated (voxels; default: the bricked encode's rule)")
    ap.add_argument("--caps", default="none", help="sigma caps (voxels) to try, comma separated; none: the default")
    ap.add_argument("--device", default=None)
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    wp = warp()
    dev = resolve_device(args.device)
    warpgauss.encode(generate("vortex", 16), budget=50, device=dev, iterations=2, samples=64, format="full")  # compile
    result = {
        "benchmark": "bricked vs monolithic encode, same N and settings (format full, defaults otherwise)",
        "command": "python benchmarks/bricked/bricked_vs_mono.py " + " ".join(argv if argv is not None else __import__("sys").argv[1:]),
        "device": dev,
        "device_name": device_name(dev),
        "warp_version": wp.config.version,
        "date": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
        "rows": [],
    }
    counts = parse_bricks(args.bricks)
    for name in filter(None, args.fields.split(",")):
        v = generate(name, args.size)
        f = normalise(v)
        near = face_band(f.shape_xyz, plan_bricks(f.shape_xyz, counts, 0))
        runs = [("monolithic", None)] + [("bricked", None if h == "default" else int(h)) for h in args.halo.split(",")]
        for cap, (mode, halo) in [(c, r) for c in args.caps.split(",") for r in runs]:
            kw = dict(budget=args.budget, device=dev, format="full", self_test=False, evaluate=False)
            if cap != "none":
                kw["allocation"] = AllocationConfig(scale_cap=float(cap))
            if mode == "bricked":
                kw.update(bricks=args.bricks, halo=halo)
            t0 = time.perf_counter()
            m = warpgauss.encode(v, **kw)
            wall = time.perf_counter() - t0
            d = m.decode(device=dev, normalised=True)
            err = (d.astype(np.float64) - f.values) ** 2
            row = {
                "field": name,
                "size": args.size,
                "mode": mode,
                "halo": halo,
                "scale_cap": None if cap == "none" else float(cap),
                "n": m.n,
                "encode_s": wall,
                "psnr_db": psnr(float(err.sum()), err.size),
                "seam_psnr_db": psnr(float(err[near].sum()), int(near.sum())),
                "interior_psnr_db": psnr(float(err[~near].sum()), int((~near).sum())),
                "samples": m.report["refinement"].get("samples") if mode == "monolithic" else None,
            }
            if mode == "bricked":
                row["halo"] = m.report["bricking"]["halo"]
                row["brick_scale_cap"] = m.report["bricking"]["scale_cap"]
                row["bricks"] = [
                    {k: b.get(k) for k in ("n", "seconds", "samples", "stand_ins", "frozen")} for b in m.report["bricking"]["bricks"]
                ]
            result["rows"].append(row)
            print({k: v_ for k, v_ in row.items() if k != "bricks"}, flush=True)
            args.out.write_text(json.dumps(result, indent=1))
            del d, err, m
    return result


if __name__ == "__main__":
    main()
