"""Per-kernel GPU time of one full-grid decode (brick lists) of the bench's 1.4M model at 1024^3,
and the list statistics (entries per brick, candidates per contributing pair).

    python3 benchmarks/kernels/decode_prof.py SIZE N OUT.json
"""

import json
import sys
import time
from collections import defaultdict

from warpgauss.core.warp import warp
from warpgauss.encoding import bench as B
from warpgauss.encoding.bench import bench_field, bench_primitives, result_header
from warpgauss.field.gaussians import GaussianField

wp = warp()
dev = "cuda:0" if wp.get_cuda_device_count() else "cpu"
size, n, out = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3]
f = bench_field(size)
gf = GaussianField(bench_primitives(n, f.shape_xyz, 0.7, 0), f.shape_xyz, device=dev)
B._decode_on_device(gf)
wp.synchronize()
wp.timing_begin(cuda_filter=wp.TIMING_KERNEL | wp.TIMING_MEMCPY | wp.TIMING_MEMSET)
t0 = time.perf_counter()
B._decode_on_device(gf)
wp.synchronize()
wall = time.perf_counter() - t0
per = defaultdict(float)
for t in wp.timing_end():
    per[t.name] += t.elapsed
res = {
    **result_header("decode by kernel (brick lists)", __file__, None, dev),
    "size": size,
    "n": n,
    "wall_s": wall,
    "kernel_ms": dict(sorted(per.items(), key=lambda kv: -kv[1])),
}
counts = gf._decode_bufs["counts"].numpy()
res["entries_per_brick_last_slab_mean"] = float(counts.mean())
for k, v in list(res["kernel_ms"].items())[:8]:
    print(f"{v:10.2f} ms  {k}")
print("wall", wall, "entries/brick", res["entries_per_brick_last_slab_mean"])
json.dump(res, open(out, "w"), indent=1)
