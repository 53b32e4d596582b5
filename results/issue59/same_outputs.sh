#!/usr/bin/env bash
# Same outputs before and after issue 59: runs the same commands with two source trees and compares what they wrote.
#   results/issue59/same_outputs.sh BEFORE_TREE AFTER_TREE [WORK]
# Each tree runs with its own .venv if it has one (else the python on PATH), with PYTHONPATH=TREE/src, in its own
# folder WORK/before or WORK/after (so the two never share a data cache); the imported mpsim is checked to be the
# tree's. SUITE=0 leaves out the default test suite and cli/smoke.sh (the slow part); CASE1=0 leaves out the
# second diagnose case; RUN=0 runs nothing and compares what an earlier run left in WORK. The comparer runs with
# AFTER_TREE's .venv if it has one. Prints one table row per comparison; exit 1 if anything differs or fails.
set -uo pipefail
BEFORE=$(cd "$1" && pwd) AFTER=$(cd "$2" && pwd)
WORK=${3:-$(mktemp -d -t mpsim-same-XXXXXX)}
SUITE=${SUITE:-1} CASE1=${CASE1:-1} RUN=${RUN:-1}
HERE=$(cd "$(dirname "$0")" && pwd)
mkdir -p "$WORK" && WORK=$(cd "$WORK" && pwd)
rows=() failed=0
row() { rows+=("| $1 | $2 | $3 |"); [[ $3 == same* || $3 == ok* ]] || failed=1; }

# the commands both trees run, from inside WORK/<label>; every output folder is named here
recipes() {
  local tree=$1 spec=$1/examples/equations/pendulums_linear_spring.yaml q=(trainer.progress=false paths.ckpt_dir=ckpt)
  mpsim train system=lorenz3 trainer.max_epochs=5 data.n_train=16 data.n_val=4 data.n_test=4 data.horizon=20 \
    seed=0 hydra.run.dir=train_lorenz3 "${q[@]}" &&
  mpsim simulate system=lorenz3 n=4 data.horizon=20 format=npz hydra.run.dir=sim_lorenz3 &&
  mpsim simulate system=lorenz10 init=lorenz3.ckpt n=2 data.horizon=20 format=npz hydra.run.dir=sim_model \
    paths.ckpt_dir=ckpt &&
  mpsim simulate system=equations system.spec="$spec" n=20 format=csv out=pend hydra.run.dir=sim_eq &&
  mpsim train model=equations model.spec="$spec" 'model.init={g: 9.0, k: 2.5}' data.path=sim_eq/pend.csv \
    trainer=whitebox eval.horizons=[1,10] hydra.run.dir=train_eq "${q[@]}" || return 1
  # cli/diagnose_cases.sh's cheapest case (clean/noise0/seed0), then case1 (an effect named and fitted)
  local clean=(experiment=pendulum_damped "system.effects=[]" system.name=pendulum2_clean data.seed=0 data.noise_std=0)
  mpsim train "${clean[@]}" hydra.run.dir=diag_clean/train "${q[@]}" &&
  mpsim diagnose "${clean[@]}" init=pendulum2_clean.ckpt fix=true hydra.run.dir=diag_clean/diagnose "${q[@]}"
  local code=$?
  [[ $code == 0 || $code == 10 || $code == 11 ]] || return 1 # verdicts, not failures
  [[ $CASE1 == 1 ]] || return 0
  mpsim train experiment=pendulum_damped hydra.run.dir=diag_case1/train "${q[@]}" &&
  mpsim diagnose experiment=pendulum_damped init=pendulum2_damped.ckpt fix=true hydra.run.dir=diag_case1/diagnose \
    "${q[@]}"
  code=$?
  [[ $code == 0 || $code == 10 || $code == 11 ]]
}

