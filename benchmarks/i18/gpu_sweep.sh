# issue #18 part 3 on the H100: samples x iterations at CR 100 (and 1000) on the head MRIs (.npz
# saved from ../shared/data, carried) and on two example fields at 512^3 (generated there).
# "-x-" rows are the default rule. usage: bash benchmarks/i18/gpu_sweep.sh mri|fields|defaults
export PYTHONPATH=/tmp/site PYTHONUNBUFFERED=1
case "$1" in
mri)  # first run (before the rate-control speed-up: its wall seconds include a slow analytic fit)
  python3 benchmarks/i18/samples_sweep.py --device cuda:0 --volumes .wk/npz/*.npz --ratios 100 \
    --grid 1500x3072,1500x16384,1500x32768,1500x65536,1500x131072,3000x32768,3000x65536,6000x32768 \
    --out $OUT/i18_sweep_mri_h100.json ;;
fields)
  python3 benchmarks/i18/samples_sweep.py --device cuda:0 --fields vortex:512,interface:512 --ratios 100 \
    --grid 1500x6144,1500x32768,1500x65536,-x-,3000x65536 --out $OUT/i18_sweep_fields512_h100.json ;;
defaults)
  python3 benchmarks/i18/samples_sweep.py --device cuda:0 --volumes .wk/npz/*.npz --ratios 100,1000 \
    --grid -x-,1500x3072 --out $OUT/i18_sweep_mri_defaults_h100.json ;;
esac
