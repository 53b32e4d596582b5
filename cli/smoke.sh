#!/usr/bin/env bash
# Smoke run (CI): train lorenz3 → finetune lorenz10 → zero-shot → simulate → eval → report, on tiny settings.
# Runs in a scratch directory (SMOKE_DIR, default a new temporary one) so it never touches your outputs.
set -euo pipefail
REPO=$(cd "$(dirname "$0")/.." && pwd)
DIR=${SMOKE_DIR:-$(mktemp -d -t mpsim-smoke-XXXXXX)}
mkdir -p "$DIR" && cd "$DIR"
tiny=(trainer=quick trainer.progress=false data.n_train=16 data.n_val=4 data.n_test=4 data.horizon=20)

mpsim train system=lorenz3 "${tiny[@]}"
test -f checkpoints/lorenz3.ckpt
mpsim train system=lorenz10 init=lorenz3.ckpt "${tiny[@]}"
mpsim train mode=zeroshot init=lorenz3.ckpt system=lorenz10 "${tiny[@]}"
mpsim simulate system=lorenz10 init=lorenz3.ckpt format=both n=2 data.horizon=20
mpsim eval init=lorenz10.ckpt system=lorenz10 data.n_test=4 data.horizon=20
mpsim train system=pendulum5_chain mode=zeroshot init=lorenz3.ckpt "${tiny[@]}" 2> err.txt && exit 1  # must refuse
grep -q "was trained on lorenz3" err.txt
mpsim report "runs=[outputs]"
n=$(find outputs -name summary.json | wc -l)
test "$n" -eq 5 || { echo "expected 5 summaries, found $n"; exit 1; }
# your own equations, no Python: simulate a spec, fit it from a CSV, diagnose it (clean data: exit 10, nothing missing)
mkdir -p eq && cd eq
spec=$REPO/examples/equations/pendulums_linear_spring.yaml
mpsim simulate system=equations system.spec=$spec n=20 format=csv out=pend hydra.run.dir=data  # 3 held out for diagnose
mpsim train model=equations model.spec=$spec 'model.init={g: 9.0, k: 2.5}' data.path=data/pend.csv trainer=whitebox \
  trainer.progress=false eval.horizons=[1,10] > train.txt
grep -q "fitted parameters     g=9.8" train.txt
set +e
mpsim diagnose init=pendulums_linear_spring.ckpt data.path=data/pend.csv diagnose.n_boot=20 > diagnose.txt
code=$?
set -e
test "$code" -eq 10 || { echo "diagnose on clean data: expected exit 10 (nothing missing), got $code"; exit 1; }
echo "smoke OK ($DIR)"
