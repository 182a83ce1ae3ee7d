"""Encode a volume with --format coded, quantisation-aware over the last fifth of 600 iterations.

    python3 benchmarks/i18/qat.py VOLUME N {s4_a6w5,s4_a7w5,old} OUT.wgs
"""
import sys, json, time, warpgauss
from warpgauss import coded
from warpgauss.refine import RefineConfig
vol, n, bits_name, out = sys.argv[1], int(sys.argv[2]), sys.argv[3], sys.argv[4]
B = {"s4_a6w5": {"mu": 2, "log_s": 4, "q": 5, "a": 6, "w": 5}, "s4_a7w5": {"mu": 2, "log_s": 4, "q": 5, "a": 7, "w": 5}, "old": {"mu": 3, "log_s": 4, "q": 6, "a": 8, "w": 7}}[bits_name]
coded.CODED_BITS.clear(); coded.CODED_BITS.update(B)
t = time.time()
# quantisation-aware over the last fifth (the runs recorded in i18_coded_cpu.json: the straight-through
# ones; the "projection at every re-bin" rows came from an earlier form of the refiner)
m = warpgauss.encode(vol, budget=n, iterations=600, device="cpu", format="coded", output=out, force=True, evaluate=False, self_test=False,
                     refine=RefineConfig(quantise=B, quantise_from=0.8))
p = warpgauss.psnr(m, vol, full=True, device="cpu")
print(json.dumps({"volume": vol, "n": n, "bits": B, "qat_psnr_full_db": p, "bytes": m.report["budget"]["bytes"], "bytes_per_primitive": m.report["budget"]["bytes_per_primitive"], "seconds": time.time() - t}), flush=True)
