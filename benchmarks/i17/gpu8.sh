# the head MRIs at --ratio 100 --compact --samples 30720 (volumes as .npy under .wk/data), H100
export PYTHONPATH=/tmp/site PYTHONUNBUFFERED=1
for v in mean_reg2mean mni_icbm152_t1_tal_nlin_sym_09a_converted inia19-t1-brain; do
  warpgauss encode .wk/data/$v.npy --ratio 100 --compact --samples 30720 -o /tmp/new_$v.wgs --force > /tmp/enc_new_$v.log 2>&1; echo "new $v rc=$?"; tail -1 /tmp/enc_new_$v.log
  cp /tmp/new_$v.wgs.report.json $OUT/mri_new_$v.json
done
python3 benchmarks/i17/mri.py new_mean $OUT/mri_new_mean_reg2mean.json new_mni $OUT/mri_new_mni_icbm152_t1_tal_nlin_sym_09a_converted.json new_inia $OUT/mri_new_inia19-t1-brain.json $OUT/mri_summary.json
