"""Where a brick's start goes: every brick of a bricking started together (the default schedule on
one GPU), set up one after another as ``warpgauss.encoding.scale.bricks.brick_refiner`` sets it up, each phase
timed with the device synchronised: the box cut, masks and seed-candidate counts on the host (Bh),
the uploads (Bu), each allocation's stages (S1b-S1e, the brick's own and its stand-ins'), the
stand-in count on the host (Bs), the refiner's set-up (Br) and its first step (the graph capture).
With ``--cprofile`` the first brick's start again under cProfile, each launch synchronised
(``warp.config.verify_cuda``), its largest functions by cumulative time.

    python benchmarks/bricked/setup_profile.py --size 1024 --bricks 2x2x2 --out $OUT/setup_profile_1024_h200.json
"""

from __future__ import annotations

import argparse
import cProfile
import json
import pstats
import time
from pathlib import Path

import warpgauss.encoding.scale.bricks as wb
import warpgauss.encoding.scale.plan as bp
from warpgauss.core.profiling import StageRecorder
from warpgauss.core.warp import warp
from warpgauss.encoding.allocate import AllocationConfig
from warpgauss.encoding.bench import result_header, warmed_device
from warpgauss.encoding.refine import RefineConfig
from warpgauss.encoding.scale import schedule as wsched
from warpgauss.field.analysis import normalise
from warpgauss.readers.synthetic import generate


def together_tasks(f, bricks: str, n: int, dev: str) -> list:
    """The bricks' tasks as the encode makes them when every brick starts at once."""
    alloc = AllocationConfig()
    alloc = AllocationConfig(scale_cap=bp.brick_cap(alloc.resolved_cap(f.shape_xyz), f.shape_xyz, n))
    plan = bp.plan_bricks(f.shape_xyz, bp.parse_bricks(bricks), bp.default_halo(alloc.scale_cap))
    _, stats = bp.split_bricks(f, plan, n)
    tasks = wb.brick_tasks(f, plan, stats, 0, alloc, RefineConfig(), dev, n)
    with wsched.schedule(False):
        return wsched.wave_tasks(tasks, {}, [t.index for t in tasks])


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--field", default="vortex")
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--budget", type=int, default=None, help="N (default 400,000 at 512^3, by voxels beyond)")
    ap.add_argument("--bricks", default="2x2x2")
    ap.add_argument("--cprofile", action="store_true", help="also the first brick's start under cProfile")
    ap.add_argument("--device", default=None)
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    wp = warp()
    dev = warmed_device(args.device)
    n = args.budget or int(round(400_000 * (args.size / 512) ** 3))
    out = result_header("a brick's start phase by phase (bricks started together)", __file__, argv, dev)
    out.update(field=args.field, size=args.size, n=n, bricks=args.bricks, rows=[], cprofile=[])
    t = time.perf_counter()
    f = normalise(generate(args.field, args.size))
    t_gen = time.perf_counter() - t
    t = time.perf_counter()
    tasks = together_tasks(f, args.bricks, n, dev)
    out.update(generate_s=t_gen, tasks_s=time.perf_counter() - t)
    print(f"{args.field} {args.size}^3: generated {t_gen:.1f} s, tasks {out['tasks_s']:.1f} s", flush=True)
    for task in tasks:
        timer = StageRecorder(device=dev)
        wp.synchronize_device(dev)
        t = time.perf_counter()
        _, r, k = wb.brick_refiner(task, dev, timer)
        wp.synchronize_device(dev)
        setup = time.perf_counter() - t
        t = time.perf_counter()
        r.step()
        wp.synchronize_device(dev)
        phases: dict[str, float] = {}
        for s in timer.stages:
            phases[s.name] = phases.get(s.name, 0.0) + s.seconds
        row = {
            "brick": task.index,
            "box_voxels": task.brick.box_voxels,
            "n": task.n,
            "stand_ins": k,
            "setup_s": setup,
            "first_step_s": time.perf_counter() - t,
            "phases_s": phases,
        }
        out["rows"].append(row)
        print(row, flush=True)
        del r
    if args.cprofile:
        prof = cProfile.Profile()
        wp.config.verify_cuda = True
        prof.enable()
        _, r, _ = wb.brick_refiner(tasks[0], dev)
        wp.synchronize_device(dev)
        prof.disable()
        wp.config.verify_cuda = False
        st = pstats.Stats(prof)
        top = sorted(st.stats.items(), key=lambda kv: -kv[1][3])[:40]  # type: ignore[attr-defined]
        out["cprofile"] = [
            {"function": f"{k[0].split('/')[-1]}:{k[1]}:{k[2]}", "calls": v[1], "cum_s": v[3], "own_s": v[2]} for k, v in top
        ]
        for row in out["cprofile"]:
            print(row, flush=True)
    sums: dict[str, float] = {}
    for row in out["rows"]:
        for name, sec in row["phases_s"].items():
            sums[name] = sums.get(name, 0.0) + sec
    out["phase_sums_s"] = sums
    out["setup_sum_s"] = sum(r["setup_s"] for r in out["rows"])
    print("sums", sums, "setup", out["setup_sum_s"], flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(out, indent=1))
    return out


if __name__ == "__main__":
    main()