# run LABEL TREE: the recipes, then (SUITE=1) the default suite and the smoke run; wall seconds in WORK/LABEL.times
run() {
  local label=$1 tree=$2 w=$WORK/$1 start
  rm -rf "$w" && mkdir -p "$w"
  (
    cd "$w" || exit 1
    [[ -d $tree/.venv ]] && export PATH="$tree/.venv/bin:$PATH"
    export PYTHONPATH=$tree/src
    where=$(python -c 'import mpsim; print(mpsim.__file__)')
    [[ $where == "$tree/src/mpsim/__init__.py" ]] || { echo "$label imports $where, not $tree"; exit 1; }
    echo "$label: $(git -C "$tree" rev-parse --short HEAD) $where" > imported.txt
    start=$SECONDS
    recipes "$tree" > recipes.log 2>&1 && echo "recipes $((SECONDS - start))" >> times || echo "recipes FAILED" >> times
    [[ $SUITE == 1 ]] || exit 0
    start=$SECONDS
    (cd "$tree" && python -m pytest -q -p no:cacheprovider) > suite.log 2>&1
    rc=$?
    echo "suite $((SECONDS - start)) rc=$rc" >> times
    start=$SECONDS
    SMOKE_DIR=$w/smoke bash "$tree/cli/smoke.sh" > smoke.log 2>&1
    rc=$?
    echo "smoke $((SECONDS - start)) rc=$rc" >> times
  ) || exit 1
}

echo "work folder: $WORK"
if [[ $RUN == 1 ]]; then
  run before "$BEFORE"
  run after "$AFTER"
fi
PY=python && [[ -x $AFTER/.venv/bin/python ]] && PY=$AFTER/.venv/bin/python
cat "$WORK/before/imported.txt" "$WORK/after/imported.txt"

compare() { # compare ITEM KIND FILE
  local note
  note=$("$PY" "$HERE/compare.py" "$2" "$WORK/before/$3" "$WORK/after/$3" 2>&1 | tail -1)
  row "$1" "$3" "$note"
}
for label in before after; do
  grep -q "recipes FAILED" "$WORK/$label/times" && row "recipes ($label)" "$label/recipes.log" "FAILED"
done
compare "train lorenz3 (MP-NODE, 5 epochs)" csv train_lorenz3/metrics.csv
compare "" ckpt train_lorenz3/checkpoints/best.ckpt
compare "" ckpt train_lorenz3/checkpoints/last.ckpt
compare "" json train_lorenz3/summary.json
compare "simulate lorenz3 (the system)" npz sim_lorenz3/trajectories.npz
compare "simulate lorenz10 from lorenz3.ckpt (the model)" npz sim_model/trajectories.npz
compare "simulate system=equations (csv)" bytes sim_eq/pend.csv
compare "train model=equations (white-box fit)" csv train_eq/metrics.csv
compare "" ckpt train_eq/checkpoints/best.ckpt
compare "" json train_eq/summary.json
for case in clean $([[ $CASE1 == 1 ]] && echo case1); do
  compare "diagnose $case: its training" csv diag_$case/train/metrics.csv
  compare "" ckpt diag_$case/train/checkpoints/best.ckpt
  compare "diagnose $case fix=true" json diag_$case/diagnose/diagnosis.json
done
[[ $CASE1 == 1 ]] && compare "" ckpt diag_case1/diagnose/fix/round1/fixed.ckpt
# tally LOG: the suite's outcome counts from its progress lines (the addopts' -q and ours make -qq: no summary line)
tally() {
  grep -E '^[.sFExX]+ *\[ *[0-9]+%\]$' "$1" | sed 's/ *\[.*//' | tr -d '\n' | fold -w1 | sort | uniq -c |
    awk '{n[$2]=$1} END {printf "%d passed, %d failed, %d skipped, %d errors", n["."], n["F"], n["s"], n["E"]}'
}
if [[ $SUITE == 1 ]]; then
  for part in suite smoke; do
    for label in before after; do
      read -r _ secs rc < <(grep "^$part " "$WORK/$label/times" || echo "$part ? rc=missing")
      if [[ $part == suite ]]; then
        what=$(tally "$WORK/$label/suite.log")
      else
        what=$(tail -1 "$WORK/$label/smoke.log" | sed "s|$WORK/||")
      fi
      [[ $rc == rc=0 ]] && result="ok, $secs s: $what" || result="FAILED ($rc), $secs s: $what"
      row "$([[ $part == suite ]] && echo 'python -m pytest -q' || echo 'bash cli/smoke.sh')" "$label" "$result"
    done
  done
fi
echo
echo "| compared | file (in WORK/before and WORK/after) | result |"
echo "|---|---|---|"
printf '%s\n' "${rows[@]}"
for label in before after; do echo "$label wall s: $(tr '\n' ' ' < "$WORK/$label/times")"; done
exit $failed
