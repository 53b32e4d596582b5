#!/usr/bin/env bash
# Issue 70, case a: the coupled electric drives benchmark (real; ../shared/data/real/ced_coupled_drives/README.md),
# scored as the field does: the report's Wiener model (examples/measured/ced_wiener.yaml: every state latent, the
# sensor reads |speed|) fitted on the official training samples 0–399 of both uniform records, then each test
# record (samples 400–499) simulated free from its first 4 samples; RMSE in volts on the other 96, beside the
# published baselines. Usage: OUT=outputs/ced bash cli/ced.sh   (about 30 s on 2 cores)
set -euo pipefail
DATA=${DATA:-../shared/data/real/ced_coupled_drives}
OUT=${OUT:-outputs/ced}
[[ -f $DATA/ced_unif_1.csv ]] || { echo "ced.sh: no recordings in DATA=$DATA" >&2; exit 2; }
mpsim train model=equations model.spec=examples/measured/ced_wiener.yaml trainer=whitebox \
  "data.path=$DATA/ced_unif_*.csv" data.input_hold=zoh data.train_range=[0,400] data.test_range=[400,500] \
  data.segment="${SEGMENT:-1.0}" eval.init_samples=4 trainer.progress=false "paths.ckpt_dir=$OUT/checkpoints" \
  "hydra.run.dir=$OUT/train"
# Issue 71, case e: `DIAGNOSE=1` then diagnoses the fitted model on the same split (held out: the test records cut
# into DIAG_SEGMENT=0.5 s segments, six: 1 s segments leave one per record, and diagnose needs three), fix=true;
# the verdict and the free run before → after are in $OUT/diagnose/diagnosis.md.
if [[ ${DIAGNOSE:-0} == 1 ]]; then
  set +e
  mpsim diagnose init="$OUT/train/checkpoints/best.ckpt" "data.path=$DATA/ced_unif_*.csv" data.input_hold=zoh \
    data.train_range=[0,400] data.test_range=[400,500] data.segment="${DIAG_SEGMENT:-0.5}" eval.init_samples=4 fix=true \
    trainer=whitebox trainer.progress=false "paths.ckpt_dir=$OUT/checkpoints" "hydra.run.dir=$OUT/diagnose"
  code=$?
  set -e
  echo "ced.sh: diagnose exit $code (0 effects named, 10 nothing missing, 11 unexplained)"
fi
