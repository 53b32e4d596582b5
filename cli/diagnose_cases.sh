#!/usr/bin/env bash
# Residual-loop scorecard (issue 11): every case is simulated by a generator in the repo, the nominal model is a
# `model=equations` spec (examples/diagnose_cases/) or a built-in, and `mpsim diagnose fix=true` runs on it.
# Prints one table: case, truth, verdict, effect named, coefficient error, held-out error before → after, wall time.
#   CASES="a_damped a_undamped b_vdp c_kuramoto_lag d_chain_friction e_pendulum_sin2 f_kuramoto_harm2 case1 case2 case2_clean
#         clean" (default: all)
#   SEEDS / NOISES: data seeds × measurement-noise levels of the clean runs (false-positive rate)
#   JOBS: runs at once (default 1). Each run (a case, or one clean seed × noise) keeps its data, checkpoints and
#         log in its own folder, so runs never share a file; give each a core (the runs are single-threaded).
#         A run is redone whole: its folder is removed first (mpsim refuses to write over an earlier run).
set -uo pipefail
OUT=${OUT:-outputs/diagnose_cases}
C=examples/diagnose_cases
SEEDS=${SEEDS:-"0 1 2 3 4"}
NOISES=${NOISES:-"0 0.01"}
JOBS=${JOBS:-1}
CASES=${CASES:-"a_damped a_undamped b_vdp c_kuramoto_lag d_chain_friction e_pendulum_sin2 f_kuramoto_harm2 case1 case2 case2_clean clean"}
source "$(dirname "$0")/lib.sh"
check_choices diagnose_cases.sh CASES a_damped a_undamped b_vdp c_kuramoto_lag d_chain_friction e_pendulum_sin2 \
  f_kuramoto_harm2 case1 case2 case2_clean clean
