"""Which attribute's bits a byte budget keeps (issue #32): the export fit in the fixed orders
(``ratefit.SHRINK_ORDER`` / ``GROW_ORDER``) against the orders measured on the model itself
(``ratefit.bit_worth``: each attribute one bit more and one fewer, projected and scored), at the same
bytes, on one float32 model per volume.

For each volume: ``warpgauss.encode(..., format="full", budget=N, iterations=I)``; then for each
budget (the model coded at the depths its accuracy asks for, ``ratefit.bits_for_psnr``, times each
``--scales``): ``ratefit.fit_bytes`` without a score (fixed orders, no choice), with the full-grid
PSNR as its score but the fixed orders (``fixed_scored``: the choice of prune shares alone, as
before the measured orders) and with it (``measured``: orders and choice), and the full-grid
PSNR of each fit (decode against the source, over its value range).

    python benchmarks/accuracy/bit_order.py --fields vortex,interface --size 96 --budget 20000 \\
        --iterations 400 --out benchmarks/results/accuracy/bit_order_fields_cpu.json
    python benchmarks/accuracy/bit_order.py --fields "" --iterations 400 \\
        --real mni_icbm152_t1_tal_nlin_sym_09a_converted.nii.gz:10000,mean_reg2mean.nii.gz:20000 \\
        --out benchmarks/results/accuracy/bit_order_mri_cpu.json
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from float_models import add_arguments, float_models  # beside this script

from warpgauss.encoding.bench import result_header
from warpgauss.format import coded, ratefit


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_arguments(ap)
    ap.add_argument("--scales", default="0.8,1.0,1.2", help="budgets as shares of the size at the accuracy's depths")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    result = {
        **result_header("fixed against measured bit orders at the same bytes (float32 models)", __file__, argv, args.device),
        "rows": [],
    }
    for label, m, psnr, seconds in float_models(args):
        base = psnr(m.params)
        bits, _ = ratefit.bits_for_psnr(base)
        at = len(coded.encode_coded(m.params, bits)[0])
        row: dict = {"volume": label, "n": m.n, "iterations": args.iterations, "encode_s": seconds, "psnr_db": base}
        row["bits"], row["bytes_at_bits"], row["fits"] = dict(bits), at, []
        print(f"{label}: float {base:.2f} dB, N {m.n}, coded at {bits}: {at} B")
        for scale in (float(s) for s in args.scales.split(",")):
            budget = int(at * scale)
            t1 = time.perf_counter()
            fixed, fb, finfo = ratefit.fit_bytes(m.params, budget, bits)
            t2 = time.perf_counter()
            ratefit.MEASURE_BIT_WORTH = True  # the orders measured on the model (off by default)
            try:
                measured, mb, minfo = ratefit.fit_bytes(m.params, budget, bits, score=lambda stored, b, psnr=psnr: psnr(stored))
            finally:
                ratefit.MEASURE_BIT_WORTH = False
            t3 = time.perf_counter()
            chosen, cb, cinfo = ratefit.fit_bytes(
                m.params, budget, bits, score=lambda stored, b, psnr=psnr: psnr(stored)
            )  # the scored choice alone
            fit = {
                "scale": scale,
                "budget": budget,
                "fixed": {
                    "psnr_db": psnr(fixed),
                    "bits": fb,
                    "steps": finfo["steps"],
                    "pruned": finfo["pruned"],
                    "bytes": finfo["bytes"],
                    "seconds": t2 - t1,
                },
                "fixed_scored": {
                    "psnr_db": psnr(chosen),
                    "bits": cb,
                    "steps": cinfo["steps"],
                    "pruned": cinfo["pruned"],
                    "chosen": cinfo.get("chosen"),
                },
                "measured": {
                    "psnr_db": psnr(measured),
                    "bits": mb,
                    "steps": minfo["steps"],
                    "pruned": minfo["pruned"],
                    "bytes": minfo["bytes"],
                    "seconds": t3 - t2,
                    "bit_worth": minfo["bit_worth"],
                    "chosen": minfo.get("chosen"),
                },
            }
            fit["measured_minus_fixed_db"] = fit["measured"]["psnr_db"] - fit["fixed"]["psnr_db"]
            fit["measured_minus_fixed_scored_db"] = fit["measured"]["psnr_db"] - fit["fixed_scored"]["psnr_db"]
            row["fits"].append(fit)
            print(
                f"  x{scale:4.2f} ({budget} B): fixed {fit['fixed']['psnr_db']:6.2f} dB {finfo['steps']} | "
                f"fixed + scored choice {fit['fixed_scored']['psnr_db']:6.2f} dB (pruned {cinfo['pruned']}) | "
                f"measured {fit['measured']['psnr_db']:6.2f} dB {minfo['steps']} pruned {minfo['pruned']} "
                f"({fit['measured_minus_fixed_db']:+.2f} / {fit['measured_minus_fixed_scored_db']:+.2f})"
            )
        result["rows"].append(row)
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(result, indent=1, default=float))
    return result


if __name__ == "__main__":
    main()
