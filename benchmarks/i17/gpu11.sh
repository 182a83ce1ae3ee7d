# final kernel figures after the run-length cell counts (256^3 and 1024^3), H100
bash .gpu/setup.sh 2>/dev/null || { ls /tmp/site/warp/bin/warp.so >/dev/null || exit 1; }
export PYTHONPATH=/tmp/site PYTHONUNBUFFERED=1
python3 -m pip install -q --no-deps --no-build-isolation --no-index -e . 2>&1 | tail -2
warpgauss bench kernels --size 256 --n 2000,12000,60000 --samples 307200 --no-decode --dense-max-n 0 --json-out $OUT/k256.json --force 2>&1 | tail -6
warpgauss bench kernels --size 1024 --n 1400000 --samples 3072,1048576 --no-decode --dense-max-n 0 --json-out $OUT/k1024.json --force 2>&1 | tail -7
