"""Where a bricked encode's time goes on one GPU: one refinement step of a brick against the
monolithic refiner's, by samples per step, and the bricks of one wave stepped one after another
against side by side (a CUDA stream each).

For the field at ``--size`` and N: the monolithic refiner and the first wave's bricks of each
bricking, set up as the encode sets them up; then
- ``samples``: ms per step (device synchronised) of the monolithic refiner and of the first brick of
  each bricking at several samples per step (the cost as fixed + per-sample parts);
- ``host``: ms the host takes to enqueue one captured step (no synchronisation);
- ``wave``: the first wave's bricks (``--together``: every brick, as when they start at once), ``--steps`` steps each, one brick after another and then side
  by side (round robin, a stream each): ms per step of the wave.

    python benchmarks/bricked/profile_wave.py --size 512 --bricks 2x2x2,4x4x4,1x1x4 --out $OUT/profile_wave_512_h200.json
"""

from __future__ import annotations

import argparse
import contextlib
import json
import time
from pathlib import Path

import numpy as np

import warpgauss.encoding.scale.bricks as wb
import warpgauss.encoding.scale.plan as bp
from warpgauss.core.profiling import StageRecorder
from warpgauss.core.warp import warp
from warpgauss.encoding.allocate import AllocationConfig, allocate
from warpgauss.encoding.bench import result_header, warmed_device
from warpgauss.encoding.refine import RefineConfig, Refiner
from warpgauss.encoding.scale import schedule as wsched
from warpgauss.field.analysis import DeviceVolume, normalise
from warpgauss.readers.synthetic import generate


def brick_refiner(task, dev: str) -> Refiner:
    """The refiner :func:`warpgauss.encoding.scale.bricks.brick_job` builds for ``task``."""
    return wb.brick_refiner(task, dev)[1]


def scoped(wp, stream):
    """``stream`` current for a block (nothing on the CPU)."""
    return contextlib.nullcontext() if stream is None else wp.ScopedStream(stream, sync_enter=False)


def ms_per_step(wp, dev, steppers, steps: int) -> float:
    """Wall ms per round of ``steppers`` (each a callable doing one step), device synchronised."""
    wp.synchronize_device(dev)
    t = time.perf_counter()
    for _ in range(steps):
        for s in steppers:
            s()
    wp.synchronize_device(dev)
    return (time.perf_counter() - t) / steps * 1e3


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--field", default="vortex")
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--budget", type=int, default=400_000)
    ap.add_argument("--bricks", default="2x2x2,4x4x4,1x1x4")
    ap.add_argument("--samples", default="3000,10000,20000,40000,80000,131072")
    ap.add_argument("--steps", type=int, default=60)
    ap.add_argument("--split-cells", choices=("auto", "on", "off"), default="auto", help="the forward pass (RefineConfig.split_cells)")
    ap.add_argument("--together", action="store_true", help="the wave is every brick, started at once (bricked.schedule(False))")
    ap.add_argument("--waves-only", action="store_true", help="leave out the samples sweeps (monolithic and first brick)")
    ap.add_argument("--device", default=None)
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    wp = warp()
    dev = warmed_device(args.device)
    out = result_header("one brick's step against the monolithic step, and a wave side by side", __file__, argv, dev)
    out.update(field=args.field, size=args.size, n=args.budget, samples=[], host=[], waves=[])
    f = normalise(generate(args.field, args.size))
    n = args.budget
    sweep = [int(s) for s in args.samples.split(",")]

    def samples_rows(label: str, r: Refiner, box) -> None:
        for _ in range(12):
            r.step()
        for m in sweep:
            r.set_samples(m)
            for _ in range(3):
                r.step()
            row = {"what": label, "box": box, "primitives": r.n, "samples": m, "ms": ms_per_step(wp, dev, [r.step], args.steps)}
            out["samples"].append(row)
            print(row, flush=True)
        wp.synchronize_device(dev)
        t = time.perf_counter()
        for _ in range(args.steps):
            r.step()
        host = (time.perf_counter() - t) / args.steps * 1e3
        wp.synchronize_device(dev)
        out["host"].append({"what": label, "host_ms_per_step": host})
        print(out["host"][-1], flush=True)
        args.out.write_text(json.dumps(out, indent=1))

    a = AllocationConfig()
    dv = DeviceVolume(f, dev)
    params, _ = allocate(dv, n, 0, a, StageRecorder())
    base = RefineConfig(split_cells={"auto": None, "on": True, "off": False}[args.split_cells])
    cfg = base.for_budget(n, int(np.prod(f.shape_xyz)), dev)
    if not args.waves_only:
        mono = Refiner(dv, np.asarray(params, np.float32), cfg, 0, a.scale_min, a.resolved_cap(f.shape_xyz))
        samples_rows("monolithic", mono, list(f.shape_xyz))
        del mono
    del dv
    for bricks in filter(None, args.bricks.split(",")):
        alloc = AllocationConfig(scale_cap=bp.brick_cap(a.resolved_cap(f.shape_xyz), f.shape_xyz, n))
        plan = bp.plan_bricks(f.shape_xyz, bp.parse_bricks(bricks), bp.default_halo(alloc.scale_cap))
        _, stats = bp.split_bricks(f, plan, n)
        tasks = wb.brick_tasks(f, plan, stats, 0, alloc, base, dev, n)
        with wsched.schedule(not args.together):
            wave = [t.index for t in tasks if wsched.brick_wave(t.brick) == 0]
            batch = wsched.wave_tasks(tasks, {}, wave)
        if not args.waves_only:
            first = brick_refiner(batch[0], dev)
            samples_rows(f"brick of {bricks}", first, [hi - lo for lo, hi in batch[0].brick.box])
            del first
        cuda = wp.get_device(dev).is_cuda
        streams = [wp.Stream(dev) if cuda else None for _ in batch]
        refiners = []
        for t, s in zip(batch, streams):
            with scoped(wp, s):
                refiners.append(brick_refiner(t, dev))
                for _ in range(12):
                    refiners[-1].step()
        wp.synchronize_device(dev)

        def on(r, s):
            def step():
                with scoped(wp, s):
                    r.step()

            return step

        serial = sum(ms_per_step(wp, dev, [on(r, s)], args.steps) for r, s in zip(refiners, streams))
        side = ms_per_step(wp, dev, [on(r, s) for r, s in zip(refiners, streams)], args.steps)
        row = {
            "bricks": bricks,
            "together": args.together,
            "forward_pass": refiners[0].forward_pass,
            "wave_bricks": len(batch),
            "samples": [t.refine.samples for t in batch],
            "one_after_another_ms": serial,
            "side_by_side_ms": side,
            "gain": serial / side,
        }
        out["waves"].append(row)
        print(row, flush=True)
        args.out.write_text(json.dumps(out, indent=1))
        del refiners
    args.out.write_text(json.dumps(out, indent=1))
    return out


if __name__ == "__main__":
    main()
