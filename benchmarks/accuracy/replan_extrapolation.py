"""How far the mid-training re-plan's extrapolation falls from the end of the run (issue #32), from
the loss histories of sweep.py's rows; no encode is run.

At REPLAN_AT of the iterations (K = T / 4) the re-plan codes the model at the bit depths of the
sample PSNR it expects at the end, ``at + factor x (at - half) x log2(T / K)`` (``half``: the
sample PSNR at K / 2), and takes primitives out where that would not fit the budget. For each row
this prints the factor its own end needed, and for each candidate factor the bits it would have
planned (``ratefit.bits_for_psnr``) against the bits the end's sample PSNR asks for: a row planned
below its end (``under``) codes over budget at the end and loses bits there (measured 0.8-1.6 dB
on the interface at 512^3), a row planned above it (``over``) gives up primitives for a bit it
did not need. Counting bit depths is not the whole cost: a factor of 2.5 (no row under) lost
0.18-0.40 dB on every row it changed when encoded again (``sweep_*_replan25_h200.json``).

    python benchmarks/accuracy/replan_extrapolation.py \\
        benchmarks/results/accuracy/sweep_mri_choice_h200.json \\
        benchmarks/results/accuracy/sweep_fields512_choice_h200.json \\
        --out benchmarks/results/accuracy/replan_extrapolation_h200.json
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

from warpgauss.encoding.bench import result_header
from warpgauss.encoding.driver.replan import REPLAN_EXTRAPOLATE, REPLAN_MAX_GAIN_DB, REPLAN_REST_GAIN_DB
from warpgauss.format.ratefit import bits_for_psnr

FACTORS = (1.0, 1.25, 1.5, 2.0, 2.5, 3.0)


def expected(at: float, half: float, factor: float, t_total: int, k: int) -> float:
    """The re-plan's expected end-of-run sample PSNR for ``factor`` (the rule in replan.py)."""
    rest = max(REPLAN_REST_GAIN_DB, (at - half) * factor * math.log2(t_total / k))
    return at + min(rest, REPLAN_MAX_GAIN_DB)


def row_facts(r: dict) -> dict | None:
    """One sweep row's re-plan facts, or None where it has no re-plan or history."""
    rp, hist = r.get("coded_replan"), r.get("history")
    if not rp or not hist or r.get("sample_psnr_db") is None:
        return None
    t_total = max(int(t) for t, _ in hist)
    k, at, half, end = int(rp["iteration"]), float(rp["sample_psnr_db"]), float(rp["sample_psnr_db_at_half"]), float(r["sample_psnr_db"])
    slope = (at - half) * math.log2(t_total / k)
    end_bits = bits_for_psnr(end)[1]
    plans = {f"{f:g}": bits_for_psnr(expected(at, half, f, t_total, k))[1] - end_bits for f in FACTORS}
    return {
        "volume": r["volume"],
        "target_ratio": r.get("target_ratio"),
        "n_before": rp["n_before"],
        "iterations": t_total,
        "replan_iteration": k,
        "psnr_at_half_db": half,
        "psnr_at_replan_db": at,
        "psnr_end_db": end,
        "needed_factor": (end - at) / slope if slope > 0 else None,
        "end_bits_added": end_bits,
        "planned_minus_end_bits": plans,
    }


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("sweeps", nargs="+", help="sweep.py JSON files")
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    rows = []
    for path in args.sweeps:
        for r in json.loads(Path(path).read_text())["rows"]:
            facts = row_facts(r)
            if facts is not None:
                rows.append(facts | {"source": Path(path).name})
    print(f"{'volume':<34} {'CR':>6} {'at T/8':>7} {'at T/4':>7} {'end':>7} {'needed':>7}  planned - end bits by factor {FACTORS}")
    for x in rows:
        need = "-" if x["needed_factor"] is None else f"{x['needed_factor']:.2f}"
        plans = " ".join(f"{v:+d}" for v in x["planned_minus_end_bits"].values())
        print(
            f"{x['volume'][:34]:<34} {x['target_ratio'] or 0:6.0f} {x['psnr_at_half_db']:7.2f} {x['psnr_at_replan_db']:7.2f} {x['psnr_end_db']:7.2f} {need:>7}  {plans}"
        )
    summary = []
    for f in FACTORS:
        d = [x["planned_minus_end_bits"][f"{f:g}"] for x in rows]
        summary.append({"factor": f, "rows": len(d), "under": sum(v < 0 for v in d), "over": sum(v > 0 for v in d)})
        print(f"factor {f:4g}: planned under the end's bits on {summary[-1]['under']} of {len(d)} rows, over on {summary[-1]['over']}")
    print(f"REPLAN_EXTRAPOLATE now: {REPLAN_EXTRAPOLATE:g}")
    if args.out:
        out = result_header("the re-plan's extrapolation against the end of the run (from sweep histories)", __file__, argv, "cpu")
        out |= {"replan_extrapolate": REPLAN_EXTRAPOLATE, "summary": summary, "rows": rows}
        Path(args.out).write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
