"""More Gaussians at coarser grids or fewer at finer ones, at one byte budget: the coded format's
default depths shifted by -1 / 0 / +1 bit on every attribute (N follows from the pilot), 600
iterations on the CPU, full-grid PSNR.

    python3 benchmarks/rate_distortion/precision_vs_count.py VOLUME RATIO OUT.json
"""

import json
import sys
import time

import warpgauss
from warpgauss.encoding.bench import result_header
from warpgauss.format import coded

vol, ratio, out = sys.argv[1], float(sys.argv[2]), sys.argv[3]
base = dict(coded.CODED_BITS)
rows = []
for shift in (-1, 0, 1):
    coded.CODED_BITS.clear()
    coded.CODED_BITS.update({k: max(v + shift, 1) for k, v in base.items()})
    t = time.time()
    m = warpgauss.encode(vol, ratio=ratio, iterations=600, device="cpu", self_test=False, full_eval=True)
    b = m.report["budget"]
    rows.append(
        {
            "shift": shift,
            "start_bits": dict(coded.CODED_BITS),
            "n": b["n"],
            "bytes": b["bytes"],
            "budget_used": b["budget_used"],
            "bytes_per_primitive": b["bytes_per_primitive"],
            "fit": b["coded_fit"],
            "psnr_full_db": m.report["psnr_db"],
            "seconds": time.time() - t,
        }
    )
    print(rows[-1], flush=True)
json.dump(
    {
        **result_header("coded: precision against primitive count at one byte budget (CPU, 600 iterations)", __file__, None, "cpu"),
        "volume": vol,
        "ratio": ratio,
        "rows": rows,
    },
    open(out, "w"),
    indent=1,
)
