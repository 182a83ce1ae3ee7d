"""cProfile of one default encode (after a warm-up): where the host's time goes, sync waits
included (a ``numpy()`` that waits for the device shows as time in it), plus CUDA-event timings
of the CUB sorts and scans an iteration runs (Warp's activity timing does not see them).

    python benchmarks/speed/host_profile.py VOLUME.npy RATIO OUT.json
    python benchmarks/speed/host_profile.py interface@512 100 OUT.json   # an example field, NAME@SIZE
    python benchmarks/speed/host_profile.py VOLUME.npy 100 OUT.json 1.0  # with --time-budget 1.0
"""

from __future__ import annotations

import cProfile
import io
import json
import pstats
import sys
import time

import numpy as np

import warpgauss
from warpgauss.core.warp import resolve_device, warp
from warpgauss.encoding.bench import Timer, result_header
from warpgauss.readers.synthetic import generate

wp = warp()
dev = resolve_device(None)
vol, ratio, out = sys.argv[1], float(sys.argv[2]), sys.argv[3]
budget = float(sys.argv[4]) if len(sys.argv) > 4 else None
warpgauss.encode(generate("vortex", 32), ratio=10, device=dev)
res = {**result_header("host profile of one default encode", __file__, None, dev), "volume": vol, "ratio": ratio, "time_budget": budget}
if "@" in vol and not vol.endswith(".npy"):
    name, size = vol.split("@")
    source = generate(name, int(size))
else:
    source = vol
if budget is not None:  # a warm-up on the same path (the budget's probe steps run plain launches)
    warpgauss.encode(source, ratio=ratio, device=dev, time_budget=budget)
pr = cProfile.Profile()
t = time.perf_counter()
pr.enable()
m = warpgauss.encode(source, ratio=ratio, device=dev, time_budget=budget)
res["report"] = {k: m.report.get(k) for k in ("stages", "budget", "skipped")}
res["report"]["refinement"] = {k: v for k, v in m.report["refinement"].items() if k != "loss_history"}
pr.disable()
res["wall_s"] = time.perf_counter() - t
s = io.StringIO()
pstats.Stats(pr, stream=s).sort_stats("tottime").print_stats(35)
res["by_tottime"] = s.getvalue()
s = io.StringIO()
pstats.Stats(pr, stream=s).sort_stats("cumulative").print_stats(45)
res["by_cumulative"] = s.getvalue()
print(res["by_tottime"][-9000:])
print(res["by_cumulative"][-9000:])
T = Timer(dev)
cub = {}
for n in (131_072 * 5, 131_072, 300_000):
    k = wp.array(np.random.default_rng(0).integers(0, 1 << 20, 2 * n).astype(np.int32), dtype=int, device=dev)
    v = wp.zeros(2 * n, dtype=int, device=dev)
    cub[f"radix_sort_pairs_{n}_20bits_ms"] = T.ms(lambda k=k, v=v, n=n: wp.utils.radix_sort_pairs(k, v, n, 0, 20), 20)
    a = wp.zeros(n, dtype=wp.int64, device=dev)
    b = wp.zeros(n, dtype=wp.int64, device=dev)
    cub[f"array_scan_int64_{n}_ms"] = T.ms(lambda a=a, b=b: wp.utils.array_scan(a, b, inclusive=True), 20)
    a32 = wp.zeros(n, dtype=int, device=dev)
    b32 = wp.zeros(n, dtype=int, device=dev)
    cub[f"array_scan_int32_{n}_ms"] = T.ms(lambda a32=a32, b32=b32: wp.utils.array_scan(a32, b32, inclusive=True), 20)
res["cub_ms"] = cub
print(cub)
json.dump(res, open(out, "w"), indent=1)
