"""Warm start against cold start on the evolving examples (issue #21 target: a warm-started
timestep reaches the cold start's PSNR of the same timestep within 0.2 dB in <= 25 % of the cold
start's refinement time), and a whole series at one N.

For each field, timestep 0 is encoded cold; then for t = 1 .. steps-1:
  cold      the timestep encoded from its own allocation (default iterations);
  warm25    from the previous warm25 model moved with the motion (stage S1m), refinement bounded
            to 25 % of cold's refinement seconds;
  static25  the same without motion compensation (--no-motion);
  warm_to   from the previous warm25 model (moved), stopped once the validation PSNR (65,536
            voxels, checked every 100 iterations) reaches cold - 0.2 dB: the iterations and
            seconds that needed.
``--series K`` then encodes K timesteps of the first field with encode_series (warm, at
``--warm-iterations``) and records the total time and the per-step PSNR.

    python benchmarks/series/warm_vs_cold.py --size 256 --budget 100000 --fields vortex,bubbles --steps 3 --out $OUT/warm_vs_cold_256_h100.json
"""

from __future__ import annotations

import argparse
import json
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import warpgauss
from warpgauss.core.warp import resolve_device
from warpgauss.encoding import motion
from warpgauss.encoding.bench import result_header
from warpgauss.readers.synthetic import generate


def steps_of(name: str, size: int, steps: int, turn: float) -> list:
    """The series' volumes, turned in parallel threads (scipy releases the GIL)."""
    from scipy.ndimage import rotate

    from warpgauss.readers.synthetic import unit_range

    base = generate(name, size)
    if steps == 1:
        return [base]

    def turned(t):
        import numpy as np

        return unit_range(rotate(base, t * turn, axes=(1, 2), reshape=False, order=1, mode="nearest").astype(np.float32))

    with ThreadPoolExecutor(max_workers=8) as pool:
        return [base, *pool.map(turned, range(1, steps))]


