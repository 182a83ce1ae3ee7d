"""Quantisation-aware refinement by refitting: at 80 % of 600 iterations the centres, scales and
rotations move onto the coded grids and stay; a and w are refitted to them; then everything is
stored on the grids. Full-grid PSNR of the stored model (compare with the float32 model's and the
single projection's in i18_coded_cpu.json).

    python3 benchmarks/i18/refit.py VOLUME N OUT.wgs
"""
import json
import sys
import time

import warpgauss
from warpgauss.coded import CODED_BITS
from warpgauss.refine import RefineConfig

vol, n, out = sys.argv[1], int(sys.argv[2]), sys.argv[3]
t = time.time()
m = warpgauss.encode(vol, budget=n, iterations=600, device="cpu", format="coded", output=out, force=True, evaluate=False, self_test=False,
                     refine=RefineConfig(quantise=dict(CODED_BITS), quantise_from=0.8, quantise_mode="refit"))
p = warpgauss.psnr(m, vol, full=True, device="cpu")
print(json.dumps({"volume": vol, "n": n, "scheme": "refit a and w after fixing the geometry at 80 %", "psnr_full_db": p,
                  "bits": m.coded_bits, "bytes": m.report["budget"]["bytes"], "seconds": time.time() - t}), flush=True)
