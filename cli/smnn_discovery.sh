#!/usr/bin/env bash
# Lorenz equation discovery with the S-MNN layer (paper Table 4), CPU-sized: about a minute on 2 cores.
# Runs `mpsim train experiment=lorenz_discovery` and prints the seven Lorenz coefficients next to the paper's.
# Extra arguments are Hydra overrides, e.g. the dense MNN layer:  cli/smnn_discovery.sh model=mnn_dense
# or the reference's order-3 layer:                              cli/smnn_discovery.sh model.n_orders=3
set -euo pipefail
OUT=${OUT:-outputs/smnn_discovery}
RUN=$OUT/run_$(date +%Y%m%d_%H%M%S)
mpsim train experiment=lorenz_discovery trainer.progress=false export=false hydra.run.dir="$RUN" "$@"
python - "$RUN/summary.json" <<'PY' | tee "$RUN/coefficients.md"
import json, sys

summary = json.load(open(sys.argv[1]))
coef = summary["model"]["coefficients"]
rows = [("a1", "x", "x", -10.0, -10.0003), ("a2", "x", "y", 10.0, 10.0004), ("a3", "y", "x", 28.0, 27.9915),
        ("a4", "y", "y", -1.0, -0.9968), ("a5", "y", "x z", -1.0, -0.9997), ("a6", "z", "z", -8 / 3, -2.6664),
        ("a7", "z", "x y", 1.0, 1.0000)]
print(f"# Lorenz discovery ({summary['model']['model']}, solver {summary['model']['solver_method']}, "
      f"O={summary['model']['n_orders']}, {summary['model']['optimiser_steps']} steps, "
      f"{summary['command_time']:.0f} s)\n")
print("| coefficient | term | truth | mpsim | rel. error | paper S-MNN |")
print("|---|---|---|---|---|---|")
worst = 0.0
for name, eq, term, truth, paper in rows:
    value = coef.get(eq, {}).get(term, 0.0)
    rel = abs(value - truth) / abs(truth)
    worst = max(worst, rel)
    print(f"| {name} | d{eq}/dt: {term} | {truth:.4f} | {value:.4f} | {100 * rel:.3f} % | {paper:.4f} |")
extra = sum(len(c) for c in coef.values()) - len(rows)
print(f"\nlargest relative error {100 * worst:.3f} % (target 1 %); {extra} other active term(s)")
for line in summary["model"]["equations"].values():
    print(f"    {line}")
PY
