#!/usr/bin/env bash
# MP-NODE paper, Figures 8 and 7: effect of the message size. Kuramoto10 (BA) with m = 1, 3, 7, 13 (Figure 8), and
# 3 and 6 quadrotors with m = 7, 13, 20 next to L2S (Figure 7), each trained from scratch over seeds.
# CPU-sized by default (about an hour on 2 free cores): K_EPOCHS=100 Kuramoto epochs on 100 trajectories,
# Q_EPOCHS=40 quadrotor epochs on 100 trajectories of QH=60 steps (one RK4 step per sample: QSOLVER=rk4), 2 seeds
# (paper: 4000 epochs; L2S 10000).
# Paper-sized: PAPER=1 cli/message_size.sh. Figures and tables: $OUT/message_size.md. PARTS=kuramoto runs only
# Figure 8 (PARTS=quad only Figure 7); the report covers whatever runs have finished under $OUT.
# Resumable: run it again with the same settings and finished runs are kept, interrupted ones resumed
# (cli/lib.sh); FRESH=1 starts over.
# At PAPER=1, Figure 7's 3-quadrotor m = 13 seed-0 run is cli/table2.sh's quadrotor pre-training (PAPER=1: the same
# data, model, trainer and seed; checked to train identically, every metric to the last digit): copy a finished
# <table2 OUT>/quad_pre to $OUT/quad/quad3_m13_s0 and it is kept, not trained again (one 4000-epoch run saved).
# Likewise 6 quadrotors train on Q6_N=500 trajectories at PAPER=1, Table 2's target size (the paper states neither),
# so their m = 13 and L2S seed-0 runs are table2.sh's quad/scratch_ds500_s0 and quad_l2s/s0 (checked the same way):
# copy those to $OUT/quad/quad6_m13_s0 and $OUT/quad_l2s/quad6_s0.
set -euo pipefail
source "$(dirname "$0")/lib.sh"
OUT=${OUT:-outputs/message_size}
PAPER=${PAPER:-0}
if [ "$PAPER" = 1 ]; then
  K_EPOCHS=${K_EPOCHS:-4000}; Q_EPOCHS=${Q_EPOCHS:-4000}; L2S_EPOCHS=${L2S_EPOCHS:-10000}; N_TRAIN=${N_TRAIN:-700}; TRAINER=${TRAINER:-paper}
  SEEDS=${SEEDS:-0,1,2}; QH=${QH:-50}; QSOLVER=${QSOLVER:-dopri5}; Q6_N=${Q6_N:-500}
  SIZE="paper-sized: MPNODE.jl trainer, $K_EPOCHS epochs ($L2S_EPOCHS for L2S), $N_TRAIN trajectories ($Q6_N for 6 quadrotors)"
else
  K_EPOCHS=${K_EPOCHS:-100}; Q_EPOCHS=${Q_EPOCHS:-40}; L2S_EPOCHS=${L2S_EPOCHS:-$Q_EPOCHS}; N_TRAIN=${N_TRAIN:-100}; TRAINER=${TRAINER:-default}
  SEEDS=${SEEDS:-0,1}; QH=${QH:-60}; QSOLVER=${QSOLVER:-rk4}; Q6_N=${Q6_N:-$N_TRAIN}
  SIZE="CPU-sized: Kuramoto $K_EPOCHS epochs, quadrotors $Q_EPOCHS epochs on $N_TRAIN trajectories of $QH steps, integrated with $QSOLVER (paper: 4000 epochs)"
fi
K_MSG=${K_MSG:-1,3,7,13}
Q_MSG=${Q_MSG:-7,13,20}
JOBS=${JOBS:-2}
PARTS=${PARTS:-"kuramoto quad"}
check_parts message_size.sh kuramoto quad
check_counts message_size.sh K_EPOCHS Q_EPOCHS L2S_EPOCHS N_TRAIN Q6_N QH
common=(paths.output_root=$OUT trainer=$TRAINER trainer.progress=false trainer.early_stop_patience=0 eval.plots=false
        export=false)
quad=(data.horizon=$QH data.n_val=30 data.n_test=30 solver=$QSOLVER)

[ "${FRESH:-0}" = 1 ] && rm -rf "$OUT"
rm -rf "$OUT/report"
for seed in ${SEEDS//,/ }; do
  if [[ " $PARTS " == *" kuramoto "* ]]; then
    for m in ${K_MSG//,/ }; do
      echo "train_once $OUT/kuramoto/m${m}_s$seed system=kuramoto10_ba model.message_size=$m seed=$seed \
        trainer.max_epochs=$K_EPOCHS data.n_train=$N_TRAIN ${common[*]}"
    done
  fi
  if [[ " $PARTS " == *" quad "* ]]; then
    for system in quad3 quad6; do
      n=$N_TRAIN; [ $system = quad6 ] && n=$Q6_N
      for m in ${Q_MSG//,/ }; do
        echo "train_once $OUT/quad/${system}_m${m}_s$seed system=$system model.message_size=$m seed=$seed trainer.max_epochs=$Q_EPOCHS \
          data.n_train=$n ${quad[*]} ${common[*]}"
      done
      echo "train_once $OUT/quad_l2s/${system}_s$seed system=$system model=l2s seed=$seed trainer.max_epochs=$L2S_EPOCHS \
        data.n_train=$n ${quad[*]} ${common[*]}"
    done
  fi
done | parallel "$JOBS"

runs=$(for d in kuramoto quad quad_l2s; do if [ -d "$OUT/$d" ]; then echo "$OUT/$d"; fi; done | paste -sd, -)
mpsim report layout=message_size "title='Figures 7 and 8: message size ($SIZE)'" \
  "runs=[$runs]" hydra.run.dir=$OUT/report paths.output_root=$OUT
cp "$OUT/report/report.md" "$OUT/message_size.md"
cp "$OUT/report/message_size.png" "$OUT/report/message_size_curves.png" "$OUT/"
echo "figures: $OUT/message_size.md"
