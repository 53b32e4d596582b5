#!/usr/bin/env bash
# MP-NODE paper, Table 1: zero-shot generalisation on gene regulatory dynamics (4×4 = 16 nodes). MP-NODE and L2S
# are trained on BA graphs (five adjacency matrices, seeds 1..5); each seed's MP-NODE checkpoint (and L2S's) is
# then evaluated without training on unseen ER and WS graphs (five each). Cells: normalised rollout RMSE over
# 50 steps, mean ± std over seeds.
# CPU-sized by default (about 15 minutes on 2 free cores): EPOCHS=150 epochs on N_TRAIN=200 trajectories, 3 seeds
# (paper: 4000 epochs, 700 trajectories). Paper-sized: PAPER=1 cli/table1.sh.
# Table: $OUT/table1.md (with table1.png and table1_horizons.png, the zero-shot ratios by rollout step).
# Resumable: run it again with the same settings and finished runs are kept, interrupted ones resumed
# (cli/lib.sh); FRESH=1 starts over.
set -euo pipefail
source "$(dirname "$0")/lib.sh"
OUT=${OUT:-outputs/table1}
PAPER=${PAPER:-0}
if [ "$PAPER" = 1 ]; then
  EPOCHS=${EPOCHS:-4000}; L2S_EPOCHS=${L2S_EPOCHS:-10000}; N_TRAIN=${N_TRAIN:-700}; TRAINER=${TRAINER:-paper}
  SIZE="paper-sized: MPNODE.jl trainer, $EPOCHS epochs ($L2S_EPOCHS for L2S), $N_TRAIN training trajectories"
else
  EPOCHS=${EPOCHS:-150}; L2S_EPOCHS=${L2S_EPOCHS:-$EPOCHS}; N_TRAIN=${N_TRAIN:-200}; TRAINER=${TRAINER:-default}
  SIZE="CPU-sized: $EPOCHS epochs on $N_TRAIN trajectories (paper: 4000 epochs, L2S 10000, on 700), batch 32, lr 3e-3"
fi
SEEDS=${SEEDS:-"0 1 2"}
MODELS=${MODELS:-"mpnode l2s"}   # add node for the monolithic baseline (same 16 nodes, so it can run zero-shot)
JOBS=${JOBS:-2}
check_counts table1.sh EPOCHS L2S_EPOCHS N_TRAIN JOBS
EXTRA=${EXTRA:-}                 # extra train overrides for an ablation, e.g. EXTRA=model.aggregation=sum OUT=outputs/table1_sum
ZS_EXTRA=${ZS_EXTRA:-}           # extra zero-shot overrides (model.* come from the checkpoint), e.g. for EXTRA=system.initial=uniform: ZS_EXTRA=++system.initial=uniform
common=(paths.output_root=$OUT trainer=$TRAINER trainer.progress=false trainer.early_stop_patience=0 eval.plots=false)

[ "${FRESH:-0}" = 1 ] && rm -rf "$OUT"
rm -rf "$OUT/zeroshot" "$OUT/report"  # zero-shot evaluations are cheap: always redone from the checkpoints
for seed in ${SEEDS//,/ }; do  # one checkpoint directory per seed: every run exports <system>.ckpt
  for model in ${MODELS//,/ }; do
    epochs=$EPOCHS; [ $model = l2s ] && epochs=$L2S_EPOCHS
    echo "train_once $OUT/train/$model/s$seed system=gene_ba_small model=$model seed=$seed data.n_train=$N_TRAIN \
      trainer.max_epochs=$epochs paths.ckpt_dir=$OUT/checkpoints/$model/s$seed ${common[*]} $EXTRA"
  done
done | parallel "$JOBS"
# zero-shot every model trained in $OUT, not only this call's MODELS and SEEDS: the table reads every run in
# $OUT/train, so a call that finishes one run (e.g. MODELS=l2s SEEDS=0) still regenerates the whole table
for ckpt in "$OUT"/checkpoints/*/s*/gene_ba_small.ckpt; do
  [ -f "$ckpt" ] || continue
  run=${ckpt#"$OUT/checkpoints/"}; run=${run%/gene_ba_small.ckpt}  # <model>/s<seed>
  mpsim train -m mode=zeroshot init="$ckpt" \
    system=gene_er_small,gene_ws_small hydra.sweep.dir="$OUT/zeroshot/$run" "${common[@]}" $ZS_EXTRA
done

mpsim report layout=table1 "title='Table 1: zero-shot generalisation on gene 4×4 ($SIZE)'" \
  "runs=[$OUT/train,$OUT/zeroshot]" hydra.run.dir=$OUT/report paths.output_root=$OUT
cp "$OUT/report/report.md" "$OUT/table1.md"; cp "$OUT/report/table1.png" "$OUT/table1.png"
# the zero-shot ratios by rollout step (when the runs recorded per-step errors), which table1.md links to
[ ! -f "$OUT/report/table1_horizons.png" ] || cp "$OUT/report/table1_horizons.png" "$OUT/table1_horizons.png"
echo "table: $OUT/table1.md"
