#!/usr/bin/env bash
# Residual-loop scorecard (issue 11): every case is simulated by a generator in the repo, the nominal model is a
# `model=equations` spec (examples/diagnose_cases/) or a built-in, and `mpsim diagnose fix=true` runs on it.
# Prints one table: case, truth, verdict, effect named, coefficient error, held-out error before → after, wall time.
#   CASES="a_damped a_undamped b_vdp c_kuramoto_lag d_chain_friction e_pendulum_sin2 f_kuramoto_harm2 g_delay g_delay_clean
#         h_drift h_drift_clean i_bias i_bias_clean j_semieuler j_semieuler_clean k_chaos_drive k_chaos_drive_clean
#         l_chain_node l_chain_node_clean case1 case2 case2_clean clean" (default: all). `<case>_clean` is a case's
#         clean twin (its data spec, or its own `<case>_clean_data.yaml`, with nothing hidden): judged as "nothing".
#   G_DELAY_EFFECT / K_CHAOS_EFFECT: the hidden effects of cases g and k (below), one YAML flow mapping each
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
# the hidden effects of cases g and k (spec files g_delay_*.yaml, k_chaos_drive_*.yaml); the scorer reads its truth
# from these same two values, so an override changes the data and the truth together
G_DELAY_EFFECT=${G_DELAY_EFFECT:-"{_target_: mpsim.effects.DelayedFeedback, coef: -0.8, delay: 0.125, target: omega}"}
K_CHAOS_EFFECT=${K_CHAOS_EFFECT:-"{_target_: mpsim.effects.PeriodicForcing, amplitude: 4.0, omega: 7.0, phase: 0.0, target: y, random_phase: true, phase_seed: 0}"}
ALL_CASES="a_damped a_undamped b_vdp c_kuramoto_lag d_chain_friction e_pendulum_sin2 f_kuramoto_harm2 g_delay g_delay_clean
  h_drift h_drift_clean i_bias i_bias_clean j_semieuler j_semieuler_clean k_chaos_drive k_chaos_drive_clean l_chain_node
  l_chain_node_clean case1 case2 case2_clean clean"
CASES=${CASES:-$ALL_CASES}
source "$(dirname "$0")/lib.sh"
# shellcheck disable=SC2086  # the list splits into words on purpose
check_choices diagnose_cases.sh CASES $ALL_CASES
CASES=$(echo $CASES)  # one line, one space between names (has() matches " name ")
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
# issue 61's cases. h and l write their effect into the data's equations (a system cannot carry a ParameterDrift; the
# one-node damping is a per-node parameter there, another generator than the effect's own `nodes=[2]`), so their
# twins have their own data spec (<case>_clean_data.yaml)
has h_drift && launch spec_case h_drift h_drift_data.yaml h_drift_model.yaml
has l_chain_node && launch spec_case l_chain_node l_chain_node_data.yaml l_chain_node_model.yaml
has j_semieuler && launch spec_case j_semieuler j_semieuler_data.yaml j_semieuler_model.yaml \
  'system.effects=[{_target_: mpsim.effects.LinearDamping, coef: 0.15, target: v}]'
has i_bias && launch spec_case i_bias i_bias_data.yaml i_bias_model.yaml \
  'system.effects=[{_target_: mpsim.effects.Bias, coef: 0.1, target: x}]'
# a case whose spec files are missing (a trimmed checkout) is skipped with a note
spec_files() { [[ -f $C/$1 && -f $C/$2 ]] || { echo "$3: skipped, $C/$1 or $C/$2 is missing"; return 1; }; }
has g_delay && spec_files g_delay_data.yaml g_delay_model.yaml g_delay &&
  launch spec_case g_delay g_delay_data.yaml g_delay_model.yaml "system.effects=[$G_DELAY_EFFECT]"
has k_chaos_drive && spec_files k_chaos_drive_data.yaml k_chaos_drive_model.yaml k_chaos_drive &&
  launch spec_case k_chaos_drive k_chaos_drive_data.yaml k_chaos_drive_model.yaml "system.effects=[$K_CHAOS_EFFECT]"
# clean twins (judged as "nothing"): <case>_clean runs <case>_clean_data.yaml if there is one, else the case's own
# data spec, with no effects
twin() {  # twin CASE DATA_STEM MODEL_SPEC
  local data=$2_data.yaml
  [[ -f $C/$1_clean_data.yaml ]] && data=$1_clean_data.yaml
  has "$1_clean" && spec_files "$data" "$3" "$1_clean" && launch spec_case "$1_clean" "$data" "$3"
}
twin h_drift h_drift h_drift_model.yaml
twin l_chain_node l_chain_node l_chain_node_model.yaml
twin j_semieuler j_semieuler j_semieuler_model.yaml
twin i_bias i_bias i_bias_model.yaml
twin g_delay g_delay g_delay_model.yaml
twin k_chaos_drive k_chaos_drive k_chaos_drive_model.yaml
has case1 && launch case1
if has clean; then
  for noise in $NOISES; do
    for s in $SEEDS; do launch clean "$noise" "$s"; done
  done
fi
wait

G_DELAY_EFFECT=$G_DELAY_EFFECT K_CHAOS_EFFECT=$K_CHAOS_EFFECT python - "$OUT" <<'PY'
import json, math, os, sys
from pathlib import Path

