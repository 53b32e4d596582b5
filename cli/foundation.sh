#!/usr/bin/env bash
# Foundation evidence (docs/results_mpnode.md), CPU-sized: about 30 minutes on 2 cores.
#   1. Lorenz3: test error of the trained model vs the untrained one.
#   2. Lorenz10: finetuning the Lorenz3 model vs training from scratch — epochs to reach the same test error
#      (the level both runs reach) and the MP-NODE paper's epochs_x_min_error.
#   3. Pendulum2: messages on vs model.zero_messages=true (the paper's ablation).
# Override the sizes with environment variables, e.g. E3=600 E10=300 DS=100 cli/foundation.sh
set -euo pipefail
OUT=${OUT:-outputs/foundation}
E3=${E3:-300}     # Lorenz3 epochs
E10=${E10:-150}   # Lorenz10 epochs (finetune and scratch)
DS=${DS:-100}     # Lorenz10 training trajectories
EP=${EP:-150}     # pendulum2 epochs
SEEDS=${SEEDS:-0,1}
CKPT=$OUT/checkpoints
common=(paths.output_root=$OUT paths.ckpt_dir=$CKPT trainer.progress=false trainer.early_stop_patience=0)

rm -rf "$OUT/lorenz3" "$OUT/lorenz10" "$OUT/pendulum2" "$OUT/report"
mpsim train system=lorenz3 trainer.max_epochs=$E3 hydra.run.dir=$OUT/lorenz3 "${common[@]}"
mpsim train -m hydra/launcher=joblib hydra.launcher.n_jobs=2 hydra.sweep.dir=$OUT/lorenz10 system=lorenz10 \
  data.n_train=$DS init=lorenz3.ckpt,null trainer.max_epochs=$E10 export=false "${common[@]}"
mpsim train -m hydra/launcher=joblib hydra.launcher.n_jobs=2 hydra.sweep.dir=$OUT/pendulum2 system=pendulum2 \
  seed=$SEEDS model.zero_messages=false,true trainer.max_epochs=$EP export=false "${common[@]}"

report=(hydra.run.dir=$OUT/report paths.output_root=$OUT)
mpsim report "runs=[$OUT/lorenz3]" "title='Lorenz3: trained vs untrained'" \
  "columns=[initial_test_error,min_test_error,min_test_error_epoch,epochs_x_min_error]" "${report[@]}"
mv "$OUT/report/report.md" "$OUT/lorenz3.md"
mpsim report "runs=[$OUT/lorenz10]" "title='Lorenz10 (ds=$DS): finetuned from Lorenz3 vs scratch'" target=max_min \
  "columns=[initial_test_error,epochs_to_target,min_test_error,min_test_error_epoch,epochs_x_min_error]" "${report[@]}"
mv "$OUT/report/report.md" "$OUT/lorenz10.md"
mpsim report "runs=[$OUT/pendulum2]" "title='Pendulum2: messages on vs zero_messages'" \
  "columns=[initial_test_error,min_test_error,min_test_error_epoch,epochs_x_min_error]" "${report[@]}"
mv "$OUT/report/report.md" "$OUT/pendulum2.md"
cat "$OUT/lorenz3.md" "$OUT/lorenz10.md" "$OUT/pendulum2.md" > "$OUT/foundation.md"
echo "tables: $OUT/foundation.md"
