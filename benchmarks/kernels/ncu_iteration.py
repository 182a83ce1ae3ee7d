"""Kernels of one refinement iteration and a decode slab, for Nsight Compute (no CUDA graph), on the
bench's field and primitives:

    ncu --csv --page raw -o ... python3 benchmarks/kernels/ncu_iteration.py SIZE N SAMPLES [decode]

(``results/kernels/ncu_iteration_{2000,1400000}_h100.csv``: 256^3 N 2,000 and 1024^3 N 1.4M.)
"""

import os
import sys

from warpgauss.core.warp import warp
from warpgauss.encoding import bench as B
from warpgauss.encoding.bench import bench_field, bench_primitives
from warpgauss.encoding.refine import RefineConfig, Refiner
from warpgauss.field.analysis import DeviceVolume
from warpgauss.field.gaussians import GaussianField

wp = warp()
DEV = os.environ.get("DEV", "cuda:0")
size, n, m = int(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3])
f = bench_field(size)
dv = DeviceVolume(f, DEV)
r = Refiner(
    dv, bench_primitives(n, f.shape_xyz, 0.7, 0), RefineConfig(iterations=1000, samples=m, graph=False), 0, 0.3, max(2.0, size / 16)
)
for _ in range(3):
    r.step()
wp.synchronize()
print("stats", r.pair_pass_stats(), flush=True)
r.sample()
r.forward()
r.backward()
wp.synchronize()
if len(sys.argv) > 4:
    gf = GaussianField(r.model_params(), f.shape_xyz, device=DEV)
    B._decode_on_device(gf)
    wp.synchronize()
