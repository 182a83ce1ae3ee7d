# after the Refiner split: graph capture and stage times unchanged (256^3), H100
bash .gpu/setup.sh 2>/dev/null || { ls /tmp/site/warp/bin/warp.so >/dev/null || exit 1; }
export PYTHONPATH=/tmp/site PYTHONUNBUFFERED=1
python3 -m pip install -q --no-deps --no-build-isolation --no-index -e . 2>&1 | tail -2
warpgauss bench kernels --size 256 --n 2000,12000,60000 --samples 3072,307200 --no-decode --dense-max-n 0 --json-out $OUT/k256_split.json --force 2>&1 | tail -9
python3 - <<'PY'
import numpy as np, warpgauss
from warpgauss.synthetic import generate
vol = generate("vortex", 96, seed=0)
a = warpgauss.encode(vol, budget=6000, iterations=120, device="cuda:0", evaluate=False)
b = warpgauss.encode(vol, budget=6000, iterations=120, device="cuda:0", evaluate=False)
print("cuda rerun bit-identical:", a.params.tobytes() == b.params.tobytes(), "graph:", a.report["refinement"].get("cuda_graph"), a.report["refinement"].get("cuda_graph_error"))
PY
