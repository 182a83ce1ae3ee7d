"""Kernels of one refinement iteration and a decode slab, for ncu (no graph)."""
import sys
import numpy as np
from warpgauss._warp import warp
from warpgauss.analysis import DeviceVolume
from warpgauss.bench import bench_field, bench_primitives
from warpgauss.optimize import RefineConfig, Refiner
from warpgauss.field import GaussianField
from warpgauss import bench as B
wp = warp()
import os
DEV = os.environ.get("DEV", "cuda:0")
size, n, m = int(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3])
f = bench_field(size)
dv = DeviceVolume(f, DEV)
r = Refiner(dv, bench_primitives(n, f.shape_xyz, 0.7, 0), RefineConfig(iterations=1000, samples=m, graph=False), 0, 0.3, max(2.0, size / 16))
for _ in range(3):
    r.step()
wp.synchronize()
print("stats", r.pair_pass_stats(), flush=True)
r.sample(); r.forward(); r.backward(); wp.synchronize()
if len(sys.argv) > 4:
    gf = GaussianField(r.model_params(), f.shape_xyz, device=DEV)
    B._decode_on_device(gf)
    wp.synchronize()
