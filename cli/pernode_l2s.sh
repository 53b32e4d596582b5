#!/usr/bin/env bash
# MP-NODE paper, Table 1: L2S trained in MPNODE.jl's per-node units. MPNODE.jl's L2S config normalises with its
# "simple" normaliser, which for gene's one feature per node z-scores every node by its own mean and std
# (fitted on the whole dataset: ../shared/reference/mpnode_reference.md §4). The same N gene 4×4 BA
# trajectories are written twice, as simulated and z-scored per node; L2S is trained on each file and MP-NODE
# on the first (data.path=, split 70/15/15; mpsim then z-scores per feature, which leaves the per-node file as
# it is). Each best checkpoint's test rollout (`mpsim eval eval.save_predictions=true`) is then read in both
# units: z-scored per feature (pooled over nodes, as MPNODE.jl reports MP-NODE) and per node (as it reports L2S).
# CPU-sized by default (EPOCHS=150, N=300 → 210 training trajectories, 3 seeds: about an hour of one core).
# Paper-sized: PAPER=1 (MPNODE.jl's trainer, 4000 epochs, L2S 10000, N=1000 → 700 training trajectories, seed 0;
# about 4 h a run here, see bench=epoch_time_trained).
# Another gene system: SYSTEM=gene_ba_large (8×8, Table 2's gene column), with DATA_SEED=<n> for a draw that shares
# nothing with the runs COMPARE names (default 0, the draw the kept 4×4 runs were read on).
#   cli/pernode_l2s.sh                         → $OUT/pernode_l2s.md
# Resumable (cli/lib.sh): run it again and finished runs are kept.
set -euo pipefail
source "$(dirname "$0")/lib.sh"
OUT=${OUT:-outputs/pernode_l2s}
SYSTEM=${SYSTEM:-gene_ba_small}
DATA_SEED=${DATA_SEED:-0}
[[ $SYSTEM == gene_* ]] || { echo "pernode_l2s.sh: SYSTEM='$SYSTEM' is not a gene system (gene_ba_small, gene_ba_large, ...)" >&2; exit 2; }
[[ $DATA_SEED =~ ^[0-9]+$ ]] || { echo "pernode_l2s.sh: DATA_SEED='$DATA_SEED' is not a non-negative integer" >&2; exit 2; }
if [ "${PAPER:-0}" = 1 ]; then
  N=${N:-1000}; EPOCHS=${EPOCHS:-4000}; L2S_EPOCHS=${L2S_EPOCHS:-10000}; SEEDS=${SEEDS:-0}; TRAINER=${TRAINER:-paper}