def row(kind: str, t: int, m) -> dict:
    r = m.report
    ref = r["refinement"]
    stop = ref.get("stop") or {}
    return {
        "kind": kind,
        "step": t,
        "psnr_db": r["psnr_db"],
        "start_psnr_db": r["evaluation"]["analytic"]["psnr_db"],
        "refine_seconds": ref.get("seconds") or 0.0,  # none: the start already met --target-psnr
        "iterations_done": ref.get("iterations_done") or 0,
        "samples": ref.get("samples"),
        "stop": stop.get("reason"),
        "total_seconds": r["total_seconds"],
        "motion_seconds": sum(s["seconds"] for s in r["stages"] if s["stage"] == "S1m"),
        "motion": (r.get("allocation") or {}).get("motion"),
    }


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--budget", type=int, default=100_000)
    ap.add_argument("--fields", default="vortex,bubbles")
    ap.add_argument("--steps", type=int, default=3, help="timesteps per field (0 cold, then the measured ones)")
    ap.add_argument("--turn", type=float, default=4.0, help="degrees per timestep")
    ap.add_argument("--share", type=float, default=0.25, help="warm refinement time as a share of cold's")
    ap.add_argument("--series", type=int, default=0, help="also encode this many timesteps of the first field as one series")
    ap.add_argument("--warm-iterations", type=int, default=375)
    ap.add_argument("--keyframe-drift", type=float, default=None, help="the series' key-frame rule (default: warpgauss's; 0: never)")
    ap.add_argument("--no-turn", action="store_true", help="motion compensation moves the primitives without turning them")
    ap.add_argument("--device", default=None)
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    dev = resolve_device(args.device)
    if args.no_turn:
        motion.TURN = False
    kw = dict(budget=args.budget, device=dev, format="full")
    warpgauss.encode(generate("vortex", 16), budget=50, device=dev, iterations=2, samples=64, format="full")  # compile, self-test
    result = {
        **result_header("warm vs cold start on the evolving examples (format full, defaults otherwise)", __file__, argv, dev),
        "size": args.size,
        "budget": args.budget,
        "turn_degrees": args.turn,
        "share": args.share,
        "rows": [],
        "summary": [],
    }
    print(f"{'field':10s} {'t':>2s} {'kind':8s} {'PSNR':>7s} {'start':>7s} {'refine s':>9s} {'its':>6s}  stop")
    for name in filter(None, args.fields.split(",")):
        vols = steps_of(name, args.size, args.steps, args.turn)
        prev = warpgauss.encode(vols[0], **kw)
        result["rows"].append({"field": name, **row("cold", 0, prev)})
        for t in range(1, len(vols)):
            cold = warpgauss.encode(vols[t], **kw)
            c = row("cold", t, cold)
            budget_s = args.share * c["refine_seconds"]
            warm = warpgauss.encode(vols[t], warm_start=prev, time_budget=budget_s, **kw)
            w = row("warm25", t, warm)
            static = warpgauss.encode(vols[t], warm_start=prev, time_budget=budget_s, motion=False, **kw)
            st = row("static25", t, static)
            to = warpgauss.encode(vols[t], warm_start=prev, target_psnr=c["psnr_db"] - 0.2, **kw)
            w_to = row("warm_to", t, to)
            for r in (c, w, st, w_to):
                result["rows"].append({"field": name, **r})
                print(
                    f"{name:10s} {t:2d} {r['kind']:8s} {r['psnr_db']:7.2f} {r['start_psnr_db']:7.2f} {r['refine_seconds']:9.2f} "
                    f"{r['iterations_done']:6d}  {r['stop'] or ''}"
                )
            result["summary"].append(
                {
                    "field": name,
                    "step": t,
                    "cold_psnr_db": c["psnr_db"],
                    "warm25_psnr_db": w["psnr_db"],
                    "warm25_gap_db": c["psnr_db"] - w["psnr_db"],
                    "static25_gap_db": c["psnr_db"] - st["psnr_db"],
                    "warm25_motion_seconds": w["motion_seconds"],
                    "warm25_time_share": w["refine_seconds"] / c["refine_seconds"],
                    "warm_to_time_share": w_to["refine_seconds"] / c["refine_seconds"],
                    "warm_to_reached": w_to["psnr_db"] >= c["psnr_db"] - 0.2,
                }
            )
            prev = warm
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(result, indent=2))
    if args.series:
        name = args.fields.split(",")[0]
        t0 = time.perf_counter()
        vols = steps_of(name, args.size, args.series, args.turn)
        gen = time.perf_counter() - t0
        t0 = time.perf_counter()
        drift = {} if args.keyframe_drift is None else {"keyframe_drift": args.keyframe_drift}
        models = warpgauss.encode_series(vols, warm_iterations=args.warm_iterations, **drift, **kw)
        total = time.perf_counter() - t0
        result["series"] = {
            "field": name,
            "steps": args.series,
            "warm_iterations": args.warm_iterations,
            "generate_seconds": gen,
            "encode_seconds": total,
            "per_step": [
                {
                    "step": t,
                    "psnr_db": m.report["psnr_db"],
                    "seconds": m.report["total_seconds"],
                    "refine_seconds": m.report["refinement"].get("seconds"),
                    "motion_seconds": sum(s["seconds"] for s in m.report["stages"] if s["stage"] == "S1m"),
                    "iterations": m.report["refinement"]["iterations_done"],
                    "warm_start": m.report["series"]["warm_start"],
                    "keyframe": m.report["series"].get("keyframe"),
                }
                for t, m in enumerate(models)
            ],
        }
        print(
            f"series {name} {args.series} x {args.size}^3: {total:.1f} s; PSNR "
            + " ".join(f"{m.report['psnr_db']:.2f}{'*' if 'keyframe' in m.report['series'] else ''}" for m in models)
            + "  (*: re-encoded cold, a key frame)"
        )
    for s in result["summary"]:
        print(
            f"{s['field']:10s} t={s['step']}: cold {s['cold_psnr_db']:.2f}, warm at {100 * s['warm25_time_share']:.0f} % time "
            f"{s['warm25_psnr_db']:.2f} (gap {s['warm25_gap_db']:+.2f} dB; without motion {s['static25_gap_db']:+.2f}); "
            f"warm to cold-0.2 in {100 * s['warm_to_time_share']:.0f} % time"
        )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2))
    return result


if __name__ == "__main__":
    main()
