"""The error stratum where its map sees few samples (issue #32; the 2048^3 out-of-core question).

The error stratum (``RefineConfig.error_share``) draws from a map of 4^3 cells; a cell sees about
``rebin_every x samples / (1 - error_decay) / cells`` samples over the map's memory. Encodes each
field per size and sample count in three variants, in the same run, and reports the full-grid
PSNR of each with that density:

- ``off``: ``error_share`` 0;
- ``fine``: the default share scored on the 4^3 cells at every density (``draw.ERROR_MIN_SAMPLES_A_CELL``
  0 for the run, so that it is drawn where an encode would leave it out);
- ``pool``: sparse cells scored by blocks of them (``draw.ERROR_POOL``), left out where even the
  largest blocks see under ``draw.ERROR_MIN_SAMPLES_A_CELL``.

    python benchmarks/accuracy/error_density.py --fields interface,ooc --size 192 --samples 64,128,512 --out error_density_cpu.json
    python benchmarks/accuracy/error_density.py --fields interface --size 1024 --samples auto --budget 1400000 --iterations 0 --device cuda:0 --out $OUT/error_density1024.json

``--samples auto`` and ``--iterations 0`` leave them to the encode's defaults.
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
    ap.add_argument("--samples", default="128,512", help="comma list, or 'auto' (the encode's)")
    ap.add_argument("--budget", type=int, default=3000)
    ap.add_argument("--iterations", type=int, default=400, help="0: the encode's")
    ap.add_argument("--variants", default="off,fine,pool")
    ap.add_argument("--pool-target", type=float, default=None, help="draw.ERROR_POOL_SAMPLES_A_CELL for the pool variant")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    import warpgauss
    from warpgauss.encoding.bench import result_header
    from warpgauss.encoding.refine import RefineConfig, draw
    from warpgauss.readers.synthetic import generate

    saved = draw.ERROR_MIN_SAMPLES_A_CELL, draw.ERROR_POOL, draw.ERROR_POOL_SAMPLES_A_CELL
    if args.pool_target is not None:
        draw.ERROR_POOL_SAMPLES_A_CELL = args.pool_target
    result = result_header("the error stratum by the samples its map sees", __file__, argv, args.device)
    result["rows"] = []
    warpgauss.encode(generate("vortex", 16), budget=50, device=args.device, iterations=2, samples=64, format="full", self_test=False)
    for name in args.fields.split(","):
        vol = ooc_field(args.size) if name == "ooc" else generate(name, args.size)
        cells = int(np.prod([-(-s // 4) for s in vol.shape]))
        for m in [None] if args.samples == "auto" else [int(s) for s in args.samples.split(",")]:
            for variant in args.variants.split(","):
                draw.ERROR_MIN_SAMPLES_A_CELL = 0.0 if variant == "fine" else saved[0]
                draw.ERROR_POOL = variant == "pool"
                t0 = time.perf_counter()
                model = warpgauss.encode(
                    vol,
                    budget=args.budget,
                    iterations=args.iterations or None,
                    samples=m,
                    refine=RefineConfig(error_share=0.0) if variant == "off" else None,
                    format="full",
                    device=args.device,
                    self_test=False,
                    full_eval=True,
                )
                ref = model.report.get("refinement", {})
                stratum = ref.get("error_stratum") or {}
                row = {
                    "field": name,
                    "size": args.size,
                    "variant": variant,
                    "n": model.n,
                    "samples": ref.get("samples"),
                    "cells": cells,
                    "samples_a_cell": stratum.get("samples_a_cell"),
                    "error_stratum": stratum,
                    "pool_target": draw.ERROR_POOL_SAMPLES_A_CELL if variant == "pool" else None,
                    "psnr_db": model.report["psnr_db"],
                    "seconds": time.perf_counter() - t0,
                }
                result["rows"].append(row)
                print(row, flush=True)
                args.out.write_text(json.dumps(result, indent=1))
    draw.ERROR_MIN_SAMPLES_A_CELL, draw.ERROR_POOL, draw.ERROR_POOL_SAMPLES_A_CELL = saved
    return result


if __name__ == "__main__":
    main()
