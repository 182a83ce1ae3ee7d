"""The error stratum where its map sees few samples (issue #32; the 2048^3 out-of-core question).

The error stratum (``RefineConfig.error_share``) draws from a map of 4^3 cells; a cell sees about
``rebin_every x samples / (1 - error_decay) / cells`` samples over the map's memory. Encodes one
field per size and sample count at ``error_share`` 0 and the default, float32, fixed samples, and
reports the full-grid PSNR of each with that density. The stratum is drawn at every density here
(``--min-samples-a-cell``, default 0, stands in for ``draw.ERROR_MIN_SAMPLES_A_CELL``, under which
an encode leaves it out).

    python benchmarks/accuracy/error_density.py --fields interface,ooc --size 192 --samples 128,512 --out error_density_cpu.json
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np


def ooc_field(n: int) -> np.ndarray:
    """benchmarks/bricked/out_of_core.py's field at n^3 (the same formula, in memory)."""
    ax = (np.arange(n, dtype=np.float32) + 0.5) / n
    z, y, x = np.meshgrid(ax, ax, ax, indexing="ij")
    r2 = (x - 0.5) ** 2 + (y - 0.5) ** 2 + (z - 0.5) ** 2
    v = np.exp(-r2 / 0.08) + 0.3 * np.sin(6 * np.pi * x) * np.sin(4 * np.pi * y) * np.cos(5 * np.pi * z)
    v += 0.1 * np.sin(23 * np.pi * x + 9 * np.pi * z) * np.cos(17 * np.pi * y)
    return v.astype(np.float32)


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--fields", default="interface,ooc", help="example fields and/or 'ooc' (out_of_core.py's field)")
    ap.add_argument("--size", type=int, default=192)
    ap.add_argument("--samples", default="128,512")
    ap.add_argument("--budget", type=int, default=3000)
    ap.add_argument("--iterations", type=int, default=400)
    ap.add_argument("--shares", default="0,0.5")
    ap.add_argument("--min-samples-a-cell", type=float, default=0.0, help="draw.ERROR_MIN_SAMPLES_A_CELL for this run")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    import warpgauss
    from warpgauss.bench import result_header
    from warpgauss.refine import RefineConfig, draw
    from warpgauss.synthetic import generate

    draw.ERROR_MIN_SAMPLES_A_CELL = args.min_samples_a_cell
    base = RefineConfig()
    result = result_header("the error stratum by the samples its map sees", __file__, argv, args.device)
    result["rows"] = []
    for name in args.fields.split(","):
        vol = ooc_field(args.size) if name == "ooc" else generate(name, args.size)
        cells = int(np.prod([-(-s // 4) for s in vol.shape]))
        for m in (int(s) for s in args.samples.split(",")):
            density = base.rebin_every * m / (1 - base.error_decay) / cells
            for share in (float(s) for s in args.shares.split(",")):
                t0 = time.perf_counter()
                model = warpgauss.encode(
                    vol,
                    budget=args.budget,
                    iterations=args.iterations,
                    samples=m,
                    refine=RefineConfig(error_share=share),
                    format="full",
                    device=args.device,
                    self_test=False,
                    full_eval=True,
                )
                row = {
                    "field": name,
                    "size": args.size,
                    "samples": m,
                    "cells": cells,
                    "samples_a_cell": density,
                    "error_share": share,
                    "error_stratum": model.report.get("refinement", {}).get("error_stratum"),
                    "psnr_db": model.report["psnr_db"],
                    "seconds": time.perf_counter() - t0,
                }
                result["rows"].append(row)
                print(row, flush=True)
                args.out.write_text(json.dumps(result, indent=1))
    return result


if __name__ == "__main__":
    main()
