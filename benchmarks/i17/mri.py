import json, sys
out = {}
for tag, path in zip(sys.argv[1::2], sys.argv[2::2]):
    r = json.load(open(path))
    st = {s["stage"]: s["seconds"] for s in r["stages"]}
    ref = r.get("refinement", {})
    out[tag] = {"n": r.get("n") or r.get("budget", {}).get("n"), "final_psnr_db": r["evaluation"]["final"]["psnr_db"], "analytic_psnr_db": r["evaluation"]["analytic"]["psnr_db"],
                "refine_s": st.get("S2"), "iterations": ref.get("iterations"), "samples": ref.get("samples"), "device": r.get("device_name"), "warp": r.get("warp_version")}
    print(tag, out[tag], flush=True)
json.dump(out, open(sys.argv[-1] if len(sys.argv) % 2 == 0 else "/dev/null", "w"), indent=1)
