"""Run `bench kernels` of the baseline copy in .wk/base (same argv as the CLI's options)."""
import sys, json
base = sys.argv[1]
import importlib.util
spec = importlib.util.spec_from_file_location("warpgauss", f"{base}/warpgauss/__init__.py", submodule_search_locations=[f"{base}/warpgauss", base])
mod = importlib.util.module_from_spec(spec); sys.modules["warpgauss"] = mod; spec.loader.exec_module(mod)
from warpgauss.bench import KernelBenchConfig, run_kernel_bench, format_table
size = int(sys.argv[2]); ns = tuple(int(x) for x in sys.argv[3].split(",")); ms = tuple(int(x) for x in sys.argv[4].split(","))
cfg = KernelBenchConfig(size=size, ns=ns, samples=ms, decode=False, dense_max_n=0, atomic_baseline=False)
res = run_kernel_bench(cfg, "cuda:0")
print(format_table(res))
json.dump(res, open(sys.argv[5], "w"), indent=1)