fi
N=${N:-300}
EPOCHS=${EPOCHS:-150}
L2S_EPOCHS=${L2S_EPOCHS:-$EPOCHS}
SEEDS=${SEEDS:-"0 1 2"}
TRAINER=${TRAINER:-default}
RUNS=${RUNS-"l2s/per_feature l2s/per_node mpnode/per_feature"}  # model/units of its training file ("": none, only COMPARE)
JOBS=${JOBS:-2}
# name=checkpoint pairs trained elsewhere on the same system (e.g. Table 1's MP-NODE models), each evaluated on this
# data's per-feature file and read both ways beside the runs, e.g.
# COMPARE="table1_mpnode_s0=results/table1_paper/train/mpnode/s0/checkpoints/best.ckpt"
COMPARE=${COMPARE:-}
for pair in $COMPARE; do  # refused before anything is simulated or trained
  [[ $pair == *=* && -f ${pair#*=} ]] || { echo "pernode_l2s.sh: COMPARE entry '$pair' is not name=<an existing checkpoint>" >&2; exit 2; }
done
draw="system=$SYSTEM data.seed=$DATA_SEED"
if [ -f "$OUT/data/per_node.npz" ]; then  # kept data must be the draw asked for (runs resume on it)
  # before SYSTEM= and DATA_SEED= the recipe drew only gene_ba_small with data.seed 0, and wrote no draw.txt
  held=$(cat "$OUT/data/draw.txt" 2>/dev/null || echo "system=gene_ba_small data.seed=0")
  [ "$held" = "$draw" ] || { echo "pernode_l2s.sh: $OUT/data holds the draw '$held', not '$draw'; use another OUT or remove $OUT/data" >&2; exit 2; }
fi
mkdir -p "$OUT/data"
if [ ! -f "$OUT/data/per_node.npz" ]; then
  echo "$draw" > "$OUT/data/draw.txt"
  # data.seed $DATA_SEED (default 0: the draw the kept gene 4×4 runs were read on)
  mpsim simulate system=$SYSTEM n=$N data.seed=$DATA_SEED hydra.run.dir="$OUT/data/sim" > /dev/null
  python - "$OUT/data" <<'PY'
import shutil
import sys
from pathlib import Path

import numpy as np

d = Path(sys.argv[1])
with np.load(d / "sim" / "trajectories.npz", allow_pickle=False) as z:
    arrays = {k: z[k] for k in z.files}
x = arrays["x"]  # [B, T, N, D]
mean, std = x.mean(axis=(0, 1)), x.std(axis=(0, 1))  # [N, D] per node, over every trajectory and time
shutil.copy(d / "sim" / "trajectories.npz", d / "per_feature.npz")
tmp = d / "per_node.tmp.npz"
np.savez(tmp, **{**arrays, "x": (x - mean) / std})
tmp.replace(d / "per_node.npz")
print(f"per-node std {std.min():.2f}..{std.max():.2f}, mean {mean.min():.2f}..{mean.max():.2f}")
PY
fi
for seed in ${SEEDS//,/ }; do
  for run in $RUNS; do
    epochs=$EPOCHS; [ "${run%%/*}" = l2s ] && epochs=$L2S_EPOCHS
    echo "train_once $OUT/train/$run/s$seed model=${run%%/*} data.path=$OUT/data/${run#*/}.npz seed=$seed \
      trainer=$TRAINER trainer.max_epochs=$epochs trainer.progress=false trainer.early_stop_patience=0 eval.plots=false export=false \
      paths.output_root=$OUT"
  done
done | parallel "$JOBS"
for seed in ${SEEDS//,/ }; do
  for run in $RUNS; do
    dir=$OUT/train/$run/s$seed
    [ -f "$dir/eval/test_model.npz" ] || mpsim eval "init=$dir/checkpoints/best.ckpt" \
      "data.path=$OUT/data/${run#*/}.npz" eval.save_predictions=true eval.plots=false hydra.run.dir="$dir/eval" \
      paths.output_root="$OUT" > /dev/null
  done
done
rows=()
for run in $RUNS; do rows+=("train/$run"); done
for pair in $COMPARE; do
  name=${pair%%=*} ckpt=${pair#*=}
  dir=$OUT/compare/$name/per_feature/s0
  [ -f "$dir/eval/test_model.npz" ] || mpsim eval "init=$ckpt" "data.path=$OUT/data/per_feature.npz" \
    eval.save_predictions=true eval.plots=false hydra.run.dir="$dir/eval" paths.output_root="$OUT" > /dev/null
  rows+=("compare/$name/per_feature")
done
python - "$OUT" "$SYSTEM" "$DATA_SEED" "${rows[@]}" <<'PY'
import sys
from pathlib import Path

import numpy as np

out, system, data_seed, runs = Path(sys.argv[1]), sys.argv[2], sys.argv[3], sys.argv[4:]
with np.load(out / "data" / "per_feature.npz") as z:
    raw = z["x"]  # [B, T, N, D] as simulated
mean, node_std = raw.mean(axis=(0, 1)), raw.std(axis=(0, 1))  # [N, D] the per-node file's transform
pooled = raw.reshape(-1, raw.shape[-1]).std(0)  # [D]
rows = []
for run in runs:
    per_feature, per_node = [], []
    for seed_dir in sorted(d for d in (out / run).glob("s*") if d.is_dir()):  # not the runs' .lock files
        with np.load(seed_dir / "eval" / "test.npz") as a, np.load(seed_dir / "eval" / "test_model.npz") as b:
            x, pred = a["x"], b["x"]  # [B, T, N, D] in the training file's units
        if run.endswith("per_node"):  # back to the simulated units
            x, pred = x * node_std + mean, pred * node_std + mean
        err = (pred - x)[:, 1:]
        per_feature.append(np.sqrt(((err / pooled) ** 2).mean()))
        per_node.append(np.sqrt(((err / node_std) ** 2).mean()))
    model, units = run.split("/")[-2:]
    f, n = np.array(per_feature), np.array(per_node)
    rows.append(f"| {model} | {units} | {len(f)} | {f.mean():.4f} ± {f.std():.4f} | {n.mean():.4f} ± {n.std():.4f} |")
lines = [
    f"# {system} (data.seed {data_seed}) trained on data z-scored per feature vs per node (MPNODE.jl's L2S normaliser)",
    "",
    f"Per-node std {node_std.min():.2f}..{node_std.max():.2f}, per-node mean {mean.min():.2f}..{mean.max():.2f}, "
    f"pooled std {pooled[0]:.2f}. Test rollout RMSE of each best checkpoint, mean ± std over seeds, read both ways:",
    "",
    "| model | trained in units | seeds | RMSE z-scored per feature | RMSE z-scored per node |",
    "|---|---|---|---|---|",
    *rows,
]
(out / "pernode_l2s.md").write_text("\n".join(lines) + "\n")
print("\n".join(lines))
PY
