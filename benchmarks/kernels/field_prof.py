"""Per-kernel GPU time of refinement iterations on an example field (Warp activity timing, no
graph), the pair-pass statistics, and a real run's CPU-side time per step (where the host waits).

    python3 benchmarks/kernels/field_prof.py FIELD SIZE N SAMPLES OUT.json [RUN_ITERATIONS]
"""

import json
import sys
import time
from collections import defaultdict

import numpy as np

from warpgauss.core.profiling import StageRecorder
from warpgauss.core.warp import warp
from warpgauss.encoding.allocate import AllocationConfig, allocate
from warpgauss.encoding.bench import result_header
from warpgauss.encoding.refine import RefineConfig, Refiner
from warpgauss.field.analysis import DeviceVolume, normalise
from warpgauss.readers.synthetic import generate

wp = warp()
dev = "cuda:0" if wp.get_cuda_device_count() else "cpu"
name, size, n, m, out = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4]), sys.argv[5]
f = normalise(generate(name, size, seed=0))
dv = DeviceVolume(f, dev)
ac = AllocationConfig()
params, _ = allocate(dv, n, 0, ac, StageRecorder())
cap = ac.resolved_cap(f.shape_xyz)
res = {**result_header("refinement by kernel on an example field", __file__, None, dev), "field": name, "size": size, "n": n, "samples": m}
r = Refiner(dv, params, RefineConfig(iterations=1500, samples=m), 0, ac.scale_min, cap)
r.use_graph = False
for _ in range(25):
    r.step()
wp.synchronize()
res["plan_sizes"] = [float(s) for s in r.plan.sizes]
res["pair_pass"] = {k: (float(v) if not isinstance(v, (list, tuple)) else list(v)) for k, v in r.pair_pass_stats().items()}
pb = r.passes.buffers()
res["point_grid_sizes"] = [float(s) for s in pb["grid_plan"].sizes]
rad = r.binner.prep[4].numpy()
res["radius_quantiles"] = [float(q) for q in np.quantile(rad[np.isfinite(rad)], [0, 0.5, 0.9, 0.99, 1.0])]
steps = 10
wp.timing_begin(cuda_filter=wp.TIMING_KERNEL | wp.TIMING_MEMCPY | wp.TIMING_MEMSET)
for _ in range(steps):
    r.step()
results = wp.timing_end()
per = defaultdict(float)
for t in results:
    per[t.name] += t.elapsed / steps
res["kernel_ms_per_step"] = dict(sorted(per.items(), key=lambda kv: -kv[1]))
res["kernel_ms_per_step_total"] = sum(per.values())
for k, v in list(res["kernel_ms_per_step"].items())[:12]:
    print(f"{v:9.3f} ms  {k}")
print("total", res["kernel_ms_per_step_total"])
# a real run: host-side time of each step (no sync), plan changes and graph captures
r2 = Refiner(dv, params, RefineConfig(iterations=int(sys.argv[6]) if len(sys.argv) > 6 else 1500, samples=m), 0, ac.scale_min, cap)
marks = []
last = [time.perf_counter(), r2.plan]
late = defaultdict(float)


def after(rr):
    if rr.iteration == 1000:  # per-kernel time late in the run (plain launches for the timing)
        rr.use_graph = False
        wp.timing_begin(cuda_filter=wp.TIMING_KERNEL | wp.TIMING_MEMCPY | wp.TIMING_MEMSET)
    elif rr.iteration == 1100:
        for t in wp.timing_end():
            late[t.name] += t.elapsed / 100
        rr.use_graph = True
    t = time.perf_counter()
    marks.append((rr.iteration, 1000 * (t - last[0]), rr.plan is not last[1], rr._graph is None))
    last[0], last[1] = t, rr.plan


wp.synchronize()
t0 = time.perf_counter()
r2.run(after_step=after)
wp.synchronize()
res["run_seconds"] = time.perf_counter() - t0
host = np.array([x[1] for x in marks])
res["run_host_ms_median"] = float(np.median(host))
res["run_plan_changes"] = int(sum(x[2] for x in marks))
res["run_slowest_steps"] = sorted(marks, key=lambda x: -x[1])[:12]
res["late_kernel_ms_per_step"] = dict(sorted(late.items(), key=lambda kv: -kv[1]))
res["late_kernel_ms_per_step_total"] = sum(late.values())
for k, v in list(res["late_kernel_ms_per_step"].items())[:12]:
    print(f"late {v:9.3f} ms  {k}")
print("late total", res["late_kernel_ms_per_step_total"])
for k in (
    "plan_sizes",
    "point_grid_sizes",
    "radius_quantiles",
    "pair_pass",
    "run_seconds",
    "run_host_ms_median",
    "run_plan_changes",
    "run_slowest_steps",
):
    print(k, res[k])
json.dump(res, open(out, "w"), indent=1)
