#!/usr/bin/env bash
# Foundation evidence (docs/results_mpnode.md), CPU-sized: about 30 minutes on 2 cores.
#   1. Lorenz3: test error of the trained model vs the untrained one.
#   2. Lorenz10: finetuning the Lorenz3 model vs training from scratch — epochs to reach the same test error
#      (the level both runs reach) and the MP-NODE paper's epochs_x_min_error.
#   3. Pendulum2: messages on vs model.zero_messages=true (the paper's ablation; Figure 3a's curves in
#      $OUT/figure3a.md and figure3a.png), and Figure 3b: the messages-on model with its messages zeroed at test
#      time, against the coupled truth and uncoupled pendulums ($OUT/figure3b.md).
# Override the sizes with environment variables, e.g. E3=600 E10=300 DS=100 cli/foundation.sh; PARTS="pendulum"
# runs only part 3. The pendulum runs are resumable (cli/lib.sh: run the recipe again; FRESH=1 starts them over).
# Paper-sized (PAPER=1): the MPNODE.jl trainer (batch 128, Adam 1e-3 halved after 500 flat epochs) for 4000 epochs,
# and for the pendulums (the paper's Figure 3a, appendix A.1) 500 trajectories of 10 s at dt 0.1 s, split 350/150
# as MPNODE.jl splits 0.7/0.3 (test: 100 more); 3 seeds.
set -euo pipefail
source "$(dirname "$0")/lib.sh"
OUT=${OUT:-outputs/foundation}
PAPER=${PAPER:-0}
if [ "$PAPER" = 1 ]; then
  E3=${E3:-4000}; E10=${E10:-4000}; EP=${EP:-4000}; SEEDS=${SEEDS:-0,1,2}; TRAINER=${TRAINER:-paper}
  PEND_DATA=${PEND_DATA:-"data.n_train=350 data.n_val=150 data.n_test=100 data.horizon=100"}
fi
E3=${E3:-300}     # Lorenz3 epochs
E10=${E10:-150}   # Lorenz10 epochs (finetune and scratch)
DS=${DS:-100}     # Lorenz10 training trajectories
EP=${EP:-150}     # pendulum2 epochs
SEEDS=${SEEDS:-0,1}
TRAINER=${TRAINER:-default}
PEND_DATA=${PEND_DATA:-}   # pendulum2 data overrides (default: the system's 200 trajectories of 50 steps)
PARTS=${PARTS:-"lorenz pendulum"}
JOBS=${JOBS:-2}    # pendulum runs at once (JOBS=1 leaves a core for another recipe)
check_parts foundation.sh lorenz pendulum
CKPT=$OUT/checkpoints
common=(paths.output_root=$OUT paths.ckpt_dir=$CKPT trainer=$TRAINER trainer.progress=false trainer.early_stop_patience=0)
report=(hydra.run.dir=$OUT/report paths.output_root=$OUT)
tables=()

rm -rf "$OUT/report"
if [[ " $PARTS " == *" lorenz "* ]]; then
  rm -rf "$OUT/lorenz3" "$OUT/lorenz10"
  mpsim train system=lorenz3 trainer.max_epochs=$E3 hydra.run.dir=$OUT/lorenz3 "${common[@]}"
  mpsim train -m hydra/launcher=joblib hydra.launcher.n_jobs=2 hydra.sweep.dir=$OUT/lorenz10 system=lorenz10 \
    data.n_train=$DS init=lorenz3.ckpt,null trainer.max_epochs=$E10 export=false "${common[@]}"
  mpsim report "runs=[$OUT/lorenz3]" "title='Lorenz3: trained vs untrained'" \
    "columns=[initial_test_error,min_test_error,min_test_error_epoch,epochs_x_min_error]" "${report[@]}"
  mv "$OUT/report/report.md" "$OUT/lorenz3.md"
  mpsim report "runs=[$OUT/lorenz10]" "title='Lorenz10 (ds=$DS): finetuned from Lorenz3 vs scratch'" target=max_min \
    "columns=[initial_test_error,epochs_to_target,min_test_error,min_test_error_epoch,epochs_x_min_error]" "${report[@]}"
  mv "$OUT/report/report.md" "$OUT/lorenz10.md"
  tables+=("$OUT/lorenz3.md" "$OUT/lorenz10.md")
