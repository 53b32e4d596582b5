#!/usr/bin/env bash
# MP-NODE paper, Table 2 and Figure 5: epochs_x_min_error (epoch of the minimum test error × that error) of
# MP-NODE finetuned vs trained from scratch, and L2S, end to end (data, pre-training, sweeps, report).
#   Lorenz10 ds=50/100/500   finetune from Lorenz3          vs scratch
#   Kuramoto ds=50/100/500   finetune from Kuramoto10 BA     vs scratch, on Kuramoto10 ER (the paper's Fig. 5c)
#   Gene                     finetune from gene 4×4 BA       vs scratch, and L2S, on gene 8×8 BA
#   Quadrotors               finetune from 3 quadrotors      vs scratch, and L2S, on 6 quadrotors
# CPU-sized by default (about an hour on 2 free cores): EPOCHS=60 epochs per target run (paper: 4000 for
# MP-NODE, 10000 for L2S), pre-training PRE_EPOCHS=150 epochs on 200 trajectories (paper: 700), quadrotor
# trajectories cut to QH=60 steps (3 s, the align-and-morph phase) and integrated by the models with one RK4 step
# per 0.05 s sample (QSOLVER=rk4; at rtol 1e-4 dopri5 also takes one step per sample, at 3× the cost), 2 seeds.
# Paper-sized: PAPER=1 cli/table2.sh.
# Finetunes refit the normalisation on the new data, as MPNODE.jl does (REFIT=false keeps the checkpoint's).
# Seeds vary the initial weights of scratch runs and the batch order of every run; datasets are fixed.
# Any size can be overridden, e.g. EPOCHS=100 SEEDS=0,1,2 PARTS="gene quad" cli/table2.sh
# (the columns to run; COLS, its older name, still works).
# REUSE=1 keeps a pre-trained checkpoint already in $OUT/checkpoints (e.g. cli/table1.sh's MP-NODE seed 0,
# which is the same run as the gene pre-training here) instead of training it again.
# Tables: $OUT/table2.md (Table 2) and $OUT/figure5.md (learning curves), with PNGs beside them.
# Resumable: run it again with the same settings and finished runs are kept, interrupted ones resumed
# (cli/lib.sh); FRESH=1 starts over.
set -euo pipefail
source "$(dirname "$0")/lib.sh"
OUT=${OUT:-outputs/table2}
PAPER=${PAPER:-0}
if [ "$PAPER" = 1 ]; then
  EPOCHS=${EPOCHS:-4000}; L2S_EPOCHS=${L2S_EPOCHS:-10000}; PRE_EPOCHS=${PRE_EPOCHS:-4000}; PRE_N=${PRE_N:-700}
  TRAINER=${TRAINER:-paper}; SEEDS=${SEEDS:-0,1,2}; QH=${QH:-50}; Q_DS=${Q_DS:-500}; G_DS=${G_DS:-700}
  QSOLVER=${QSOLVER:-dopri5}
  SIZE="paper-sized: MPNODE.jl trainer (batch 128, lr 1e-3), $EPOCHS epochs per run ($L2S_EPOCHS for L2S), pre-training on $PRE_N trajectories"
else
  EPOCHS=${EPOCHS:-60}; L2S_EPOCHS=${L2S_EPOCHS:-$EPOCHS}; PRE_EPOCHS=${PRE_EPOCHS:-150}; PRE_N=${PRE_N:-200}
  TRAINER=${TRAINER:-default}; SEEDS=${SEEDS:-0,1}; QH=${QH:-60}; Q_DS=${Q_DS:-100}; G_DS=${G_DS:-100}
  QSOLVER=${QSOLVER:-rk4}
  SIZE="CPU-sized: $EPOCHS epochs per run (paper: 4000; L2S 10000), pre-training $PRE_EPOCHS epochs on $PRE_N trajectories (paper: 4000 on 700), batch 32, lr 3e-3; gene 8×8 on $G_DS trajectories; quadrotors $Q_DS trajectories of $QH steps, models integrated with $QSOLVER"