check_counts diagnose_cases.sh JOBS
SEEDS=${SEEDS//,/ }; NOISES=${NOISES//,/ }
mkdir -p "$OUT"
has() { [[ " $CASES " == *" $1 "* ]]; }
# launch CMD...: runs CMD in the background once fewer than JOBS runs are under way
launch() {
  while (( $(jobs -rp | wc -l) >= JOBS )); do wait -n; done
  "$@" &
}
# opts RUN: the settings every command of a run shares (its own checkpoint folder)
opts() { echo "paths.ckpt_dir=$1/checkpoints trainer.progress=false"; }

# spec_case NAME DATA_SPEC MODEL_SPEC [simulate overrides...]: simulate 64 recordings, fit the nominal model,
# diagnose with fix=true (exit codes 0/10/11 are verdicts, not failures)
spec_case() {
  local name=$1 data=$2 model=$3; shift 3
  local run=$OUT/$name start=$SECONDS
  rm -rf "$run" && mkdir -p "$run"
  mpsim simulate system=equations system.spec=$C/$data system.name=$name "$@" n=64 format=npz \
    hydra.run.dir=$run/data > "$run.log" 2>&1 || { echo "$name: simulate failed (see $run.log)"; return; }
  mpsim train model=equations model.spec=$C/$model data.path=$run/data/trajectories.npz trainer=whitebox \
    hydra.run.dir=$run/train $(opts "$run") >> "$run.log" 2>&1 || { echo "$name: train failed (see $run.log)"; return; }
  mpsim diagnose init=$name.ckpt data.path=$run/data/trajectories.npz fix=true hydra.run.dir=$run/diagnose \
    $(opts "$run") >> "$run.log" 2>&1
  echo "$(( SECONDS - start ))" > "$run/wall_s"
}

# case 1 (docs/residual_loop.md): pendulum pair, hidden damping 0.2, built-in white-box `physics` model
case1() {
  local run=$OUT/case1 start=$SECONDS
  rm -rf "$run" && mkdir -p "$run"
  { mpsim train experiment=pendulum_damped hydra.run.dir=$run/train $(opts "$run") &&
    mpsim diagnose experiment=pendulum_damped init=pendulum2_damped.ckpt fix=true hydra.run.dir=$run/diagnose \
      $(opts "$run"); } > "$run.log" 2>&1
  echo "$(( SECONDS - start ))" > "$run/wall_s"
}

# case 2 (docs/residual_loop.md): Lorenz3 with a hidden drive dx/dt += 20 sin(20 t); black-box MP-NODE.
# fix=true judges a network's candidates by finetuning: each candidate + 80 epochs against the same 80 epochs
# without it (the control, under diagnose/fix/round1/control), at the full learning rate (the network must
# unlearn what it made up for once the drive is explicit)
case2() {
  local run=$OUT/case2 start=$SECONDS
  rm -rf "$run" && mkdir -p "$run"
  { mpsim train experiment=lorenz3_forced hydra.run.dir=$run/train $(opts "$run") &&
    mpsim diagnose experiment=lorenz3_forced init=lorenz3_forced.ckpt fix=true diagnose.fix_lr_factor=1.0 \
      trainer.max_epochs=80 hydra.run.dir=$run/diagnose $(opts "$run"); } > "$run.log" 2>&1
  echo "$(( SECONDS - start ))" > "$run/wall_s"
}

# case 2's black-box twin without the drive: nothing may be named (a false-positive check)
case2_clean() {
  local run=$OUT/clean/case2_clean start=$SECONDS
  local clean2=(experiment=lorenz3_forced "system.effects=[]" system.name=lorenz3_clean)
  rm -rf "$run" && mkdir -p "$run"
  { mpsim train "${clean2[@]}" hydra.run.dir=$run/train $(opts "$run") &&
    mpsim diagnose "${clean2[@]}" init=lorenz3_clean.ckpt fix=true diagnose.fix_lr_factor=1.0 \
      trainer.max_epochs=80 hydra.run.dir=$run/diagnose $(opts "$run"); } > "$run.log" 2>&1
  echo "$(( SECONDS - start ))" > "$run/wall_s"
}

# clean NOISE SEED: the pendulum pair without its damping, one data seed and noise level (a false-positive check)
clean() {
  local noise=$1 s=$2
  local run=$OUT/clean/noise$noise/seed$s start=$SECONDS
  local clean=(experiment=pendulum_damped "system.effects=[]" system.name=pendulum2_clean data.seed=$s
    data.noise_std=$noise)
  rm -rf "$run" && mkdir -p "$run"
  { mpsim train "${clean[@]}" hydra.run.dir=$run/train $(opts "$run") &&
    mpsim diagnose "${clean[@]}" init=pendulum2_clean.ckpt fix=true hydra.run.dir=$run/diagnose \
      $(opts "$run"); } > "$run.log" 2>&1
  echo "$(( SECONDS - start ))" > "$run/wall_s"
}

# the longest first, so that JOBS > 1 ends soonest
has case2 && launch case2
has a_damped && launch spec_case a_damped a_chain_data.yaml a_chain_model.yaml \
  'system.effects=[{_target_: mpsim.effects.LinearDamping, coef: 0.3, target: v}]'
has case2_clean && launch case2_clean
has a_undamped && launch spec_case a_undamped a_chain_data.yaml a_chain_model.yaml
has d_chain_friction && launch spec_case d_chain_friction d_chain_friction_data.yaml d_chain_friction_model.yaml \
  'system.effects=[{_target_: mpsim.effects.DryFriction, coef: 0.5, target: v, scale: 0.001}]'
has b_vdp && launch spec_case b_vdp b_vdp_data.yaml b_vdp_model.yaml \
  'system.effects=[{_target_: mpsim.effects.PeriodicForcing, amplitude: 1.5, omega: 3.1, phase: 0.0, target: v, random_phase: true, phase_seed: 0}]'
has e_pendulum_sin2 && launch spec_case e_pendulum_sin2 e_pendulum_sin2_data.yaml e_pendulum_sin2_model.yaml
has c_kuramoto_lag && launch spec_case c_kuramoto_lag c_kuramoto_lag_data.yaml c_kuramoto_lag_model.yaml
has f_kuramoto_harm2 && launch spec_case f_kuramoto_harm2 f_kuramoto_harm2_data.yaml f_kuramoto_harm2_model.yaml \
  'system.effects=[{_target_: mpsim.effects.SineCoupling, coef: 0.25, target: theta, harmonic: 2}]'
has case1 && launch case1
if has clean; then
  for noise in $NOISES; do
    for s in $SEEDS; do launch clean "$noise" "$s"; done
  done
fi
wait

python - "$OUT" <<'PY'
import json, sys
from pathlib import Path
out = Path(sys.argv[1])
# what each case holds: (kind, target row, reported key, true value, bound); None: nothing to name. A coupling's
# harmonic k > 1 is part of its kind: "SineCoupling(k=2)"
TRUTH = {
    "a_damped": ("LinearDamping", "v", "coef", 0.3, 0.10),
    "a_undamped": None,
    "b_vdp": ("PeriodicForcing", "v", "omega", 3.1, 0.03),
    "c_kuramoto_lag": ("CosineCoupling", "theta", "coef", -0.4 * __import__("math").sin(0.25), 0.10),
    "d_chain_friction": ("DryFriction", "v", "coef", 0.5, 0.10),
    "e_pendulum_sin2": "unexplained",
    "f_kuramoto_harm2": ("SineCoupling(k=2)", "theta", "coef", 0.25, 0.10),
    "case1": ("LinearDamping", "omega", "coef", 0.2, 0.10),
    "case2": ("PeriodicForcing", "x", "omega", 20.0, 0.03),
}
rows, clean = [], []


def kind_of(t):  # a named effect's kind, with its harmonic when k > 1 ("SineCoupling(k=2)")
    k = (t.get("effect") or {}).get("harmonic", 1)
    return t["kind"] if k == 1 else f"{t['kind']}(k={k})"


for d in sorted(out.rglob("diagnose/diagnosis.json")):
    case = d.parent.parent.relative_to(out).as_posix()
    r = json.loads(d.read_text())
    wall = (d.parent.parent / "wall_s").read_text().strip() if (d.parent.parent / "wall_s").exists() else "?"
    if "error" in r:
        rows.append((case, "?", "ERROR", r["error"][:60], "", "", wall, "no"))
        continue
    named = r["effects_named"]
    label = "; ".join(f"{t['label']} ({', '.join(f'{k} {v:.4g}' for k, v in t['values'].items())})" for t in named)
    b, a = r["before"]["rollout_rmse"], (r["after"] or {}).get("rollout_rmse")
    err_text = f"{b:.3g} → {a:.3g}" if a is not None else f"{b:.3g} (unchanged)"
    worse = a is not None and a > b
    truth = TRUTH.get(case.split("/")[0])
    coef_err, ok = "", not worse
    if case.startswith("clean") or truth is None:
        truth_text = "nothing"
        ok = ok and not named
        clean.append(not named)
    elif truth == "unexplained":
        truth_text = "sin 2θ torque (outside the library)"
        ok = ok and r["verdict"] == "unexplained structured residual"
    else:
        kind, row, key, value, bound = truth
        base, _, k = kind.partition("(")
        truth_text = f"{base}({row}{', ' + k.rstrip(')') if k else ''}) {key} {value:.4g}"
        hit = [t for t in named if kind_of(t) == kind and t["label"].startswith(f"d{row}/dt")]
        if hit:
            rel = abs(hit[0]["values"][key] - value) / abs(value)
            coef_err = f"{rel:.1%}"
            ok = ok and rel <= bound and len(named) == 1
        else:
            ok = False
    rows.append((case, truth_text, r["verdict"], label or "—", coef_err, err_text, wall, "yes" if ok else "NO"))
lines = ["| case | truth | verdict | effect named (fitted) | coefficient error | held-out rollout RMSE before → after | "
         "wall s | holds |", "|---|---|---|---|---|---|---|---|"]
lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
if clean:
    lines += ["", f"False positives on clean data: {len(clean) - sum(clean)} of {len(clean)} runs."]
text = "\n".join(lines)
(out / "scorecard.md").write_text(text + "\n")
print(text)
PY
