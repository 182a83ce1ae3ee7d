# after the parallel cell-start table: paper/fast presets at 1024^3, interface profile, 256^3 kernels + decode
bash .gpu/setup.sh 2>/dev/null || { ls /tmp/site/warp/bin/warp.so >/dev/null || exit 1; }
export PYTHONPATH=/tmp/site PYTHONUNBUFFERED=1
python3 -m pip install -q --no-deps --no-build-isolation --no-index -e . 2>&1 | tail -2
python3 benchmarks/bench_refine.py --size 1024 --budget 1400000 --fields vortex,interface,bubbles --presets paper,fast --out $OUT/refine1024.json 2>&1 | tail -9
python3 benchmarks/i17/field_prof.py interface 1024 1400000 3072 $OUT/prof_interface1024.json 1500 2>&1 | tail -22
warpgauss bench kernels --size 256 --n 2000,12000,60000 --samples 307200 --dense-max-n 0 --json-out $OUT/k256.json --force 2>&1 | tail -12
