bash .gpu/setup.sh 2>/dev/null || { ls /tmp/site/warp/bin/warp.so || exit 1; }
export PYTHONPATH=/tmp/site PYTHONUNBUFFERED=1
python3 -m pip install -q --no-deps --no-build-isolation --no-index -e . 2>&1 | tail -2
for v in mean_reg2mean mni_icbm152_t1_tal_nlin_sym_09a_converted inia19-t1-brain; do
  warpgauss encode .wk/data/$v.npy --ratio 100 --compact --samples 30720 -o /tmp/new_$v.wgs --force > /tmp/enc_new_$v.log 2>&1; echo "new $v rc=$?"; tail -1 /tmp/enc_new_$v.log
  cp /tmp/new_$v.wgs.report.json $OUT/mri_new_$v.json
done
v=mean_reg2mean
python3 .wk/cli_base.py .wk/base encode .wk/data/$v.npy --ratio 100 --compact --samples 30720 -o /tmp/base_$v.wgs --force > /tmp/enc_base.log 2>&1; echo "base rc=$?"; tail -1 /tmp/enc_base.log
cp /tmp/base_$v.wgs.report.json $OUT/mri_base_$v.json
python3 .wk/mri.py new_mean $OUT/mri_new_mean_reg2mean.json base_mean $OUT/mri_base_mean_reg2mean.json new_mni $OUT/mri_new_mni_icbm152_t1_tal_nlin_sym_09a_converted.json new_inia $OUT/mri_new_inia19-t1-brain.json $OUT/mri_summary.json
