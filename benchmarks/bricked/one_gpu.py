"""A bricked encode on one GPU against the monolithic encode of the same field, N and settings, in
the same run (issue #35, part 1: bricked <= 1.5x the monolithic time, PSNR within 0.2 dB).

For each field and size: the monolithic encode, then each bricking with the bricks of a wave
stepping side by side on the device (the default: ``warpgauss.encoding.scale.bricks.bricks_at_once``), and, with
``--serial``, the same bricking with one brick at a time (``MAX_AT_ONCE = 1``): both must give the
same model bit for bit. Rows: ``size``, ``bricks``, ``at_once``, ``seconds``,
``bricked_over_monolithic`` (time ratio, same run), ``psnr_db`` and ``dpsnr_db`` (full grid,
against the monolithic), the per-brick setup and refinement seconds. ``--profile`` times one
brick's iteration phase by phase (sample, forward, backward, update, re-bin) with the device
synchronised around each, and a captured iteration, to show where a brick's time goes.
``--together 0,0.25,0.5`` adds each bricking with every brick started at once (no waves:
``warpgauss.encoding.scale.bricks.NEIGHBOURS_FIRST`` False), then the seams refit together for that share of the
iterations (``SEAM_REFIT``; 0: none), rows with ``"waves": "together"`` and ``seam_refit``.

    python benchmarks/bricked/one_gpu.py --sizes 512 --fields vortex,interface --bricks 2x2x2,4x4x4 --out $OUT/one_gpu_512_h200.json
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

import warpgauss
import warpgauss.encoding.scale.bricks as wb
import warpgauss.encoding.scale.plan as bp
from warpgauss.core.warp import resolve_device, warp
from warpgauss.encoding.bench import result_header
from warpgauss.encoding.scale import schedule as wsched
from warpgauss.field.analysis import normalise
from warpgauss.readers.synthetic import generate


def psnr(f, m, dev) -> float:
    d = m.decode(device=dev, normalised=True)
    err = (d.astype(np.float64) - f.values) ** 2
    return float(10 * np.log10(err.size / max(float(err.sum()), 1e-30)))


def default_budget(size: int) -> int:
    return int(round(400_000 * (size / 512) ** 3 if size <= 512 else 1_400_000 * (size / 1024) ** 3))


def profile_brick(v: np.ndarray, n: int, bricks: str, dev: str, steps: int = 60, split: bool | None = None) -> dict:
    """One brick of the first wave, set up as the bricked encode does, its iteration timed phase by phase."""
    from warpgauss.encoding.allocate import AllocationConfig
    from warpgauss.encoding.refine import RefineConfig, load_kernels

    wp = warp()
    f = normalise(v)
    alloc = AllocationConfig()
    alloc = AllocationConfig(scale_cap=bp.brick_cap(alloc.resolved_cap(f.shape_xyz), f.shape_xyz, n))
    plan = bp.plan_bricks(f.shape_xyz, bp.parse_bricks(bricks), bp.default_halo(alloc.scale_cap))
    _, stats = bp.split_bricks(f, plan, n)
    tasks = wb.brick_tasks(f, plan, stats, 0, alloc, RefineConfig(split_cells=split), dev, n)
    task = wsched.wave_tasks(tasks, {}, [0])[0]
    t0 = time.perf_counter()
    load_kernels(dev)
    _, r, k = wb.brick_refiner(task, dev)  # as the bricked encode starts a brick
    wp.synchronize_device(dev)
    t_setup = time.perf_counter() - t0
    for _ in range(20):
        r.step()
    wp.synchronize_device(dev)

    def timed(fn, count=steps) -> float:
        wp.synchronize_device(dev)
        t = time.perf_counter()
        for _ in range(count):
            fn()
        wp.synchronize_device(dev)
        return (time.perf_counter() - t) / count * 1e3

    out = {
        "bricks": bricks,
        "box": [hi - lo for lo, hi in task.brick.box],
        "n": task.n,
        "stand_ins": k,
        "samples": task.refine.samples,
        "setup_s": t_setup,
        "step_ms": timed(r.step),
        "rebin_ms": timed(r.rebin, 20),
    }
    r.use_graph = False
    r._graph = None
    out["step_nograph_ms"] = timed(r.step)
    for name in ("sample", "forward", "backward", "update"):
        out[f"{name}_ms"] = timed(getattr(r, name))
    print("profile", out, flush=True)
    return out


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", default="512")
    ap.add_argument("--fields", default="vortex,interface")
    ap.add_argument("--bricks", default="2x2x2,4x4x4")
    ap.add_argument("--budget", type=int, default=None, help="N (default 400,000 at 512^3, 1,400,000 at 1024^3, by voxels between)")
    ap.add_argument("--serial", action="store_true", help="also each bricking one brick at a time (the model must be the same)")
    ap.add_argument("--profile", default="", help="brickings whose first brick is profiled phase by phase")
    ap.add_argument("--split-cells", choices=("auto", "on", "off"), default="auto", help="the forward pass (RefineConfig.split_cells)")
    ap.add_argument("--together", default="", help="seam-refit shares for bricks started at once, comma list (0: no refit)")
    ap.add_argument("--no-waves", action="store_true", help="leave out the default schedule (the waves; with --together)")
    ap.add_argument("--device", default=None)
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    dev = resolve_device(args.device)
    split = {"auto": None, "on": True, "off": False}[args.split_cells]
    warpgauss.encode(generate("vortex", 24), budget=60, device=dev, iterations=3, samples=64, format="full", self_test=False)
    warpgauss.encode(
        generate("vortex", 24), budget=60, device=dev, iterations=3, samples=64, format="full", bricks="2x1x1", self_test=False
    )
    result = result_header("bricked encode on one GPU against the monolithic (format full, defaults otherwise)", __file__, argv, dev)
    result["rows"], result["profiles"] = [], []
    for size in [int(s) for s in args.sizes.split(",")]:
        n = args.budget or default_budget(size)
        for name in filter(None, args.fields.split(",")):
            t = time.perf_counter()
            v = generate(name, size)
            f = normalise(v)
            print(f"{name} {size}^3 generated in {time.perf_counter() - t:.1f} s", flush=True)
            kw = dict(budget=n, device=dev, format="full", self_test=False, evaluate=False)
            if split is not None:
                from warpgauss.encoding.refine import RefineConfig

                kw["refine"] = RefineConfig(split_cells=split)
            t = time.perf_counter()
            mono = warpgauss.encode(v, **kw)
            mono_s = time.perf_counter() - t
            base = psnr(f, mono, dev)
            row = {"field": name, "size": size, "n": n, "mode": "monolithic", "seconds": mono_s, "psnr_db": base}
            result["rows"].append(row)
            print(row, flush=True)
            del mono
            for bricks in filter(None, args.bricks.split(",")):
                if bricks in args.profile.split(","):
                    result["profiles"].append({"field": name, "size": size, **profile_brick(v, n, bricks, dev, split=split)})
                models = {}
                modes = ([] if args.no_waves else ["side by side"]) + (["serial"] if args.serial else [])
                modes += [f"together {x}" for x in filter(None, args.together.split(","))]
                most = wb.MAX_AT_ONCE
                for mode in modes:
                    wb.MAX_AT_ONCE = 1 if mode == "serial" else most
                    together = mode.startswith("together")
                    t = time.perf_counter()
                    with wsched.schedule(not together, float(mode.split()[1]) if together else 0.0):
                        m = warpgauss.encode(v, bricks=bricks, **kw)
                    secs = time.perf_counter() - t
                    p = psnr(f, m, dev)
                    br = m.report["bricking"]
                    row = {
                        "field": name,
                        "size": size,
                        "n": n,
                        "mode": "bricked",
                        "bricks": bricks,
                        "waves": "together" if together else "neighbours first",
                        "seam_refit": m.report["bricking"]["seam_refit"],
                        "at_once": max(b.get("at_once", 1) for b in br["bricks"]),
                        "seconds": secs,
                        "bricked_over_monolithic": secs / mono_s,
                        "psnr_db": p,
                        "dpsnr_db": p - base,
                        "halo": br["halo"],
                        "bricks_wall_s": br["wall_seconds"],
                        "brick_setup_s_sum": float(sum(b.get("setup_seconds") or 0 for b in br["bricks"])),
                        "brick_refine_s_sum": float(sum(b.get("refine_seconds") or 0 for b in br["bricks"])),
                        "brick_samples": sorted({b["samples"] for b in br["bricks"]}),
                    }
                    models[mode] = m.params
                    if mode == "serial":
                        row["same_model_as_side_by_side"] = bool(np.array_equal(models["serial"], models["side by side"]))
                    result["rows"].append(row)
                    print(row, flush=True)
                    args.out.write_text(json.dumps(result, indent=1))
                wb.MAX_AT_ONCE = most
            del v, f
    args.out.write_text(json.dumps(result, indent=1))
    print(f"wrote {args.out}")
    return result


if __name__ == "__main__":
    main()