fi
DS=${DS:-50,100,500}        # Lorenz10 / Kuramoto finetuning dataset sizes
REFIT=${REFIT:-true}        # finetunes refit the state (and control) normalisation on the target data
MSG=${MSG:-13}              # quadrotor message size
JOBS=${JOBS:-2}             # parallel jobs per sweep
PARTS=${PARTS:-${COLS:-"lorenz kuramoto gene quad"}}  # the columns to run; COLS is its older name
check_parts table2.sh lorenz kuramoto gene quad
check_counts table2.sh EPOCHS L2S_EPOCHS PRE_EPOCHS PRE_N QH Q_DS G_DS DS MSG JOBS
CKPT=$OUT/checkpoints
common=(paths.output_root=$OUT paths.ckpt_dir=$CKPT trainer=$TRAINER trainer.progress=false
        trainer.early_stop_patience=0 eval.plots=false)
quad=(data.horizon=$QH data.n_val=30 data.n_test=30 solver=$QSOLVER)
REUSE=${REUSE:-0}
[ "${FRESH:-0}" = 1 ] && rm -rf "$OUT"
rm -rf "$OUT/report"

pretrain() {  # name system [overrides...]: one scratch run that exports <system>.ckpt
  local name=$1 system=$2; shift 2
  if [ "$REUSE" = 1 ] && [ -f "$CKPT/$system.ckpt" ]; then echo "reusing $CKPT/$system.ckpt"; return; fi
  train_once "$OUT/$name" system=$system data.n_train=$PRE_N trainer.max_epochs=$PRE_EPOCHS "${common[@]}" "$@"
}
# target and l2s print one line per run; a column's lines go to one pool of $JOBS, so a core freed by a finished
# run takes the next one (L2S does not wait for the slowest MP-NODE run)
target() {  # name system init sizes [overrides...]: finetune (init) and scratch runs over seeds and dataset sizes
  local name=$1 system=$2 init=$3 sizes=$4; shift 4
  for ds in ${sizes//,/ }; do
    for start in $init null; do
      tag=finetune; [ "$start" = null ] && tag=scratch
      for seed in ${SEEDS//,/ }; do
        echo "train_once $OUT/$name/${tag}_ds${ds}_s$seed system=$system init=$start seed=$seed data.n_train=$ds \
          mode.refit_normalisation=$REFIT trainer.max_epochs=$EPOCHS export=false ${common[*]} $*"
      done
    done
  done
}
l2s() {  # name system size [overrides...]: L2S from scratch over seeds
  local name=$1 system=$2 ds=$3; shift 3
  for seed in ${SEEDS//,/ }; do
    echo "train_once $OUT/$name/s$seed system=$system model=l2s seed=$seed data.n_train=$ds \
      trainer.max_epochs=$L2S_EPOCHS export=false ${common[*]} $*"
  done
}

for column in $PARTS; do
  case $column in
    lorenz)
      pretrain lorenz3_pre lorenz3
      target lorenz10 lorenz10 lorenz3.ckpt "$DS" | parallel "$JOBS" ;;
    kuramoto)
      pretrain kuramoto_pre kuramoto10_ba
      target kuramoto kuramoto10_er kuramoto10_ba.ckpt "$DS" | parallel "$JOBS" ;;
    gene)
      pretrain gene_pre gene_ba_small
      { target gene gene_ba_large gene_ba_small.ckpt "$G_DS"; l2s gene_l2s gene_ba_large "$G_DS"; } | parallel "$JOBS" ;;
    quad)
      pretrain quad_pre quad3 model.message_size=$MSG "${quad[@]}"
      { target quad quad6 quad3.ckpt "$Q_DS" model.message_size=$MSG "${quad[@]}"
        l2s quad_l2s quad6 "$Q_DS" "${quad[@]}"; } | parallel "$JOBS" ;;
  esac
done

runs=$(ls -d "$OUT"/*/ | grep -v -e /report -e /checkpoints | paste -sd, -)
report=(hydra.run.dir=$OUT/report paths.output_root=$OUT "runs=[$runs]")
mpsim report layout=table2 "title='Table 2 ($SIZE)'" "${report[@]}"
cp "$OUT/report/report.md" "$OUT/table2.md"; cp "$OUT/report/report.csv" "$OUT/table2.csv"
cp "$OUT/report/table2.png" "$OUT/table2.png"
rm -rf "$OUT/report"  # copied out above; mpsim refuses to write a report over an earlier one
mpsim report layout=curves "title='Figure 5: finetuned vs from scratch ($SIZE)'" "${report[@]}"
cp "$OUT/report/report.md" "$OUT/figure5.md"; cp "$OUT/report/curves.png" "$OUT/curves.png"
echo "tables: $OUT/table2.md, $OUT/figure5.md"
