import sys, warpgauss
from warpgauss import coded
from warpgauss.model import Model
B = {"mu": 2, "log_s": 4, "q": 5, "a": 6, "w": 5}
for vol, n, ref in [("mni_icbm152_t1_tal_nlin_sym_09a_converted.nii.gz", 10000, "mni"), ("inia19-t1-brain.nii.gz", 20000, "inia"), ("mean_reg2mean.nii.gz", 25000, "mean"), ("nAChR_M2_water.plt", 3000, "water")]:
    a = warpgauss.encode("/work/shared/data/" + vol, budget=n, iterations=0, device="cpu", evaluate=False)
    r = Model.load(f"/tmp/q/{ref}.wgs")
    pa, _, _ = coded.encode_coded(a.params, B)
    pr, _, _ = coded.encode_coded(r.params, B)
    print(f"{ref:6s} N {n}: analytic {len(pa)/n:.3f} B/prim, refined {len(pr)/n:.3f} B/prim, ratio {len(pr)/len(pa):.3f}", flush=True)
