# per-kernel profile of refinement on interface and vortex 1024^3, 1.4M Gaussians, paper samples
bash .gpu/setup.sh 2>/dev/null || { ls /tmp/site/warp/bin/warp.so >/dev/null || exit 1; }
export PYTHONPATH=/tmp/site PYTHONUNBUFFERED=1
python3 -m pip install -q --no-deps --no-build-isolation --no-index -e . 2>&1 | tail -2
python3 benchmarks/i17/field_prof.py interface 1024 1400000 3072 $OUT/prof_interface1024.json 200 2>&1 | tail -22
python3 benchmarks/i17/field_prof.py vortex 1024 1400000 3072 $OUT/prof_vortex1024.json 1500 2>&1 | tail -22
