# issue #18 part 4 on the H100: warpgauss at CR 10-1000 with the default settings; the reference
# codecs ran on the CPU (benchmarks/results/i18_rd_codecs_cpu.json). The MRIs travel as .npz
# (benchmarks/build/rdvol, written by bench_rd.py --volume-dir; the GPU host has no pyvista).
# usage: bash benchmarks/i18/gpu_rd.sh mri|vortex|interface
export PYTHONPATH=/tmp/site PYTHONUNBUFFERED=1
mkdir -p /tmp/vol && cp benchmarks/build/rdvol/*.npz /tmp/vol/ 2>/dev/null
MRI=mean_reg2mean.nii.gz,mni_icbm152_t1_tal_nlin_sym_09a_converted.nii.gz,inia19-t1-brain.nii.gz
case "$1" in
mri) timeout 580 python3 benchmarks/bench_rd.py --device cuda:0 --codecs none --ratios 10,30,100,300,1000 --fields "" \
       --volume-dir /tmp/vol --real $MRI --max-voxels 100000000 --out $OUT/i18_rd_wg_mri_h100.json ;;
*)   timeout 580 python3 benchmarks/bench_rd.py --device cuda:0 --codecs none --ratios 10,30,100,300,1000 --fields $1 --size 512 \
       --volume-dir /tmp/vol --workers 2 --real none --out $OUT/i18_rd_wg_$1_h100.json ;;
esac
