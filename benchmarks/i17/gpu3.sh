bash .gpu/setup.sh || exit 1
export PYTHONPATH=/tmp/site PYTHONUNBUFFERED=1
python3 -m pip install -q --no-deps --no-build-isolation --no-index -e . 2>&1 | tail -2
NCU=$(command -v ncu || ls /opt/nvidia/nsight-compute/*/ncu | head -1)
echo "ncu: $NCU"
python3 .wk/prof.py 1024 1400000 1048576 decode > /dev/null 2>&1  # compile + cache kernels
for cfg in "1024 1400000 1048576 decode" "256 2000 307200"; do
  tag=$(echo $cfg | cut -d' ' -f2)
  timeout 240 $NCU --clock-control none --launch-skip 0 --launch-count 6 -k "regex:eval_points_ordered|pair_grad_chunks|eval_grid_blocked|pair_work|reduce_chunks" \
    --section SpeedOfLight --section Occupancy --section WarpStateStats --section LaunchStats --section MemoryWorkloadAnalysis \
    --csv --page details python3 .wk/prof.py $cfg > $OUT/ncu_$tag.csv 2> $OUT/ncu_$tag.err
  echo "rc=$? $(wc -l < $OUT/ncu_$tag.csv) lines"
  python3 - $OUT/ncu_$tag.csv <<'PY'
import csv, sys, collections
rows = list(csv.DictReader(open(sys.argv[1])))
keep = ("Duration", "Compute (SM) Throughput", "Memory Throughput", "Achieved Occupancy", "Theoretical Occupancy", "Registers Per Thread",
        "L1/TEX Hit Rate", "L2 Hit Rate", "Warp Cycles Per Issued Instruction", "Block Limit Registers", "DRAM Throughput", "Issue Slots Busy")
seen = collections.OrderedDict()
for r in rows:
    k = (r.get("ID"), r.get("Kernel Name", "")[:40])
    if r.get("Metric Name") in keep:
        seen.setdefault(k, []).append(f"{r['Metric Name']}={r['Metric Value']}{r.get('Metric Unit','')}")
for k, v in seen.items():
    print(k[1], "|", "; ".join(v))
PY
done
tail -5 $OUT/ncu_*.err
