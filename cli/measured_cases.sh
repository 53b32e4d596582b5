#!/usr/bin/env bash
# Residual-loop scorecard on measured-style data (issue 60): every case comes from a generator of our own
# (cli/measured_cases.py: numpy RK4, input held zero-order, positions only, sensor noise and quantisation), not
# from mpsim's simulator. Each case is one long wide CSV (t, position, u) cut into 1 s segments, a nominal
# `model=equations` spec with `inputs: [u]`, and a clean twin. For the recording and its twin: fit the nominal
# model (trainer=whitebox), then `mpsim diagnose fix=true`; cli/measured_scorecard.py prints the table.
# Case a, the real recordings, is cli/dfki_pendulum.sh (run here into <OUT>/a_dfki when CASES names a_dfki).
#   CASES="a_dfki b_axis_coulomb c_duffing d_input_gain d_deadzone" (default: all)
#   VARIANTS="recording clean" (default: both)
#   SEED: the generator's seed (default 0); RECORD_S: every recording's length in s (default: the case's, 20 or 30)
#   JOBS: runs at once (default 1); each run (a case's recording or twin) has its own folder and checkpoints
#   TRAIN_ARGS / DIAGNOSE_ARGS: extra overrides for every `mpsim train` / `mpsim diagnose` (e.g. trainer.max_epochs=10)
# Pass rule (cli/measured_scorecard.py): the right kind on the right row, coefficient within 10 %; "unexplained"
# with nothing named for the input-path cases; nothing named on a clean twin; no returned model worse than given.
set -uo pipefail
OUT=${OUT:-outputs/measured_cases}
SEED=${SEED:-0}
JOBS=${JOBS:-1}
ALL="a_dfki b_axis_coulomb c_duffing d_input_gain d_deadzone"
CASES=${CASES:-$ALL}
VARIANTS=${VARIANTS:-"recording clean"}
TRAIN_ARGS=${TRAIN_ARGS:-}
DIAGNOSE_ARGS=${DIAGNOSE_ARGS:-}
HERE=$(dirname "$0")
source "$HERE/lib.sh"
# shellcheck disable=SC2086 # the case lists are word lists
check_choices measured_cases.sh CASES $ALL
check_choices measured_cases.sh VARIANTS recording clean
check_counts measured_cases.sh JOBS
[[ $SEED =~ ^[0-9]+$ ]] || { echo "measured_cases.sh: SEED='$SEED' is not an integer >= 0" >&2; exit 2; }
mkdir -p "$OUT"
DATA=$OUT/data

# the data keys each case's file needs: the position column's name, and how time is given
data_keys() {
  local case=$1
  local keys=(data.control_columns=[u] data.observed=[q] data.segment=1.0 data.input_hold=zoh)
  case $case in
    b_axis_coulomb) keys+=("data.columns={q: enc_pos}");;  # the encoder's column name
    d_input_gain) keys+=(data.time_column=null data.dt=0.002);;  # no time column: a fixed sampling step
  esac
  printf '%s\n' "${keys[@]}"
}

launch() {
  while (( $(jobs -rp | wc -l) >= JOBS )); do wait -n; done
  "$@" &
}

# run CASE VARIANT: fit the nominal spec to the case's recording (or clean twin), then diagnose with fix=true
# (exit codes 0/10/11 are verdicts, not failures)
run() {
  local case=$1 variant=$2 start=$SECONDS
  local run=$OUT/$case/$variant csv
  csv=$DATA/$case/$case.csv
  [[ $variant == clean ]] && csv=$DATA/$case/${case}_clean.csv
  local keys
  mapfile -t keys < <(data_keys "$case")
  rm -rf "$run" && mkdir -p "$run"
  # shellcheck disable=SC2086 # TRAIN_ARGS / DIAGNOSE_ARGS are lists of overrides
  mpsim train model=equations model.spec="$DATA/$case/model.yaml" trainer=whitebox data.path="$csv" "${keys[@]}" \
    hydra.run.dir="$run/train" paths.ckpt_dir="$run/checkpoints" trainer.progress=false $TRAIN_ARGS \
    > "$run.log" 2>&1 || { echo "$case/$variant: train failed (see $run.log)"; echo "$(( SECONDS - start ))" > "$run/wall_s"; return; }
  # shellcheck disable=SC2086
  mpsim diagnose init="$run/train/checkpoints/best.ckpt" data.path="$csv" "${keys[@]}" fix=true \
    hydra.run.dir="$run/diagnose" paths.ckpt_dir="$run/checkpoints" trainer.progress=false $DIAGNOSE_ARGS \
    >> "$run.log" 2>&1
  echo "$(( SECONDS - start ))" > "$run/wall_s"
}

# the real recordings: their own recipe (train on three, diagnose held-out ones), no clean twin
real() {  # its wall_s: train + diagnose, written by the recipe
  OUT=$OUT/a_dfki bash "$HERE/dfki_pendulum.sh" > "$OUT/a_dfki.log" 2>&1 || echo "a_dfki: failed (see $OUT/a_dfki.log)"
}

length=()
[[ -n ${RECORD_S:-} ]] && length=(--seconds "$RECORD_S")
# shellcheck disable=SC2086,SC2116 # unquoted on purpose: one space between names
simulated=$(echo ${CASES//a_dfki/})
if [[ -n $simulated ]]; then
  python "$HERE/measured_cases.py" "$DATA" --seed "$SEED" --cases "${simulated// /,}" "${length[@]}" || exit 1
fi
[[ " $CASES " == *" a_dfki "* ]] && launch real
for case in $simulated; do
  for variant in $VARIANTS; do launch run "$case" "$variant"; done
done
wait
python "$HERE/measured_scorecard.py" "$OUT"
