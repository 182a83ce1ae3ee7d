# decode kernels by time, and a vortex 1024^3 paper run's late per-kernel time, H100
bash .gpu/setup.sh 2>/dev/null || { ls /tmp/site/warp/bin/warp.so >/dev/null || exit 1; }
export PYTHONPATH=/tmp/site PYTHONUNBUFFERED=1
python3 -m pip install -q --no-deps --no-build-isolation --no-index -e . 2>&1 | tail -2
python3 benchmarks/i17/decode_prof.py 1024 1400000 $OUT/decode_prof1024.json 2>&1 | tail -10
python3 benchmarks/i17/field_prof.py vortex 1024 1400000 3072 $OUT/prof_vortex1024.json 1500 2>&1 | tail -40
