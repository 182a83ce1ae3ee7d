set -x
bash .gpu/setup.sh || exit 1
export PYTHONPATH=/tmp/site PYTHONUNBUFFERED=1
python3 -m pip install -q --no-deps --no-build-isolation --no-index -e . 2>&1 | tail -2
nvidia-smi --query-gpu=name,clocks.sm,clocks.mem --format=csv
warpgauss bench kernels --size 256 --n 2000,12000,60000 --samples 307200 --no-decode --dense-max-n 0 --json-out $OUT/k256_new.json --force 2>&1 | grep -v "^|"
warpgauss bench kernels --size 1024 --n 1400000 --samples 3072,1048576 --no-decode --dense-max-n 0 --json-out $OUT/k1024_new.json --force 2>&1 | grep -v "^|"
python3 .wk/bench_base.py .wk/base 256 2000,12000,60000 307200 $OUT/k256_base.json 2>&1 | grep -v "^|"
python3 .wk/bench_base.py .wk/base 1024 1400000 3072,1048576 $OUT/k1024_base.json 2>&1 | grep -v "^|"
