#!/usr/bin/env bash
# Issue 71, cases a-c: the residual loop on recordings with latent states (cli/loop_cases.py: a_osc_two — an
# oscillator at 8.6 samples a period, output only, with a cubic stiffness and an output offset; b_tank_leak — a seepage
# from the unmeasured upper tank) and on a closed-loop axis recorded 25 s at 1 kHz, cut into 1 s segments at
# data.stride=10 (cli/measured_cases.py b_axis_coulomb --seconds 25). Each recording and its clean twin: fit the
# nominal model (trainer=whitebox), then `mpsim diagnose fix=true`; the verdict and what was named are printed.
#   OUT=outputs/loop_cases CASES="a_osc_two b_tank_leak c_axis_stride" JOBS=2 bash cli/loop_cases.sh
set -uo pipefail
OUT=${OUT:-outputs/loop_cases}
ALL="a_osc_two a_osc_two_noisy b_tank_leak c_axis_stride"
CASES=${CASES:-$ALL}
JOBS=${JOBS:-2}
HERE=$(cd "$(dirname "$0")" && pwd)
source "$HERE/lib.sh"
# shellcheck disable=SC2086 # word lists
check_choices loop_cases.sh CASES $ALL
check_counts loop_cases.sh JOBS
mkdir -p "$OUT/data"
python "$HERE/loop_cases.py" "$OUT/data" || exit 1
python "$HERE/measured_cases.py" "$OUT/data" --cases b_axis_coulomb --seconds 25 || exit 1

launch() {
  while (( $(jobs -rp | wc -l) >= JOBS )); do wait -n; done
  "$@" &
}

run() {  # case variant
  local case=$1 variant=$2 start=$SECONDS spec csv keys run
  run=$OUT/$case/$variant
  if [[ $case == c_axis_stride ]]; then
    spec=$OUT/data/b_axis_coulomb/model.yaml
    csv=$OUT/data/b_axis_coulomb/b_axis_coulomb$([[ $variant == clean ]] && echo _clean).csv
    keys=(data.control_columns=[u] data.observed=[q] data.segment=1.0 data.input_hold=zoh "data.columns={q: enc_pos}" data.stride=10)
  else
    spec=$OUT/data/$case/model.yaml
    csv=$OUT/data/$case/$case$([[ $variant == clean ]] && echo _clean).csv
    mapfile -t keys < <(python -c "import json,sys; print('\n'.join(json.load(open(sys.argv[1]))['keys']))" "$OUT/data/$case/truth.json")
    keys+=(data.control_columns=[u])
  fi
  rm -rf "$run" && mkdir -p "$run"
  mpsim train model=equations model.spec="$spec" trainer=whitebox data.path="$csv" "${keys[@]}" \
    hydra.run.dir="$run/train" paths.ckpt_dir="$run/checkpoints" trainer.progress=false > "$run.log" 2>&1 \
    || { echo "$case/$variant: train failed (see $run.log)"; return; }
  local trained=$SECONDS
  mpsim diagnose init="$run/train/checkpoints/best.ckpt" data.path="$csv" "${keys[@]}" fix=true \
    hydra.run.dir="$run/diagnose" paths.ckpt_dir="$run/checkpoints" trainer.progress=false >> "$run.log" 2>&1
  echo "$case/$variant: exit $?, train $(( trained - start )) s, diagnose $(( SECONDS - trained )) s"
}

for case in $CASES; do
  for variant in recording clean; do launch run "$case" "$variant"; done
done
wait
for case in $CASES; do
  for variant in recording clean; do
    echo "== $case / $variant"
    grep -h -A3 " verdict" "$OUT/$case/$variant.log" | grep -v "^--" | cut -c1-220
  done
done
