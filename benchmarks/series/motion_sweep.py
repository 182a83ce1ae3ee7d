"""Motion-compensation variants along warm chains (issue #21: why a long motion-compensated series
lost 0.3-0.7 dB a step on the vortex while the static chain gained).

For each field, timestep 0 is encoded cold; then every variant runs its own chain of ``--steps``
warm timesteps at ``--iterations`` refinement iterations each (the series' warm setting), from
that same model. A variant sets constants of :mod:`warpgauss.encoding.motion` (``static``: no motion;
``oracle``: the true displacement of the turn instead of the estimate).
Each row records the start PSNR (the moved model before refinement) and the final PSNR.

    python benchmarks/series/motion_sweep.py --size 512 --budget 400000 --fields vortex --steps 4 --out $OUT/motion_sweep.json
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import warpgauss
from warpgauss.core.warp import resolve_device, warp
from warpgauss.encoding import motion
from warpgauss.encoding.bench import result_header
from warpgauss.readers.synthetic import generate

sys.path.insert(0, str(Path(__file__).resolve().parent))
from warm_vs_cold import steps_of  # noqa: E402

DEFAULTS = {k: getattr(motion, k) for k in ("BLOCK", "COARSE_BLOCK", "PASSES", "TURN", "FINEST", "SMOOTH", "STEPS", "WARM_LR_SCALE")}
ESTIMATE = motion.estimate_motion
VARIANTS = "static|oracle|default|BLOCK=4|FINEST=1|SMOOTH=4|PASSES=1"


def oracle(turn_degrees: float):
    """An estimate_motion that returns the true displacement of the examples' turn (scipy's
    rotate about the grid's centre in the y-x plane: x' = cos t dx + sin t dy, y' = -sin t dx + cos t dy)."""
    import numpy as np

    def estimate(ref, cur, levels=None):
        wp = warp()
        nz, ny, nx = (int(s) for s in ref.shape)
        b = motion.BLOCK
        t = np.deg2rad(turn_degrees)
        z, y, x = np.meshgrid(*[(np.arange(-(-n // b)) + 0.5) * b - 0.5 for n in (nz, ny, nx)], indexing="ij")
        dx, dy = x - (nx - 1) / 2, y - (ny - 1) / 2
        d = np.stack([np.cos(t) * dx + np.sin(t) * dy - dx, -np.sin(t) * dx + np.cos(t) * dy - dy, np.zeros_like(dx)], axis=-1)
        return wp.array(d.astype(np.float32), dtype=wp.vec3, device=ref.device)

    return estimate


def parse(variant: str, turn: float) -> tuple[bool, dict, object, dict]:
    """(motion on, warpgauss.encoding.motion constants, the estimate function, RefineConfig changes) of a
    variant: ','-separated tokens static | oracle | default | KEY=VAL (a warpgauss.encoding.motion constant,
    ``smooth`` the smoothness weight's start, or a RefineConfig field)."""
    use_motion, sets, estimate, refine = True, {}, ESTIMATE, {}
    for tok in variant.split(","):
        if tok == "static":
            use_motion = False
        elif tok == "oracle":
            sets["PASSES"], estimate = 1, oracle(turn)
        elif tok != "default":
            k, v = tok.split("=")
            if k in DEFAULTS:
                d = DEFAULTS[k]
                sets[k] = bool(int(v)) if isinstance(d, bool) else type(d)(float(v))
            else:
                refine[k] = float(v)
    return use_motion, sets, estimate, refine


def refine_config(changes: dict):
    """A RefineConfig with ``changes`` (None when there are none: encode's own defaults)."""
    import dataclasses

    from warpgauss.encoding.refine import RefineConfig

    if not changes:
        return None
    cfg = RefineConfig()
    if "smooth" in changes:
        cfg = dataclasses.replace(cfg, weights=dataclasses.replace(cfg.weights, smooth=changes.pop("smooth")))
    return dataclasses.replace(cfg, **changes)


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--budget", type=int, default=100_000)
    ap.add_argument("--fields", default="vortex")
    ap.add_argument("--steps", type=int, default=4, help="warm timesteps after the cold one")
    ap.add_argument("--turn", type=float, default=4.0, help="degrees per timestep")
    ap.add_argument("--iterations", type=int, default=375)
    ap.add_argument(
        "--variants", default=VARIANTS, help="'|'-separated: static, default, or KEY=VAL[,KEY=VAL] of warpgauss.encoding.motion"
    )
    ap.add_argument("--cold-last", action="store_true", help="also encode the last timestep cold (reference)")
    ap.add_argument("--device", default=None)
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    dev = resolve_device(args.device)
    kw = dict(budget=args.budget, device=dev, format="full")
    warpgauss.encode(generate("vortex", 16), budget=50, device=dev, iterations=2, samples=64, format="full")  # compile
    result = {
        **result_header("motion-compensation variants along warm chains", __file__, argv, dev),
        "size": args.size,
        "budget": args.budget,
        "turn_degrees": args.turn,
        "iterations": args.iterations,
        "defaults": {k: (int(v) if isinstance(v, bool) else v) for k, v in DEFAULTS.items()},
        "rows": [],
    }
    for name in filter(None, args.fields.split(",")):
        vols = steps_of(name, args.size, args.steps + 1, args.turn)
        cold0 = warpgauss.encode(vols[0], **kw)
        result["rows"].append({"field": name, "variant": "cold", "step": 0, "psnr_db": cold0.report["psnr_db"]})
        if args.cold_last:
            c = warpgauss.encode(vols[-1], **kw)
            result["rows"].append({"field": name, "variant": "cold", "step": args.steps, "psnr_db": c.report["psnr_db"]})
            print(f"{name} cold step {args.steps}: {c.report['psnr_db']:.2f}")
        for variant in args.variants.split("|"):
            use_motion, sets, motion.estimate_motion, changes = parse(variant, args.turn)
            for k, v in {**DEFAULTS, **sets}.items():
                setattr(motion, k, v)
            cfg = refine_config(changes)
            prev, line = cold0, []
            for t in range(1, args.steps + 1):
                m = warpgauss.encode(vols[t], warm_start=prev, iterations=args.iterations, motion=use_motion, refine=cfg, **kw)
                r = m.report
                row = {
                    "field": name,
                    "variant": variant,
                    "step": t,
                    "start_psnr_db": r["evaluation"]["analytic"]["psnr_db"],
                    "psnr_db": r["psnr_db"],
                    "motion_seconds": sum(s["seconds"] for s in r["stages"] if s["stage"] == "S1m"),
                    "total_seconds": r["total_seconds"],
                    "samples": r["refinement"].get("samples"),
                    "motion": (r.get("allocation") or {}).get("motion"),
                }
                result["rows"].append(row)
                line.append(f"{row['start_psnr_db']:.1f}->{row['psnr_db']:.2f}")
                prev = m
            print(f"{name:9s} {variant:18s} " + "  ".join(line), flush=True)
            args.out.parent.mkdir(parents=True, exist_ok=True)
            args.out.write_text(json.dumps(result, indent=2))
    for k, v in DEFAULTS.items():
        setattr(motion, k, v)
    motion.estimate_motion = ESTIMATE
    return result


if __name__ == "__main__":
    main()