fi
if [[ " $PARTS " == *" pendulum "* ]]; then
  # one resumable run per (seed, messages): run the recipe again to keep finished runs and resume the others
  [ "${FRESH:-0}" = 1 ] && rm -rf "$OUT/pendulum2"
  for seed in ${SEEDS//,/ }; do
    for zero in false true; do
      echo "train_once $OUT/pendulum2/s$seed-zero_messages_$zero system=pendulum2 seed=$seed \
        model.zero_messages=$zero trainer.max_epochs=$EP export=false $PEND_DATA ${common[*]}"
    done
  done | parallel "$JOBS"
  mpsim report "runs=[$OUT/pendulum2]" "title='Pendulum2: messages on vs zero_messages'" \
    "columns=[initial_test_error,min_test_error,min_test_error_epoch,epochs_x_min_error]" "${report[@]}"
  mv "$OUT/report/report.md" "$OUT/pendulum2.md"
  # the paper's Figure 3a: train loss (and test error) per epoch, messages on vs off, and their ratio
  mpsim report layout=messages "runs=[$OUT/pendulum2]" "title='Figure 3a: pendulum2, messages on vs zero_messages'" \
    "${report[@]}"
  sed 's/(messages\.png)/(figure3a.png)/' "$OUT/report/report.md" > "$OUT/figure3a.md"
  mv "$OUT/report/messages.png" "$OUT/figure3a.png"
  # the paper's Figure 3b: each messages-on model evaluated with its messages zeroed at test time, against the
  # coupled truth and against uncoupled pendulums (system.spring=0) from the same initial states
  for seed in ${SEEDS//,/ }; do
    ck=$OUT/pendulum2/s$seed-zero_messages_false/checkpoints/best.ckpt
    [ -f "$ck" ] || continue
    for truth in coupled uncoupled; do
      spring=(); [ $truth = uncoupled ] && spring=(system.spring=0)
      for zero in false true; do
        dir=$OUT/figure3b/s$seed/${truth}_zero_messages_$zero
        [ -f "$dir/test_model.npz" ] || mpsim eval "init=$ck" system=pendulum2 "${spring[@]}" model.zero_messages=$zero \
          eval.save_predictions=true $PEND_DATA paths.output_root=$OUT hydra.run.dir="$dir" > /dev/null
      done
    done
  done
  python - "$OUT/figure3b" > "$OUT/figure3b.md" <<'PY'
import sys
from pathlib import Path

import numpy as np

root = Path(sys.argv[1])
seeds = sorted(d for d in root.glob("s*") if d.is_dir())
if not seeds:
    print("No messages-on checkpoint to evaluate.")
    sys.exit(0)


def arrays(seed, truth, zero):
    d = seed / f"{truth}_zero_messages_{zero}"
    with np.load(d / "test.npz") as a, np.load(d / "test_model.npz") as b:
        return a["x"], b["x"]  # [B, T, N, D] truth and prediction, simulated units


def rmse(a, b):  # [B, T, N, D] twice -> [T] per step over trajectories, nodes and features
    return np.sqrt(((a - b) ** 2).mean(axis=(0, 2, 3)))


rows = {
    "messages on vs the coupled truth (the model as trained)": [],
    "messages zeroed vs the coupled truth": [],
    "messages zeroed vs uncoupled pendulums": [],
    "messages on vs uncoupled pendulums": [],
    "uncoupled pendulums vs the coupled truth (the two truths apart)": [],
}
for seed in seeds:
    (xc, on_c), (_, off_c) = arrays(seed, "coupled", "false"), arrays(seed, "coupled", "true")
    (xu, on_u), (_, off_u) = arrays(seed, "uncoupled", "false"), arrays(seed, "uncoupled", "true")
    if not np.array_equal(xc[:, 0], xu[:, 0]):
        sys.exit("figure3b: the coupled and uncoupled test sets do not start from the same states")
    for key, err in zip(rows, (rmse(on_c, xc), rmse(off_c, xc), rmse(off_u, xu), rmse(on_u, xu), rmse(xu, xc))):
        rows[key].append(err)
steps = [k for k in (1, 10, 25, 50, 100, 200) if k < xc.shape[1]]
print("# Figure 3b: the trained coupled model with its messages zeroed at test time\n")
print(f"Test RMSE at step k (simulated units, mean over {len(seeds)} seed(s); uncoupled = `system.spring=0`, same "
      "initial states):\n")
print("| prediction vs truth | " + " | ".join(f"step {k}" for k in steps) + " |")
print("|---|" + "---|" * len(steps))
mean = {key: np.mean(v, axis=0) for key, v in rows.items()}
for key, err in mean.items():
    print(f"| {key} | " + " | ".join(f"{err[k]:.3g}" for k in steps) + " |")
off_c, off_u, apart = (mean[k] for k in list(rows)[1:3] + list(rows)[4:])
with np.errstate(divide="ignore", invalid="ignore"):  # step 0: both truths start from the same states
    share = off_u / apart  # [T] how much of the distance between the two truths the zeroed model is from uncoupled
print("| messages zeroed vs uncoupled, as a share of the two truths apart | " + " | ".join(f"{share[k]:.2f}" for k in steps) + " |")
closer = sum(off_u[k] < off_c[k] for k in steps)
later = [share[k] for k in steps[1:]] or [share[steps[0]]]  # after the first step, once the truths have parted
verdict = (
    "behave like uncoupled pendulums" if closer == len(steps) and max(later) < 0.5
    else "move towards uncoupled pendulums without becoming them" if closer > len(steps) / 2
    else "do NOT behave like uncoupled pendulums"
)
print(f"\nWith messages zeroed the nodes {verdict} (the paper's Figure 3b: like simple pendulums): closer to the "
      f"uncoupled truth than to the coupled one at {closer} of {len(steps)} steps, and {min(later):.2f}–{max(later):.2f}× "
      "the distance between the two truths from the uncoupled one after the first step.")
PY
  tables+=("$OUT/pendulum2.md")
fi
cat "${tables[@]}" > "$OUT/foundation.md"
echo "tables: $OUT/foundation.md"