import yaml

out = Path(sys.argv[1])


def truth_from(effect_yaml):
    """A case's truth from its `system.effects` entry (a YAML flow mapping): a drive's omega (3 %), a delay's τ and
    its gain (10 % each), else coef (10 %)."""
    e = yaml.safe_load(effect_yaml)
    kind = e["_target_"].rsplit(".", 1)[-1]
    if kind == "PeriodicForcing":
        return (kind, e["target"], "omega", float(e["omega"]), 0.03)
    if kind == "DelayedFeedback":
        return (kind, e["target"], "delay", float(e["delay"]), 0.10, {"also": {"coef": float(e["coef"])}})
    return (kind, e["target"], "coef", float(e["coef"]), 0.10)


# what each case holds: (kind, target row, reported key, true value, bound[, where]); None: nothing to name. A
# coupling's harmonic k > 1 is part of its kind: "SineCoupling(k=2)". `where` narrows the match: {"node": i} an
# effect on node i alone (labelled "..., node i)", its value under key or "key[node i]"), {"param": p} the
# drifting parameter of a ParameterDrift (whose reported value is its rate "s"); {"also": {key: value}} more values
# that must each be within the bound too (a delay's gain beside its τ)
TRUTH = {
    "a_damped": ("LinearDamping", "v", "coef", 0.3, 0.10),
    "a_undamped": None,
    "b_vdp": ("PeriodicForcing", "v", "omega", 3.1, 0.03),
    "c_kuramoto_lag": ("CosineCoupling", "theta", "coef", -0.4 * math.sin(0.25), 0.10),
    "d_chain_friction": ("DryFriction", "v", "coef", 0.5, 0.10),
    "e_pendulum_sin2": "unexplained",
    "f_kuramoto_harm2": ("SineCoupling(k=2)", "theta", "coef", 0.25, 0.10),
    "case1": ("LinearDamping", "omega", "coef", 0.2, 0.10),
    "case2": ("PeriodicForcing", "x", "omega", 20.0, 0.03),
    "g_delay": truth_from(os.environ["G_DELAY_EFFECT"]),
    "h_drift": ("ParameterDrift", "v", "s", 0.04, 0.10, {"param": "k"}),
    "i_bias": ("Bias", "x", "coef", 0.1, 0.10),
    "j_semieuler": ("LinearDamping", "v", "coef", 0.15, 0.10),
    "k_chaos_drive": truth_from(os.environ["K_CHAOS_EFFECT"]),
    "l_chain_node": ("LinearDamping", "v", "coef", 0.3, 0.10, {"node": 2}),
}
for case in ("g_delay", "h_drift", "i_bias", "j_semieuler", "k_chaos_drive", "l_chain_node"):
    TRUTH[f"{case}_clean"] = None  # the clean twins
rows, clean = [], []


def kind_of(t):  # a named effect's kind, with its harmonic when k > 1 ("SineCoupling(k=2)")
    k = (t.get("effect") or {}).get("harmonic", 1)
    return t["kind"] if k == 1 else f"{t['kind']}(k={k})"


def matches(t, where):  # a named effect on the node / of the parameter the truth says (see TRUTH)
    effect = t.get("effect") or {}
    if "node" in where:
        i = where["node"]
        return f"node {i})" in t["label"] or f"node {i}," in t["label"] or effect.get("nodes") in ([i], i)
    if "param" in where:
        return effect.get("param") == where["param"] or f"({where['param']})" in t["label"]
    return True


def value_of(values, key, where):  # the reported value under key, or a per-node effect's "key[node i]"
    if key in values:
        return values[key]
    return values.get(f"{key}[node {where['node']}]") if "node" in where else None


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
    truth = TRUTH.get(case.split("/")[0], "unknown")
    coef_err, ok = "", not worse
    if truth == "unknown" and not case.startswith("clean"):
        truth_text, ok = "? (no truth for this case)", False
    elif case.startswith("clean") or truth is None:
        truth_text = "nothing"
        ok = ok and not named
        clean.append(not named)
    elif truth == "unexplained":
        truth_text = "sin 2θ torque (outside the library)"
        ok = ok and r["verdict"] == "unexplained structured residual"
    else:
        kind, row, key, value, bound = truth[:5]
        where = dict(truth[5]) if len(truth) > 5 else {}
        base, _, k = kind.partition("(")
        also = where.pop("also", {})
        inside = [row] + ([k.rstrip(")")] if k else []) + [f"{n} {v}" for n, v in where.items()]
        truth_text = f"{base}({', '.join(inside)}) " + ", ".join(f"{n} {v:.4g}" for n, v in {key: value, **also}.items())
        hit = [t for t in named if kind_of(t) == kind and t["label"].startswith(f"d{row}/dt") and matches(t, where)]
        wanted = {key: value, **also}
        got = {n: value_of(hit[0]["values"], n, where) for n in wanted} if hit else {}
        if got and all(v is not None for v in got.values()):
            rels = {n: abs(got[n] - v) / abs(v) for n, v in wanted.items()}
            coef_err = ", ".join(f"{rels[n]:.1%}" + (f" ({n})" if len(rels) > 1 else "") for n in rels)
            ok = ok and max(rels.values()) <= bound and len(named) == 1
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
