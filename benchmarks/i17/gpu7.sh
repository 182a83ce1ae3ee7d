# after the support-mark and device-plan fixes: iteration profile, paper/fast presets at 1024^3, H100
bash .gpu/setup.sh 2>/dev/null || { ls /tmp/site/warp/bin/warp.so >/dev/null || exit 1; }
export PYTHONPATH=/tmp/site PYTHONUNBUFFERED=1
python3 -m pip install -q --no-deps --no-build-isolation --no-index -e . 2>&1 | tail -2
python3 benchmarks/i17/iter_prof.py 1024 1400000 3072 $OUT/iter_1024.json 2>&1 | grep -v "^date\|^warp\|^device"
python3 benchmarks/i17/iter_prof.py 256 12000 307200 $OUT/iter_256.json 2>&1 | grep -v "^date\|^warp\|^device"
python3 benchmarks/bench_refine.py --size 1024 --budget 1400000 --fields vortex,interface --presets paper,fast --out $OUT/refine1024.json 2>&1 | tail -8
