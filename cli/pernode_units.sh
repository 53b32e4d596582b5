#!/usr/bin/env bash
# MP-NODE paper, Table 1: does MPNODE.jl's per-node normaliser explain its L2S-vs-MP-NODE margin? MPNODE.jl
# reports MP-NODE's error z-scored per feature (pooled over nodes) and L2S's z-scored per *node* (its "simple"
# normaliser, for gene's one feature per node). This reads the same rollouts in both units: each kept
# Table 1 checkpoint (paper budget, seed 0) rolls out N trajectories of gene 4×4 BA from their first states
# (`mpsim simulate init=`), and the error is measured over steps 1..T−1 both ways. A few seconds of CPU.
#   cli/pernode_units.sh                      → $OUT/pernode_units.md
set -euo pipefail
OUT=${OUT:-outputs/pernode_units}
N=${N:-200}
CKPTS=${CKPTS:-"mpnode=results/table1_paper/train/mpnode/s0/checkpoints/best.ckpt l2s=results/table1_paper/train/l2s/s0/checkpoints/best.ckpt"}
rm -rf "$OUT"
for pair in $CKPTS; do
  mpsim simulate system=gene_ba_small "init=${pair#*=}" n=$N data.seed=7 hydra.run.dir="$OUT/${pair%%=*}" > /dev/null
done
python - "$OUT" $CKPTS <<'EOF'
import sys
from pathlib import Path

import numpy as np

out, pairs = Path(sys.argv[1]), [p.split("=", 1) for p in sys.argv[2:]]
rows, truth = [], None
for name, ckpt in pairs:
    with np.load(out / name / "trajectories.npz") as a, np.load(out / name / "trajectories_model.npz") as b:
        x, pred = a["x"], b["x"]  # [B, T, N, D] the same truth for every checkpoint (same seed)
    if truth is not None and not np.array_equal(truth, x):
        sys.exit("pernode_units: the checkpoints' truths differ; they must share system and seed")
    truth = x
    pooled = x.reshape(-1, x.shape[-1]).std(0)  # [D] per feature, pooled over nodes (ztransform)
    node = x.std(axis=(0, 1))  # [N, D] per node (MPNODE.jl's "simple" for one feature per node)
    err = (pred - x)[:, 1:]
    r_pool, r_node = np.sqrt(((err / pooled) ** 2).mean()), np.sqrt(((err / node) ** 2).mean())
    rows.append(f"| {name} | `{ckpt}` | {r_pool:.4f} | {r_node:.4f} | {r_node / r_pool:.2f} | {r_pool**2:.5f} | {r_node**2:.5f} |")
node = truth.std(axis=(0, 1))
lines = [
    f"# Table 1 errors z-scored per feature vs per node ({truth.shape[0]} trajectories of gene 4×4 BA)",
    "",
    f"Per-node std: min {node.min():.2f}, median {np.median(node):.2f}, max {node.max():.2f} "
    f"(pooled {truth.reshape(-1, truth.shape[-1]).std(0)[0]:.2f}).",
    "",
    "| model | checkpoint | RMSE per feature | RMSE per node | per node / per feature | MSE per feature | MSE per node |",
    "|---|---|---|---|---|---|---|",
    *rows,
]
(out / "pernode_units.md").write_text("\n".join(lines) + "\n")
print("\n".join(lines))
EOF
