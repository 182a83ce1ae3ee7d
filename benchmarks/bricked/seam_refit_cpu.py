"""Bricks that do not wait for their neighbours, then a joint refit of the seams (issue #35, part 1),
CPU: can every brick start at once (one wave, which a GPU steps side by side) if the primitives
near the inner faces are refined together afterwards?

For each example field at ``--size`` (2x2x2 bricks, the default halo, format full): the
monolithic encode, the bricked encode in waves (the default), the bricked encode with every brick
at once (``warpgauss.encoding.scale.bricks.NEIGHBOURS_FIRST`` False), and that model refined again over the
whole grid for each share of ``--refit`` x the iterations (``warpgauss.encoding.scale.bricks.refit_seams``), with
only the primitives whose 3-sigma box reaches within ``--band`` voxels of an inner face stepped (the
rest frozen). Rows: full-grid
PSNR, at the seams (within 2 voxels of an inner face) and elsewhere, the primitives refit, and
the seconds of each step (the CPU's: only the accuracy transfers to a GPU).

    python benchmarks/bricked/seam_refit_cpu.py --out benchmarks/results/bricked/seam_refit_cpu.json
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

import warpgauss
from warpgauss.encoding.allocate import AllocationConfig
from warpgauss.encoding.bench import result_header
from warpgauss.encoding.refine import RefineConfig
from warpgauss.encoding.scale import schedule as wsched
from warpgauss.encoding.scale import seams as wseams
from warpgauss.encoding.scale.plan import brick_cap, face_band, plan_bricks
from warpgauss.field.analysis import normalise
from warpgauss.field.gaussians import GaussianField
from warpgauss.readers.synthetic import generate


def psnr(e: np.ndarray) -> float:
    return float(10 * np.log10(1 / max(float(e.mean()), 1e-20)))


def scores(params: np.ndarray, f, near: np.ndarray) -> dict:
    d = np.concatenate([s for _, s in GaussianField(params, f.shape_xyz, "cpu").iter_slabs()])
    e = (d.astype(np.float64) - f.values) ** 2
    return {"psnr_db": psnr(e), "seam_psnr_db": psnr(e[near]), "interior_psnr_db": psnr(e[~near])}


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", type=int, default=48)
    ap.add_argument("--budget", type=int, default=1500)
    ap.add_argument("--iterations", type=int, default=150)
    ap.add_argument("--refit", default="0.1,0.25,0.5", help="refit iterations as shares of --iterations")
    ap.add_argument("--band", type=float, default=2.0)
    ap.add_argument("--lr", default="1", help="the refit's learning-rate scales (bricked.SEAM_LR), comma list")  # 1: the first runs
    ap.add_argument(
        "--samples-band",
        default="0",
        help="the refit's samples where its primitives reach (1) or over the grid (0), comma list (bricked.SEAM_SAMPLES_BAND)",
    )
    ap.add_argument("--no-baselines", action="store_true", help="skip the monolithic and waves encodes")
    ap.add_argument("--fields", default="vortex,interface")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    out = {**result_header("bricks at once, then a joint refit of the seams (CPU)", __file__, argv, "cpu"), "rows": []}
    kw = dict(budget=args.budget, iterations=args.iterations, device="cpu", format="full", self_test=False)
    for name in filter(None, args.fields.split(",")):
        v = generate(name, args.size)
        f = normalise(v)
        bricks = plan_bricks(f.shape_xyz, (2, 2, 2), 0)
        near = face_band(f.shape_xyz, bricks)

        def row(label: str, params: np.ndarray, seconds: float, name=name, f=f, near=near, **more) -> None:
            r = {"field": name, "run": label, "seconds": seconds, **scores(params, f, near), **more}
            out["rows"].append(r)
            print(r, flush=True)
            args.out.write_text(json.dumps(out, indent=1))

        runs = (("monolithic", None), ("waves", True), ("together", False))
        for label, first in runs[2:] if args.no_baselines else runs:
            t = time.perf_counter()
            if first is None:
                m = warpgauss.encode(v, **kw)
            else:
                with wsched.schedule(neighbours_first=first):
                    m = warpgauss.encode(v, bricks="2x2x2", **kw)
            row(label, np.asarray(m.params, np.float32), time.perf_counter() - t)
        together = np.asarray(m.params, np.float32)
        alloc = AllocationConfig(scale_cap=brick_cap(AllocationConfig().resolved_cap(f.shape_xyz), f.shape_xyz, args.budget))
        saved = wseams.SEAM_BAND, wseams.SEAM_LR, wseams.SEAM_SAMPLES_BAND
        wseams.SEAM_BAND = args.band
        for band in (bool(int(x)) for x in args.samples_band.split(",")):
            wseams.SEAM_SAMPLES_BAND = band
            for lr in (float(x) for x in args.lr.split(",")):
                wseams.SEAM_LR = lr
                for share in (float(x) for x in args.refit.split(",")):
                    t = time.perf_counter()
                    refit, facts = wseams.refit_seams(f, bricks, together, RefineConfig(iterations=args.iterations), alloc, 0, "cpu", share)
                    row(
                        f"together + refit {share:g}"
                        + (f" at {lr:g}x the rate" if lr != 1 else "")
                        + (", samples where it reaches" if band else ""),
                        refit,
                        time.perf_counter() - t,
                        refit_primitives=facts["primitives"],
                        refit_iterations=facts["iterations"],
                        refit_samples=facts.get("samples"),
                        sampled_share=facts.get("sampled_share", 1.0),
                        lr_scale=lr,
                    )
        wseams.SEAM_BAND, wseams.SEAM_LR, wseams.SEAM_SAMPLES_BAND = saved
    args.out.write_text(json.dumps(out, indent=1))
    return out


if __name__ == "__main__":
    main()
