"""Training and rate-control variants at fixed ratios (issue #32): what the samples, their weights
and the rate control buy, on the three head/brain volumes of ``../shared/data`` and example fields.

For each volume, ratio and variant: the default coded encode (``warpgauss encode VOL --ratio R``
with the variant's settings), its full-grid PSNR (decode of the coded model, normalised, masked
voxels out), the end-of-training sample PSNR, N, the rate control's steps and the encode time;
with ``--float`` also a float32 model of the same N and variant (``--format full --budget N``),
the reference the coded file is held to (within 0.5 dB).

Variants (``--variants``, comma list):
    paper      samples jittered by up to half a voxel, trilinear targets, equal weights, and the
               old rate control (bits dropped beyond a 3 % excess, no refit)
    jitter     jittered samples, equal weights, new rate control
    centres    voxel centres, equal weights, new rate control
    default    voxel centres, importance weights, new rate control (the library's defaults)
    jitter-iw  jittered samples with importance weights, new rate control
    quarter    samples within a quarter voxel, importance weights, new rate control
    norefit    the defaults without the refit after pruning
    oldfit     the defaults with the old rate control
    prune10    up to a 10 % excess pruned (no refit), beyond it bits dropped
    keepbits   the refined model coded at the depths N was sized for (no refit; rows measured
               before a fix started from the default grids)
    refit-lo   pruning up to a 50 % excess, refit for 20 % of the iterations at 0.02 x the rate
    s16k       the defaults at 16,384 samples an iteration (whatever N and the grid)
    s32k       the defaults at 32,768 samples an iteration
    split      the defaults with the split forward pass wherever its partial sums fit (the CUDA
               choice before ``SPLIT_MAX_POINTS``; the same model to float32 rounding)
    bits37     one bit more on every attribute from 3 dB lower expected PSNRs
               (``coded.BITS_REFERENCE_DB`` 37 instead of 40)
    bits34     the same from 6 dB lower (34)
    bits43     one bit fewer: every bit 3 dB later (``coded.BITS_REFERENCE_DB`` 43)
    it1000     the defaults at 1,000 iterations instead of 1,500 (the encode-time target)
    err0, err25, err50, err75
               that share of the samples drawn where the error is (``RefineConfig.error_share``
               0 / 0.25 / 0.5 / 0.75), the rest as the defaults
    err50-s16k the error stratum at half the samples, at 16,384 samples an iteration
    late       the late re-plan on (``replan.REPLAN_LATE``: more Gaussians taken out half-way
               from the re-plan to the end where the model will need more bits)
    nosmooth   the smoothness term off (``LossWeights.smooth`` 0): no partner points, half the
               points of an iteration (the default since issue #52)
    nosmooth-2x
               the smoothness term off at twice the samples on a GPU (one per 64 voxels, up to
               262,144): as many points an iteration as the defaults had with the term on
    smooth     the smoothness term on, 0.01 annealed to 0.0001 (the default before issue #52)
    nosmooth-2x-it1000
               nosmooth-2x at 1,000 iterations
    rebin20    the defaults with a re-bin every 20 iterations instead of 10 (half the re-bins)
    relocate   the defaults with dead primitives (weight below 0.02) relocated to the error
               every 100 iterations for the first half (``RefineConfig.relocate_every``, issue #53)
    relocate-w10, relocate-w20
               relocate with the weight below which a primitive counts as dead at 0.10 / 0.20
    rc16, rc32 the point grids planned with ROW_COST 16 / 32 (finer cells) instead of 64
    pad0, pad05
               the cell lists' boxes padded by 0 / 0.5 voxels (and the 10 % share) instead of 1
    rc16-pad0  both
    cellorder  the listed forward visits the points by level-0 point cell (before the Morton order)
    cut-weight the re-plan takes out the least weight x sigma volume first (``replan.CUT_ORDER``
               "weight", the order before "left-out", ``ratefit.importance_left_out``)

    python benchmarks/accuracy/sweep.py --device cuda:0 --ratios 30,300 --size 256 \\
        --variants paper,default,centres,jitter-iw --volume-dir /tmp/vol --out sweep.json
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "rate_distortion"))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "speed"))

import bench_rd  # noqa: E402  (the volumes and the full-grid PSNR every RD figure uses)
from profile_encode import _apply as set_constants  # noqa: E402  ("module.CONST" -> value; returns the old values)

from warpgauss.core.profiling import StageRecorder  # noqa: E402
from warpgauss.encoding.allocate import AllocationConfig  # noqa: E402
from warpgauss.encoding.bench import result_header  # noqa: E402
from warpgauss.encoding.driver import (  # noqa: E402
    EncodeOptions,
    encode_field,
    load_field,
    replan,  # noqa: E402 - the rate-control constants
)
from warpgauss.encoding.refine import RefineConfig  # noqa: E402
from warpgauss.encoding.refine import config as refine_config  # noqa: E402
from warpgauss.encoding.refine.config import LossWeights  # noqa: E402
from warpgauss.format import coded, ratefit  # noqa: E402

HEAD_MRIS = "mean_reg2mean.nii.gz,mni_icbm152_t1_tal_nlin_sym_09a_converted.nii.gz,inia19-t1-brain.nii.gz"
# name: (RefineConfig fields, (prune share, refit share)[, refined bits from, refit learning-rate scale])
VARIANTS: dict[str, tuple] = {
    "paper": ({"jitter": 0.5, "importance": False}, (0.03, 0.0)),
    "jitter": ({"jitter": 0.5, "importance": False}, (None, None)),
    "centres": ({"jitter": 0.0, "importance": False}, (None, None)),
    "default": ({}, (None, None)),
    "jitter-iw": ({"jitter": 0.5, "importance": True}, (None, None)),
    "quarter": ({"jitter": 0.25, "importance": True}, (None, None)),
    "norefit": ({}, (None, 0.0)),
    "oldfit": ({}, (0.03, 0.0)),
    "prune10": ({}, (0.10, 0.0)),
    "keepbits": ({}, (None, 0.0), "sizing"),
    "refit-lo": ({}, (None, 0.2), "accuracy", 0.02),
    "s16k": ({"samples": 16384, "auto_samples": False}, (None, None)),
    "s32k": ({"samples": 32768, "auto_samples": False}, (None, None)),
    "split": ({"split_cells": True}, (None, None)),
    "bits37": ({}, (None, None)),
    "bits34": ({}, (None, None)),
    "bits43": ({}, (None, None)),
    "it1000": ({"iterations": 1000}, (None, None)),
    "err0": ({"error_share": 0.0}, (None, None)),
    "err25": ({"error_share": 0.25}, (None, None)),
    "err50": ({"error_share": 0.5}, (None, None)),
    "err75": ({"error_share": 0.75}, (None, None)),
    "err50-s16k": ({"error_share": 0.5, "samples": 16384, "auto_samples": False}, (None, None)),
    "late": ({}, (None, None)),
    "nosmooth": ({"weights": LossWeights(smooth=0.0)}, (None, None)),
    "nosmooth-2x": ({"weights": LossWeights(smooth=0.0)}, (None, None)),
    "nosmooth-2x-it1000": ({"weights": LossWeights(smooth=0.0), "iterations": 1000}, (None, None)),
    "smooth": ({"weights": LossWeights(smooth=0.01, smooth_final=0.0001)}, (None, None)),
    "rebin20": ({"rebin_every": 20}, (None, None)),
    "relocate": ({"relocate_every": 100}, (None, None)),
    "relocate-w10": ({"relocate_every": 100, "relocate_weight": 0.1}, (None, None)),
    "relocate-w20": ({"relocate_every": 100, "relocate_weight": 0.2}, (None, None)),
    "rc16": ({}, (None, None)),
    "rc32": ({}, (None, None)),
    "pad0": ({}, (None, None)),
    "pad05": ({}, (None, None)),
    "rc16-pad0": ({}, (None, None)),
    "cellorder": ({}, (None, None)),
    "cut-weight": ({}, (None, None)),
}
# variants that change a constant of warpgauss.encoding.refine.config for their encodes
TWICE_THE_SAMPLES = {"GPU_VOXELS_PER_SAMPLE": 64, "GPU_MAX_SAMPLES": 262_144}
CONFIG_CONSTANTS: dict[str, dict[str, int]] = {"nosmooth-2x": TWICE_THE_SAMPLES, "nosmooth-2x-it1000": TWICE_THE_SAMPLES}
# variants that change a constant of warpgauss.encoding.driver.replan for their encodes
REPLAN_CONSTANTS: dict[str, dict[str, object]] = {"late": {"REPLAN_LATE": True}, "cut-weight": {"CUT_ORDER": "weight"}}
# variants that change a constant of warpgauss.format.coded for their encodes
CODED_CONSTANTS: dict[str, dict[str, float]] = {
    "bits37": {"BITS_REFERENCE_DB": 37.0},
    "bits34": {"BITS_REFERENCE_DB": 34.0},
    "bits43": {"BITS_REFERENCE_DB": 43.0},
}
# variants that set any module constant ("module.CONST") for their encodes: the point grids' row cost
# (finer cells: fewer candidate pairs, more rows and list entries) and the cell lists' padding
ROW_COST = "warpgauss.field.gaussians.ROW_COST"
PAD_VOXELS = "warpgauss.encoding.refine.passes.LIST_PAD_VOXELS"
MODULE_CONSTANTS: dict[str, dict[str, float]] = {
    "rc16": {ROW_COST: 16.0},
    "rc32": {ROW_COST: 32.0},
    "pad0": {PAD_VOXELS: 0.0},
    "pad05": {PAD_VOXELS: 0.5},
    "rc16-pad0": {ROW_COST: 16.0, PAD_VOXELS: 0.0},
    "cellorder": {"warpgauss.encoding.refine.passes.FORWARD_MORTON": 0},
}


def encode(f, info, ratio, variant, dev, budget=None, fmt=None):
    fields, (prune, refit), *more = VARIANTS[variant]
    saved = ratefit.PRUNE_SHARE, replan.REFIT_SHARE, replan.REFINED_BITS, replan.REFIT_LR
    # the variant's module constants, each module's old values kept for the restore below
    constants = [(coded, CODED_CONSTANTS), (replan, REPLAN_CONSTANTS), (refine_config, CONFIG_CONSTANTS)]
    saved_constants = [(m, {k: getattr(m, k) for k in table.get(variant, {})}) for m, table in constants]
    for m, table in constants:
        for k, v in table.get(variant, {}).items():
            setattr(m, k, v)
    saved_module = set_constants(MODULE_CONSTANTS.get(variant, {}))
    if prune is not None:
        ratefit.PRUNE_SHARE = prune
    if refit is not None:
        replan.REFIT_SHARE = refit
    if more:
        replan.REFINED_BITS = more[0]
        replan.REFIT_LR = more[1] if len(more) > 1 else replan.REFIT_LR
    try:
        cfg = dataclasses.replace(RefineConfig(), **fields)
        opts = EncodeOptions(ratio=None if budget else ratio, budget=budget, seed=0, allocation=AllocationConfig(), refine=cfg, format=fmt)
        t0 = time.perf_counter()
        model = encode_field(f, opts, device=dev, timer=StageRecorder(), input_info=info, evaluate=False)
        seconds = time.perf_counter() - t0
    finally:
        ratefit.PRUNE_SHARE, replan.REFIT_SHARE, replan.REFINED_BITS, replan.REFIT_LR = saved
        for m, old in saved_constants:
            for k, v in old.items():
                setattr(m, k, v)
        set_constants(saved_module)
    return model, seconds


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--fields", default="vortex,interface")
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--real", default=HEAD_MRIS, help="files in --data-dir (comma list) or 'none'")
    ap.add_argument("--data-dir", type=Path, default=bench_rd.DATA_DIR)
    ap.add_argument("--volume-dir", type=Path, default=None)
    ap.add_argument("--max-voxels", type=int, default=100_000_000)
    ap.add_argument("--ratios", type=bench_rd._floats, default=(30.0, 300.0))
    ap.add_argument("--variants", default="paper,default")
    ap.add_argument("--float", action="store_true", help="also a float32 model of the coded file's N")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--out", default="benchmarks/results/accuracy_sweep_cpu.json")
    args = ap.parse_args(argv)
    from warpgauss.core.warp import warp

    warp().init()
    result = {**result_header("training and rate-control variants at fixed ratios (issue #32)", __file__, argv, args.device)}
    result["rows"] = rows = []
    out = Path(args.out)
    for label, src, raw, _ in bench_rd.volumes(args):
        f, info = load_field(src["source"], src.get("read"))
        truth = bench_rd.Truth(raw, f.vmin, f.vmax, f.mask)
        encode(f, info, min(args.ratios), "default", args.device)  # warm-up: kernels compiled, self-test done
        for r in args.ratios:
            for v in args.variants.split(","):
                model, secs = encode(f, info, r, v, args.device)
                rep = model.report
                dec = model.decode(device=args.device, normalised=True)
                hist = rep["refinement"].get("loss_history") or [{}]
                row = {
                    "volume": label,
                    "target_ratio": r,
                    "variant": v,
                    "n": model.n,
                    "bytes": rep["budget"]["bytes"],
                    "ratio": rep["budget"]["compression_ratio"],
                    "psnr_db": truth.psnr(dec, normalised=True),
                    "sample_psnr_db": hist[-1].get("sample_psnr_db"),
                    "grid_psnr_db_from_samples": hist[-1].get("grid_psnr_db"),  # one iteration's samples: noisy
                    "end_estimate": rep["refinement"].get("end_estimate"),  # Refiner.end_estimate: several draws
                    "encode_s": secs,
                    "refinement_s": rep["refinement"].get("seconds"),
                    "samples": rep["refinement"].get("samples"),
                    "coded_sizing": rep["budget"]["coded_sizing"],
                    "coded_fit": rep["budget"]["coded_fit"],
                    "bits_note": rep["budget"]["coded_bits_from_accuracy"],
                    "coded_replan": rep["budget"].get("coded_replan"),
                    "history": [(h["iteration"], h.get("sample_psnr_db")) for h in rep["refinement"].get("loss_history") or []],
                }
                if args.float:
                    fm, fsecs = encode(f, info, r, v, args.device, budget=model.n, fmt="full")
                    row["float_same_n_psnr_db"] = truth.psnr(fm.decode(device=args.device, normalised=True), normalised=True)
                    row["float_encode_s"] = fsecs
                    row["coded_minus_float_db"] = row["psnr_db"] - row["float_same_n_psnr_db"]
                rows.append(row)
                print(
                    f"{label:44s} R {r:6g} {v:9s} N {model.n:8d} CR {row['ratio']:7.1f} psnr {row['psnr_db']:6.2f} "
                    f"sample {row['sample_psnr_db'] or float('nan'):6.2f} "
                    f"end grid est {(row['end_estimate'] or {}).get('grid_psnr_db', float('nan')):6.2f} "
                    + (f"float {row['float_same_n_psnr_db']:6.2f} " if args.float else "")
                    + f"{secs:6.1f} s pruned {(row['coded_fit'] or {}).get('pruned')} steps {(row['coded_fit'] or {}).get('steps')}",
                    flush=True,
                )
                tmp = out.with_name(out.name + ".tmp")
                out.parent.mkdir(parents=True, exist_ok=True)
                tmp.write_text(json.dumps(result, indent=1, default=float))
                os.replace(tmp, out)
    return result


if __name__ == "__main__":
    main()
