# decode (brick lists vs cell walk vs row-major) and the iteration profile, H100
bash .gpu/setup.sh 2>/dev/null || { ls /tmp/site/warp/bin/warp.so >/dev/null || exit 1; }
export PYTHONPATH=/tmp/site PYTHONUNBUFFERED=1
python3 -m pip install -q --no-deps --no-build-isolation --no-index -e . 2>&1 | tail -2
warpgauss bench kernels --size 1024 --n 1400000 --samples 3072 --repeat 5 --dense-max-n 0 --json-out $OUT/k1024_decode.json --force 2>&1 | tail -12
python3 benchmarks/i17/iter_prof.py 1024 1400000 3072 $OUT/iter_1024.json 2>&1 | tail -30
python3 benchmarks/i17/iter_prof.py 256 12000 307200 $OUT/iter_256.json 2>&1 | tail -30
