"""The decode/refinement grid's ROW_COST (cost of visiting one row of point cells, in candidate-point
tests) swept over 1, 4, 16, 64: forward and backward times of the bench's models at 256^3 (N 2,000)
and 1024^3 (N 1.4M) on CUDA (what set ``warpgauss.field.gaussians.ROW_COST`` = 16).

    python3 benchmarks/kernels/row_cost.py $OUT/row_cost_h100.json
"""

import json
import sys

import warpgauss.field.gaussians as fld
from warpgauss.encoding.bench import KernelBenchConfig, result_header, run_kernel_bench

out: dict = {**result_header("ROW_COST sweep of the kernels", __file__, None, "cuda:0")}
for rc in (1.0, 4.0, 16.0, 64.0):
    fld.ROW_COST = rc
    for size, ns, ms in ((256, (2000,), (307200,)), (1024, (1400000,), (1048576,))):
        cfg = KernelBenchConfig(size=size, ns=ns, samples=ms, decode=False, dense_max_n=0, atomic_baseline=False, repeat=5)
        res = run_kernel_bench(cfg, "cuda:0", log=lambda s: None)
        r = res["rows"][0]
        print(
            f"row_cost {rc:5.1f} N {ns[0]:>8} fwd {r['forward_ms']:7.2f} bwd {r['backward_ms']:7.2f} cells {r['point_cells']} cand/pair {r['backward_candidates_per_pair']:.2f} chunk {r['backward_chunk_size']} Gp/s {r['gpairs_per_s']:.2f}",
            flush=True,
        )
        out[f"{rc}_{ns[0]}"] = r
json.dump(out, open(sys.argv[1], "w"), indent=1)
