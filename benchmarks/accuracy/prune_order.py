"""Which primitives a byte budget may take out (issue #32): the PSNR a float32 model keeps when the
least important 3, 10 and 30 % of its primitives are dropped, by each ranking, and what one bit
less on each attribute costs against pruning at the same bytes.

The model is a normalised blend (a point's value is sum(w a G) / sum(w G)), so a primitive of value 0
holds its neighbourhood at 0 as much as any other holds its value. Rankings:
    value       weight x |value| x sigma volume (the rule before this benchmark)
    weight      weight x sigma volume (its share of the blend's denominator)
    loo         weight x sigma volume x |value - the model at its centre| / (the rest of the
                denominator there): what leaving it out changes at its centre
    loo-hole    the same with 0.05 added to the value difference (a lone primitive leaves a hole)
    random      a random order (seed 0)

Models: ``warpgauss.encode(..., format="full", budget=N, iterations=I)`` per volume; full-grid PSNR
of the decode against the source, over its value range. Volumes: example fields (generated) and
files of ``../shared/data``.

    python benchmarks/accuracy/prune_order.py --fields vortex,interface --size 96 --budget 20000 \\
        --iterations 400 --out benchmarks/results/accuracy/prune_order_fields_cpu.json
    python benchmarks/accuracy/prune_order.py --fields "" --iterations 400 \\
        --real mni_icbm152_t1_tal_nlin_sym_09a_converted.nii.gz:10000,mean_reg2mean.nii.gz:20000 \\
        --out benchmarks/results/accuracy/prune_order_mri_cpu.json
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from float_models import add_arguments, float_models  # beside this script

from warpgauss.encoding.bench import result_header
from warpgauss.format import coded, ratefit
from warpgauss.format.model import Model

SHARES = (0.03, 0.10, 0.30)


def rankings(m: Model, device: str) -> dict[str, np.ndarray]:
    """Importance by each rule (larger: kept longer)."""
    p = m.params.astype(np.float64)
    w, a = np.abs(p[:, 11]), p[:, 10]
    vol = np.exp(np.clip(p[:, 3:6].sum(1), -60.0, 60.0))
    value, density, _ = m.field(device).evaluate_full(m.params[:, 0:3])
    rest = np.maximum(density - w, 1e-3 * float(np.median(density)))
    return {
        "value": np.abs(w * a) * vol,
        "weight": w * vol,
        "loo": w * vol * np.abs(a - value) / rest,
        "loo-hole": ratefit.importance_left_out(m.params, value, density),  # the re-plan's cut order
        "random": np.random.default_rng(0).random(len(p)),
        "ratefit.importance": ratefit.importance(m.params),
    }


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_arguments(ap)
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    result = {**result_header("pruning order and bit depths against bytes (float32 models)", __file__, argv, args.device), "rows": []}
    for label, m, psnr, seconds in float_models(args):
        base = psnr(m.params)
        row: dict = {"volume": label, "n": m.n, "iterations": args.iterations, "encode_s": seconds, "psnr_db": base}
        ranks = rankings(m, args.device)
        row["pruned_psnr_db"] = {
            name: {f"{s:.0%}": psnr(m.params[np.sort(np.argsort(r, kind="stable")[int(s * m.n) :])]) for s in SHARES}
            for name, r in ranks.items()
        }
        bits, _ = ratefit.bits_for_psnr(base)
        at = {"bits": dict(bits), "bytes": len(coded.encode_coded(m.params, bits)[0]), "psnr_db": psnr(coded.as_stored(m.params, bits))}
        drops, b = [], dict(bits)
        for k in ratefit.SHRINK_ORDER:  # one bit less on each attribute in turn, as the rate control drops them
            b[k] -= 1
            drops.append(
                {"dropped": k, "bytes": len(coded.encode_coded(m.params, b)[0]), "psnr_db": psnr(coded.as_stored(m.params, dict(b)))}
            )
        order = np.argsort(ranks["weight"], kind="stable")
        pruned = []
        for d in drops:  # pruning by weight to the bytes each drop reached, at the accuracy's depths
            keep = max(1, int(m.n * d["bytes"] / at["bytes"]))
            sub = m.params[np.sort(order[m.n - keep :])]
            pruned.append({"kept": keep, "bytes": len(coded.encode_coded(sub, bits)[0]), "psnr_db": psnr(coded.as_stored(sub, bits))})
        row["coded"] = {"at_accuracy_bits": at, "bits_dropped": drops, "pruned_to_same_bytes": pruned}
        result["rows"].append(row)
        print(f"{label}: float {base:.2f} dB, N {m.n}")
        for name, by in row["pruned_psnr_db"].items():
            print(f"  prune by {name:16s} " + "  ".join(f"{k} {v:6.2f}" for k, v in by.items()))
        print(f"  coded at {bits}: {at['bytes']} B, {at['psnr_db']:.2f} dB")
        for d, q in zip(drops, pruned):
            print(
                f"  {d['dropped']:6s}-1 (cumulative): {d['bytes']:8d} B {d['psnr_db']:6.2f} dB | pruned by weight to {q['bytes']:8d} B {q['psnr_db']:6.2f} dB"
            )
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(result, indent=1))
    return result


if __name__ == "__main__":
    main()
