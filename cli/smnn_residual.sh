#!/usr/bin/env bash
# Residual loop, case 3 (issue 4): S-MNN discovery with a library that lacks a term of the data.
# Lorenz1 with dx/dt += -0.005·x³ (experiment=lorenz_cubic_discovery); about 6 minutes on 2 cores.
#   1. degree-2 discovery (biased: it cannot express x³)
#   2. mpsim diagnose names the missing term (CubicStiffness on x)
#   3. rediscovery with x³ added to the library (model.extra_terms=[x**3]), diagnosed again
# Prints the coefficients against the truth and the residual / error before and after.
set -euo pipefail
OUT=${OUT:-outputs/smnn_residual}
common=(experiment=lorenz_cubic_discovery trainer.progress=false paths.ckpt_dir=$OUT/checkpoints)
# every run is redone: mpsim refuses to train or diagnose into a folder that holds an earlier run
rm -rf "$OUT/degree2" "$OUT/diagnose_degree2" "$OUT/with_x3" "$OUT/diagnose_with_x3"
mpsim train "${common[@]}" hydra.run.dir=$OUT/degree2
mpsim diagnose "${common[@]}" init=lorenz1_cubic.ckpt hydra.run.dir=$OUT/diagnose_degree2
mpsim train "${common[@]}" 'model.extra_terms=[x**3]' system.name=lorenz1_cubic_x3 hydra.run.dir=$OUT/with_x3
mpsim diagnose "${common[@]}" init=lorenz1_cubic_x3.ckpt hydra.run.dir=$OUT/diagnose_with_x3
python - "$OUT" <<'PY' | tee "$OUT/smnn_residual.md"
import json, sys
from pathlib import Path

out = Path(sys.argv[1])
truth = {("x", "x"): -10.0, ("x", "y"): 10.0, ("x", "x^3"): -0.005, ("y", "x"): 28.0, ("y", "y"): -1.0,
         ("y", "x z"): -1.0, ("z", "z"): -8 / 3, ("z", "x y"): 1.0}
runs = {"degree 2": ("degree2", "diagnose_degree2"), "degree 2 + x^3": ("with_x3", "diagnose_with_x3")}
print("| coefficient | truth | " + " | ".join(runs) + " |\n|---|---|---|---|")
coefs = {k: json.loads((out / a / "summary.json").read_text())["model"]["coefficients"] for k, (a, _) in runs.items()}
for (eq, term), value in truth.items():
    cells = []
    for k in runs:
        got = coefs[k].get(eq, {}).get(term)
        cells.append("absent" if got is None else f"{got:.5g} ({100 * abs(got - value) / abs(value):.2f} %)")
    print(f"| d{eq}/dt: {term} | {value:.5g} | " + " | ".join(cells) + " |")
for k in runs:
    extra = [f"d{eq}/dt: {t} = {v:.4g}" for eq, c in coefs[k].items() for t, v in c.items() if (eq, t) not in truth]
    print(f"\n{k}: other active terms: {', '.join(extra) or 'none'}")
print("\n| model | effects named by mpsim diagnose | residual RMS x, y, z (held-in) | one-step RMSE | rollout RMSE "
      "(held-out) |\n|---|---|---|---|---|")
for k, (_, d) in runs.items():
    diag = json.loads((out / d / "diagnosis.json").read_text())
    named = "; ".join(f"{f['label']} ({f['coef'][0]:.4g})" for f in diag["effects_found"]) or "none"
    rms = ", ".join(f"{v:.3g}" for v in diag["diagnosis"]["residual_rms"])
    print(f"| {k} | {named} | {rms} | {diag['before']['one_step_rmse']:.3g} | {diag['before']['rollout_rmse']:.3g} |")
PY
