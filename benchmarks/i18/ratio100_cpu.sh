D=/work/shared/data
for v in mni_icbm152_t1_tal_nlin_sym_09a_converted inia19-t1-brain; do
  for f in compact coded; do
    warpgauss encode $D/$v.nii.gz --ratio 100 --format $f --iterations 600 --device cpu --full-eval -o /tmp/q/rd/${v}_$f.wgs --force --json > /tmp/q/rd/${v}_$f.json 2> /tmp/q/rd/${v}_$f.err
  done
done
echo finished > /tmp/q/rd/done
