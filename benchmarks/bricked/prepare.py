"""The host work of a brick's start (its box cut and copied, the interior, halo and training
masks and their seed-candidate counts: ``warpgauss.encoding.scale.bricks.prepare_brick``) for every brick of a
bricking started together, one brick after another against ``--threads`` threads (whether
bricks side by side would gain from cutting their boxes on threads ahead of their start). Host work only: it runs the same on any machine,
with or without a GPU; the JSON names the cores.

    python benchmarks/bricked/prepare.py --size 384 --bricks 2x2x2 --threads 2 --out benchmarks/results/bricked/prepare_384_cpu.json
"""

from __future__ import annotations

import argparse
import json
import os
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import warpgauss.encoding.scale.bricks as wb
import warpgauss.encoding.scale.plan as bp
from warpgauss.encoding.allocate import AllocationConfig
from warpgauss.encoding.bench import result_header
from warpgauss.encoding.refine import RefineConfig
from warpgauss.encoding.scale import schedule as wsched
from warpgauss.field.analysis import normalise
from warpgauss.readers.synthetic import generate


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--field", default="vortex")
    ap.add_argument("--size", type=int, default=384)
    ap.add_argument("--bricks", default="2x2x2")
    ap.add_argument("--budget", type=int, default=200_000)
    ap.add_argument("--threads", default="2", help="comma list of thread counts")
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    out = result_header("a brick's host set-up, one brick after another against threads", __file__, argv, "cpu")
    out.update(field=args.field, size=args.size, bricks=args.bricks, cores=os.cpu_count(), rows=[])
    f = normalise(generate(args.field, args.size))
    alloc = AllocationConfig()
    alloc = AllocationConfig(scale_cap=bp.brick_cap(alloc.resolved_cap(f.shape_xyz), f.shape_xyz, args.budget))
    plan = bp.plan_bricks(f.shape_xyz, bp.parse_bricks(args.bricks), bp.default_halo(alloc.scale_cap))
    _, stats = bp.split_bricks(f, plan, args.budget)
    tasks = wb.brick_tasks(f, plan, stats, 0, alloc, RefineConfig(), "cpu", args.budget)
    with wsched.schedule(False):
        tasks = wsched.wave_tasks(tasks, {}, [t.index for t in tasks])

    def serial() -> None:
        for t in tasks:
            wb.prepare_brick(t)

    def threaded(k: int):
        def run() -> None:
            with ThreadPoolExecutor(max_workers=k) as pool:
                list(pool.map(wb.prepare_brick, tasks))

        return run

    def best(fn) -> float:
        times = []
        for _ in range(args.repeats):
            t = time.perf_counter()
            fn()
            times.append(time.perf_counter() - t)
        return min(times)

    base = best(serial)
    out["rows"].append({"threads": 1, "seconds": base, "speedup": 1.0, "box_voxels": tasks[0].brick.box_voxels})
    print(out["rows"][-1], flush=True)
    for k in (int(x) for x in args.threads.split(",") if x.strip()):
        sec = best(threaded(k))
        out["rows"].append({"threads": k, "seconds": sec, "speedup": base / sec})
        print(out["rows"][-1], flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(out, indent=1))
    return out


if __name__ == "__main__":
    main()
