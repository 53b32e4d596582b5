#!/usr/bin/env bash
# Foundation evidence (docs/results_mpnode.md), CPU-sized: about 30 minutes on 2 cores.
#   1. Lorenz3: test error of the trained model vs the untrained one.
#   2. Lorenz10: finetuning the Lorenz3 model vs training from scratch — epochs to reach the same test error
#      (the level both runs reach) and the MP-NODE paper's epochs_x_min_error.
#   3. Pendulum2: messages on vs model.zero_messages=true (the paper's ablation; Figure 3a's curves in
#      $OUT/figure3a.md and figure3a.png).
# Override the sizes with environment variables, e.g. E3=600 E10=300 DS=100 cli/foundation.sh; PARTS="pendulum"
# runs only part 3. The pendulum runs are resumable (cli/lib.sh: run the recipe again; FRESH=1 starts them over).
# Paper-sized (PAPER=1): the MPNODE.jl trainer (batch 128, Adam 1e-3 halved after 500 flat epochs) for 4000 epochs,
# and for the pendulums (the paper's Figure 3a, appendix A.1) 500 trajectories of 10 s at dt 0.1 s, split 350/150
# as MPNODE.jl splits 0.7/0.3 (test: 100 more); 3 seeds.
set -euo pipefail
source "$(dirname "$0")/lib.sh"
OUT=${OUT:-outputs/foundation}
PAPER=${PAPER:-0}
if [ "$PAPER" = 1 ]; then
  E3=${E3:-4000}; E10=${E10:-4000}; EP=${EP:-4000}; SEEDS=${SEEDS:-0,1,2}; TRAINER=${TRAINER:-paper}
  PEND_DATA=${PEND_DATA:-"data.n_train=350 data.n_val=150 data.n_test=100 data.horizon=100"}
fi
E3=${E3:-300}     # Lorenz3 epochs
E10=${E10:-150}   # Lorenz10 epochs (finetune and scratch)
DS=${DS:-100}     # Lorenz10 training trajectories
EP=${EP:-150}     # pendulum2 epochs
SEEDS=${SEEDS:-0,1}
TRAINER=${TRAINER:-default}
PEND_DATA=${PEND_DATA:-}   # pendulum2 data overrides (default: the system's 200 trajectories of 50 steps)
PARTS=${PARTS:-"lorenz pendulum"}
check_parts foundation.sh lorenz pendulum
CKPT=$OUT/checkpoints
common=(paths.output_root=$OUT paths.ckpt_dir=$CKPT trainer=$TRAINER trainer.progress=false trainer.early_stop_patience=0)
report=(hydra.run.dir=$OUT/report paths.output_root=$OUT)
tables=()

rm -rf "$OUT/report"
if [[ " $PARTS " == *" lorenz "* ]]; then
  rm -rf "$OUT/lorenz3" "$OUT/lorenz10"
  mpsim train system=lorenz3 trainer.max_epochs=$E3 hydra.run.dir=$OUT/lorenz3 "${common[@]}"
  mpsim train -m hydra/launcher=joblib hydra.launcher.n_jobs=2 hydra.sweep.dir=$OUT/lorenz10 system=lorenz10 \
    data.n_train=$DS init=lorenz3.ckpt,null trainer.max_epochs=$E10 export=false "${common[@]}"
  mpsim report "runs=[$OUT/lorenz3]" "title='Lorenz3: trained vs untrained'" \
    "columns=[initial_test_error,min_test_error,min_test_error_epoch,epochs_x_min_error]" "${report[@]}"
  mv "$OUT/report/report.md" "$OUT/lorenz3.md"
  mpsim report "runs=[$OUT/lorenz10]" "title='Lorenz10 (ds=$DS): finetuned from Lorenz3 vs scratch'" target=max_min \
    "columns=[initial_test_error,epochs_to_target,min_test_error,min_test_error_epoch,epochs_x_min_error]" "${report[@]}"
  mv "$OUT/report/report.md" "$OUT/lorenz10.md"
  tables+=("$OUT/lorenz3.md" "$OUT/lorenz10.md")
fi
if [[ " $PARTS " == *" pendulum "* ]]; then
  # one resumable run per (seed, messages): run the recipe again to keep finished runs and resume the others
  [ "${FRESH:-0}" = 1 ] && rm -rf "$OUT/pendulum2"
  for seed in ${SEEDS//,/ }; do
    for zero in false true; do
      echo "train_once $OUT/pendulum2/s$seed-zero_messages_$zero system=pendulum2 seed=$seed \
        model.zero_messages=$zero trainer.max_epochs=$EP export=false $PEND_DATA ${common[*]}"
    done
  done | parallel 2
  mpsim report "runs=[$OUT/pendulum2]" "title='Pendulum2: messages on vs zero_messages'" \
    "columns=[initial_test_error,min_test_error,min_test_error_epoch,epochs_x_min_error]" "${report[@]}"
  mv "$OUT/report/report.md" "$OUT/pendulum2.md"
  # the paper's Figure 3a: train loss (and test error) per epoch, messages on vs off, and their ratio
  mpsim report layout=messages "runs=[$OUT/pendulum2]" "title='Figure 3a: pendulum2, messages on vs zero_messages'" \
    "${report[@]}"
  sed 's/(messages\.png)/(figure3a.png)/' "$OUT/report/report.md" > "$OUT/figure3a.md"
  mv "$OUT/report/messages.png" "$OUT/figure3a.png"
  tables+=("$OUT/pendulum2.md")
fi
cat "${tables[@]}" > "$OUT/foundation.md"
echo "tables: $OUT/foundation.md"
