#!/usr/bin/env bash
# N-body evidence (README "N-body"): a CPU-sized reproduction of the shape of Martinkus et al.'s Table 2 /
# Figure 2 — hierarchical vs full vs 15-NN DeltaGN (+ hierarchical HOGN) at N = 100 and N = 1000, next to the
# constant-velocity baseline and the paper's numbers, with rollout-step time, training-step time and memory.
# About an hour on 2 cores: the N = 100 and N = 1000 chains run side by side, one thread each.
#
# Reductions against the paper (1000/200/200 trajectories, 500k steps of 100 states, 5 seeds, P100):
#   N = 100:  100 training trajectories of 200 steps; 1200 steps of 16 states (hierarchical HOGN: 600 steps of
#             4 states); 1 seed.
#   N = 1000: 16 training trajectories of the first 50 steps; 640 steps of 4 states; full DeltaGN not trained
#             (its cost is measured instead); 1 seed.
#   Test: 20 (N = 100) and 4 (N = 1000) trajectories of 200 steps, generated separately (data.seed=0 test split).
# Override the sizes with environment variables, e.g. E100=24 NT100=50 cli/nbody_table.sh
set -euo pipefail
OUT=${OUT:-outputs/nbody_table}
E100=${E100:-12}        # N = 100 epochs (100 steps each)
E1000=${E1000:-40}      # N = 1000 epochs (16 steps each)
EHOGN=${EHOGN:-6}       # HOGN epochs at N = 100 (100 steps of 4 states each)
NT100=${NT100:-20}      # N = 100 test trajectories
NT1000=${NT1000:-4}     # N = 1000 test trajectories
common=(paths.output_root=$OUT eval.plots=false)
quiet=(trainer.progress=false export=false)
# test sets: the data.seed=0 test split, 200 steps (train/val splits of one trajectory are generated unused)
eval100=(system=nbody100 data.n_train=1 data.n_val=1 data.n_test=$NT100 "${common[@]}")
eval1000=(system=nbody1000 data.n_train=1 data.n_val=1 data.n_test=$NT1000 "${common[@]}")

rm -rf "$OUT/train" "$OUT/eval" "$OUT/table"

train() {  # train <name> <overrides...>: one training run in $OUT/train/<name>
  local name=$1; shift
  mpsim train "$@" hydra.run.dir="$OUT/train/$name" "${common[@]}" "${quiet[@]}" > "$OUT/logs/$name.txt" 2>&1
}
evaluate() {  # evaluate <name> <checkpoint run> <overrides...>: test-set metrics in $OUT/eval/<name>
  local name=$1 run=$2; shift 2
  mpsim eval init="$OUT/train/$run/checkpoints/best.ckpt" "$@" hydra.run.dir="$OUT/eval/$name" \
    > "$OUT/logs/eval_$name.txt" 2>&1
}
mkdir -p "$OUT/logs"

chain100() {
  e100=(experiment=nbody100_cpu trainer.max_epochs=$E100)
  mpsim train model=constant_velocity trainer.max_epochs=0 hydra.run.dir="$OUT/eval/n100_cv" \
    "${eval100[@]}" "${quiet[@]}" > "$OUT/logs/n100_cv.txt" 2>&1
  for graph in hierarchical knn full; do
    train "n100_$graph" "${e100[@]}" model=deltagn model.graph=$graph
    evaluate "n100_$graph" "n100_$graph" "${eval100[@]}"
  done
}

chain1000() {
  e1000=(experiment=nbody1000_cpu trainer.max_epochs=$E1000 model.pairs_per_trajectory=4)
  mpsim train model=constant_velocity trainer.max_epochs=0 hydra.run.dir="$OUT/eval/n1000_cv" \
    "${eval1000[@]}" "${quiet[@]}" > "$OUT/logs/n1000_cv.txt" 2>&1
  for graph in hierarchical knn; do
    train "n1000_$graph" "${e1000[@]}" model=deltagn model.graph=$graph
    evaluate "n1000_$graph" "n1000_$graph" "${eval1000[@]}"
  done
  # the paper's HierHOGN at N = 100 (4 states per step: HOGN differentiates through 4 RK4 stages of ∂H)
  train n100_hogn_hierarchical experiment=nbody100_cpu trainer.max_epochs=$EHOGN model=hogn \
    model.graph=hierarchical model.pairs_per_trajectory=4 data.n_val=1 data.n_test=1
  evaluate n100_hogn_hierarchical n100_hogn_hierarchical "${eval100[@]}"
}

chain100 & pid100=$!
chain1000 & pid1000=$!
wait $pid100 && wait $pid1000

# generalisation to an unseen N (the paper's Figure 5): models trained at N = 100, evaluated at N = 1000
for graph in hierarchical knn; do
  evaluate "n100_${graph}_at_1000" "n100_$graph" "${eval1000[@]}"
done

runs=(n100_cv n100_knn n100_full n100_hierarchical n100_hogn_hierarchical n1000_cv n1000_knn n1000_hierarchical
      n100_knn_at_1000 n100_hierarchical_at_1000)
list=$(printf "$OUT/eval/%s," "${runs[@]}")
mpsim bench bench=nbody_table "bench.runs=[${list%,}]" "bench.cost_only=[deltagn:full:1000]" bench.train_states=1 \
  hydra.run.dir="$OUT/table" paths.output_root=$OUT
mpsim report "runs=[$OUT/train]" "title='N-body training runs (validation/test: 200-step rollouts of 2 trajectories)'" \
  "columns=[initial_test_error,min_test_error,min_test_error_epoch,test_error,wall_time]" \
  hydra.run.dir="$OUT/report" paths.output_root=$OUT
echo "table: $OUT/table/bench.md; training runs: $OUT/report/report.md"
