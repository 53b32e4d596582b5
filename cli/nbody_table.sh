#!/usr/bin/env bash
# N-body evidence (docs/results_nbody.md): a CPU-sized reproduction of the shape of Martinkus et al.'s Table 2 /
# Figure 2 — hierarchical vs full vs 15-NN DeltaGN at N = 100 and N = 1000, next to the constant-velocity
# baseline and the paper's numbers, with rollout-step time, training-step time and memory; plus the
# generalisation across N, 100 -> 1000 and 1000 -> 100 (the paper's Figure 5). One thread per process; the
# N = 100 and N = 1000 chains run side by side (about an hour on a 2-core box shared with other work).
#
# Reductions against the paper (1000/200/200 trajectories, 500k steps of 100 states, 5 seeds, P100):
#   N = 100:  100 training trajectories of 200 steps; E100 epochs of 100 optimiser steps, each on P100 random
#             (t, t+1) pairs of one trajectory (default 8 × 100 × 8 = 6400 states; the full graph EFULL = 40 epochs
#             at lr LRFULL = 1e-3: at 3e-3 it never leaves the "predict the mean change" plateau); 1 seed.
#   N = 1000: 16 training trajectories of the first 50 steps; E1000 epochs of 16 steps of P1000 states
#             (default 25 × 16 × 4 = 1600 states); full DeltaGN not trained (its cost is measured instead).
#   Per-epoch model selection on EW-step rollouts (trainer.eval_window) of 2 (N = 100) / 1 (N = 1000)
#   validation trajectories. Test: NT100 (N = 100) and NT1000 (N = 1000) trajectories of 200 steps, generated
#   separately (data.seed = 0 test split) and rolled out by `mpsim eval`.
# EHOGN > 0 also trains the hierarchical HOGN at N = 100 for that many epochs (4 states per step).
# Override the sizes with environment variables, e.g. E100=24 NT100=50 cli/nbody_table.sh
set -euo pipefail
OUT=${OUT:-outputs/nbody_table}
E100=${E100:-8}         # N = 100 epochs (100 steps each)
P100=${P100:-8}         # N = 100 states per optimiser step
E1000=${E1000:-25}      # N = 1000 epochs (16 steps each)
P1000=${P1000:-4}       # N = 1000 states per optimiser step
EHOGN=${EHOGN:-0}       # hierarchical HOGN epochs at N = 100 (0: skip; 20 leaves the plateau, ~20 min)
EFULL=${EFULL:-40}      # full-graph DeltaGN epochs at N = 100 (it needs ~25 to leave the mean-change plateau)
LRFULL=${LRFULL:-1e-3}  # ... at this learning rate (at the recipe's 3e-3 it never left it in 8 epochs)
EW=${EW:-20}            # steps of the per-epoch validation rollouts
NT100=${NT100:-20}      # N = 100 test trajectories
NT1000=${NT1000:-4}     # N = 1000 test trajectories
common=(paths.output_root=$OUT eval.plots=false)
quiet=(trainer.progress=false export=false)
# test sets: the data.seed=0 test split, 200 steps (train/val splits of one trajectory are generated unused)
eval100=(system=nbody100 data.n_train=1 data.n_val=1 data.n_test=$NT100 "${common[@]}")
eval1000=(system=nbody1000 data.n_train=1 data.n_val=1 data.n_test=$NT1000 "${common[@]}")

rm -rf "$OUT/train" "$OUT/eval" "$OUT/table" "$OUT/report"

train() {  # train <name> <overrides...>: one training run in $OUT/train/<name>
  local name=$1; shift
  mpsim train "$@" trainer.eval_window=$EW hydra.run.dir="$OUT/train/$name" "${common[@]}" "${quiet[@]}" \
    > "$OUT/logs/$name.txt" 2>&1
}
evaluate() {  # evaluate <name> <checkpoint run> <overrides...>: test-set metrics in $OUT/eval/<name>
  local name=$1 run=$2; shift 2
  mpsim eval init="$OUT/train/$run/checkpoints/best.ckpt" "$@" hydra.run.dir="$OUT/eval/$name" \
    > "$OUT/logs/eval_$name.txt" 2>&1
}
mkdir -p "$OUT/logs"

chain100() {
  e100=(experiment=nbody100_cpu trainer.max_epochs=$E100 model.pairs_per_trajectory=$P100)
  mpsim train model=constant_velocity trainer.max_epochs=0 hydra.run.dir="$OUT/eval/n100_cv" \
    "${eval100[@]}" "${quiet[@]}" > "$OUT/logs/n100_cv.txt" 2>&1
  for graph in hierarchical knn; do
    train "n100_$graph" "${e100[@]}" model=deltagn model.graph=$graph
    evaluate "n100_$graph" "n100_$graph" "${eval100[@]}"
  done
  train n100_full "${e100[@]}" trainer.max_epochs=$EFULL trainer.lr=$LRFULL model=deltagn model.graph=full
  evaluate n100_full n100_full "${eval100[@]}"
}

chain1000() {
  e1000=(experiment=nbody1000_cpu trainer.max_epochs=$E1000 model.pairs_per_trajectory=$P1000)
  mpsim train model=constant_velocity trainer.max_epochs=0 hydra.run.dir="$OUT/eval/n1000_cv" \
    "${eval1000[@]}" "${quiet[@]}" > "$OUT/logs/n1000_cv.txt" 2>&1
  for graph in hierarchical knn; do
    train "n1000_$graph" "${e1000[@]}" model=deltagn model.graph=$graph
    evaluate "n1000_$graph" "n1000_$graph" "${eval1000[@]}"
  done
  if [ "$EHOGN" -gt 0 ]; then  # the paper's HierHOGN at N = 100 (HOGN differentiates through 4 RK4 stages)
    train n100_hogn_hierarchical experiment=nbody100_cpu trainer.max_epochs=$EHOGN model=hogn \
      model.graph=hierarchical model.pairs_per_trajectory=4 data.n_val=1 data.n_test=1
    evaluate n100_hogn_hierarchical n100_hogn_hierarchical "${eval100[@]}"
  fi
}

chain100 & pid100=$!
chain1000 & pid1000=$!
wait $pid100 && wait $pid1000

# generalisation to an unseen N (the paper's Figure 5 and notebook): models trained at N = 100 evaluated at
# N = 1000 and the other way round (the full graph is left out: one of its steps at N = 1000 costs ~10 s here)
for graph in hierarchical knn; do
  evaluate "n100_${graph}_at_1000" "n100_$graph" "${eval1000[@]}"
  evaluate "n1000_${graph}_at_100" "n1000_$graph" "${eval100[@]}"
done

runs=(n100_cv n100_knn n100_full n100_hierarchical n1000_cv n1000_knn n1000_hierarchical
      n100_knn_at_1000 n100_hierarchical_at_1000 n1000_knn_at_100 n1000_hierarchical_at_100)
[ "$EHOGN" -gt 0 ] && runs+=(n100_hogn_hierarchical)
list=$(printf "$OUT/eval/%s," "${runs[@]}")
mpsim bench bench=nbody_table "bench.runs=[${list%,}]" "bench.cost_only=[deltagn:full:1000]" bench.train_states=1 \
  hydra.run.dir="$OUT/table" paths.output_root=$OUT
mpsim report "runs=[$OUT/train]" "title='N-body training runs (per-epoch errors: $EW-step rollouts)'" \
  "columns=[initial_test_error,min_test_error,min_test_error_epoch,test_error,wall_time]" \
  hydra.run.dir="$OUT/report" paths.output_root=$OUT
echo "table: $OUT/table/bench.md; training runs: $OUT/report/report.md"
