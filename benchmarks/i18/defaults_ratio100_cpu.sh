D=/work/shared/data
for v in mni_icbm152_t1_tal_nlin_sym_09a_converted inia19-t1-brain; do
  warpgauss encode $D/$v.nii.gz --ratio 100 --format full --device cpu --full-eval -o /tmp/q/def/${v}_full.wgs --force --json > /tmp/q/def/${v}_full.json 2> /tmp/q/def/${v}_full.err
  warpgauss encode $D/$v.nii.gz --ratio 100 --device cpu --full-eval -o /tmp/q/def/${v}_coded.wgs --force --json > /tmp/q/def/${v}_coded.json 2> /tmp/q/def/${v}_coded.err
done
echo finished > /tmp/q/def/done
