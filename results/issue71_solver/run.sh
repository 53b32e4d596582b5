#!/usr/bin/env bash
# dopri5 (default) vs rk4 (one step per sample) for `mpsim diagnose` (fix=false) on issue 60's measured-style cases
# run from the repository root with mpsim importable

OUT=${OUT:-outputs/issue71_solver}
mkdir -p "$OUT"
python cli/measured_cases.py $OUT/data > $OUT/gen.log
keys() {
  local k=("data.control_columns=[u]" "data.observed=[q]" "data.segment=1.0" "data.input_hold=zoh")
  case $1 in
    b_axis_coulomb*) k+=("data.columns={q: enc_pos}");;
    d_input_gain) k+=(data.time_column=null data.dt=0.002);;
  esac
  [[ $1 == *_stride10 ]] && k+=(data.stride=10)
  printf '%s\n' "${k[@]}"
}
for run in b_axis_coulomb c_duffing d_input_gain d_deadzone b_axis_coulomb_stride10; do
  case=${run%_stride10}
  mapfile -t K < <(keys $run)
  R=$OUT/$run
  mkdir -p $R
  s=$SECONDS
  python -m mpsim train model=equations model.spec=$OUT/data/$case/model.yaml trainer=whitebox data.path=$OUT/data/$case/$case.csv "${K[@]}" hydra.run.dir=$R/train paths.ckpt_dir=$R/ckpt trainer.progress=false > $R/train.log 2>&1
  echo "$run train rc=$? $((SECONDS-s)) s" >> $OUT/summary.txt
  for solver in dopri5 rk4; do
    s=$SECONDS
    python -m mpsim diagnose init=$R/train/checkpoints/best.ckpt data.path=$OUT/data/$case/$case.csv "${K[@]}" solver=$solver hydra.run.dir=$R/diag_$solver paths.ckpt_dir=$R/ckpt trainer.progress=false > $R/diag_$solver.log 2>&1
    echo "$run $solver rc=$? $((SECONDS-s)) s" >> $OUT/summary.txt
  done
done
echo done >> $OUT/summary.txt
