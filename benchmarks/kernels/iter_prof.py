"""Where a refinement iteration's time goes beyond the kernels: the re-bin's parts (CUDA events),
per-step wall times over 200 steps (re-bins every 10, re-plans every 100), and a real run's
ms/iteration (Refiner.run) against the bench's step median.

    python3 benchmarks/kernels/iter_prof.py SIZE N SAMPLES OUT.json
"""

import json
import sys
import time

import numpy as np

from warpgauss.core.warp import warp
from warpgauss.encoding.bench import Timer, bench_field, bench_primitives, result_header
from warpgauss.encoding.refine import RefineConfig, Refiner
from warpgauss.field.analysis import DeviceVolume

wp = warp()
dev = "cuda:0" if wp.get_cuda_device_count() else "cpu"
size, n, m, out = int(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3]), sys.argv[4]
f = bench_field(size)
dv = DeviceVolume(f, dev)
r = Refiner(dv, bench_primitives(n, f.shape_xyz, 0.7, 0), RefineConfig(iterations=1500, samples=m), 0, 0.3, max(2.0, size / 16))
T = Timer(dev)
for _ in range(20):
    r.step()
wp.synchronize()
p = r.prims
parts = {
    "prepare+radius": r.binner.prepare,
    "sort_into_cells": r.binner.sort,
    "global_members (sync)": r.binner.global_members,
    "slot_cells": r.binner.slot_cells,
    "zero_grads": r.state.zero_grads,
    "mark_support": lambda: r.sampler.mark_support(r.binner.prep[0], r.binner.prep[3]),
    "rebin": r.rebin,
    "rebin+replan": lambda: r.rebin(replan=True),
}
res = {
    **result_header("where a refinement iteration's time goes beyond the kernels", __file__, None, dev),
    "size": size,
    "n": n,
    "samples": m,
    "uniform_support": bool(r.uniform_support),
    "parts_ms": {},
}
for k, fn in parts.items():
    res["parts_ms"][k] = T.ms(fn, 10)
    res["parts_ms"][k + " wall"] = T.wall_ms(fn, 10)
r.rebin(replan=True)
each = T.each_ms(r.step, 200)
res["step_ms_median"] = float(np.median(each))
res["step_ms_mean_200"] = float(np.mean(each))
res["step_ms_max"] = float(np.max(each))
res["step_ms_top5"] = sorted(each)[-5:]
r2 = Refiner(dv, bench_primitives(n, f.shape_xyz, 0.7, 0), RefineConfig(iterations=1500, samples=m), 0, 0.3, max(2.0, size / 16))
wp.synchronize()
t0 = time.perf_counter()
info = r2.run()
wp.synchronize()
res["run_seconds"] = time.perf_counter() - t0
res["run_iterations"] = r2.iteration
res["run_ms_per_iteration"] = 1000 * res["run_seconds"] / max(r2.iteration, 1)
res["run_over_step_median"] = res["run_ms_per_iteration"] / res["step_ms_median"]
for k, v in res.items():
    print(k, v)
json.dump(res, open(out, "w"), indent=1)
