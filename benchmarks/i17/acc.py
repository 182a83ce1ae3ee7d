"""PSNR and refinement seconds of the four example fields (base copy or this tree)."""
import sys, json, time
which, out = sys.argv[1], sys.argv[2]
size, n = int(sys.argv[3]), int(sys.argv[4])
if which != "new":
    import importlib.util
    spec = importlib.util.spec_from_file_location("warpgauss", f"{which}/warpgauss/__init__.py", submodule_search_locations=[f"{which}/warpgauss", which])
    mod = importlib.util.module_from_spec(spec); sys.modules["warpgauss"] = mod; spec.loader.exec_module(mod)
import warpgauss
from warpgauss.synthetic import generate
dev = sys.argv[5] if len(sys.argv) > 5 else "cuda:0"
res = {}
for f in ("vortex", "bubbles", "turbulence", "interface"):
    t = time.time()
    m = warpgauss.encode(generate(f, size), budget=n, device=dev, seed=0)
    rep = m.report
    ev = rep["evaluation"]
    st = {s["stage"]: s["seconds"] for s in rep["stages"]}
    res[f] = {"analytic_db": ev["analytic"]["psnr_db"], "final_db": ev["final"]["psnr_db"], "wall_s": time.time() - t, "refine_s": st.get("S2")}
    print(which, f, res[f], flush=True)
json.dump(res, open(out, "w"), indent=1)
