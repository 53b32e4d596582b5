#!/usr/bin/env bash
# Issue 70, cases c: recordings whose latent states are no derivative of anything measured (tanks: the upper level),
# that a derivative cannot follow (oscillator: 8.6 samples a period), or all behind a sensor of |speed| (abs_speed).
# Each is generated (cli/latent_cases.py), fitted by its own nominal model (nothing missing) on its first samples,
# free-run on the rest, and scored: the latent estimate against the generator's truth, the free-run RMSE against the
# sensor's noise. Usage: OUT=outputs/latent bash cli/latent_cases.sh   (about 2 minutes on 2 cores)
set -euo pipefail
OUT=${OUT:-outputs/latent_cases}
HERE=$(cd "$(dirname "$0")" && pwd)
python "$HERE/latent_cases.py" "$OUT/data"
run() {  # case, observed, hold, train rows, test rows, segment (s), init samples
  local case=$1
  mpsim train model=equations "model.spec=$OUT/data/$case/model.yaml" trainer=whitebox \
    "data.path=$OUT/data/$case/$case.csv" "data.observed=[$2]" "data.input_hold=$3" \
    "data.train_range=$4" "data.test_range=$5" "data.segment=$6" "eval.init_samples=$7" \
    eval.save_predictions=true trainer.progress=false "paths.ckpt_dir=$OUT/checkpoints" "hydra.run.dir=$OUT/runs/$case"
  python "$HERE/latent_cases.py" "$OUT/data/$case" "$OUT/runs/$case" | tee "$OUT/runs/$case/score.json"
}
run tanks h2 zoh "[0,700]" "[700,1024]" 200 "${TANKS_INIT:-25}"
run oscillator q linear "[0,3000]" "[3000,4000]" 5 "${OSC_INIT:-9}"
run abs_speed y zoh "[0,1000]" "[1000,1500]" 1 "${ABS_INIT:-10}"
