#!/usr/bin/env bash
# Keep a recipe's runs in the repository: copies the small files of a recipe's output directory (per-epoch
# metrics.csv, summary.json, train.log, the Hydra record, checkpoints, reports) into results/<name>/, so the
# numbers in docs/ can be checked against the runs that produced them, and an interrupted paper-sized run can be
# resumed from another checkout.
#   cli/keep_runs.sh /work/runs/table1_paper            → results/table1_paper/
# Files over MAX_KB (default 2048) are left out (simulated data, trajectory dumps) and listed. CHECKPOINTS=0 keeps
# only the record (metrics, summaries, logs, Hydra record): for finished runs nobody needs to resume or reload.
# A finished run (it has summary.json) is never resumed, so its checkpoints/last.ckpt (optimiser state, 3-10x its
# best.ckpt) is left out and listed, unless a .md/.sh/.py/.yaml file in the checkout names it as
# results/<name>/<path> (a bench that starts from those weights); its best.ckpt is kept. FINISHED_LAST=1 keeps all.
# RESULTS=<dir> writes <dir>/<name> instead of the checkout's results/ (and looks there for such names too).
# To go on with them, copy the folder anywhere and run the recipe again with the same settings and OUT pointing at
# the copy: finished runs are kept, interrupted ones resume there (a resumed run takes new paths.*), e.g.
#   cp -r results/table1_paper /tmp/ && OUT=/tmp/table1_paper PAPER=1 cli/table1.sh
set -euo pipefail
src=${1:?usage: cli/keep_runs.sh <recipe output directory> [name]}
name=${2:-$(basename "$src")}
[ -d "$src" ] || { echo "keep_runs: $src is not a directory" >&2; exit 2; }
case "$name" in *[!A-Za-z0-9_.-]*|.*) echo "keep_runs: name '$name' must be [A-Za-z0-9_.-]" >&2; exit 2;; esac
here=$(cd "$(dirname "$0")/.." && pwd)
results=${RESULTS:-$here/results}
dest="$results/$name"
max_kb=${MAX_KB:-2048}
skip=(! -name '*.tmp' ! -name '*.lock')
[ "${CHECKPOINTS:-1}" = 0 ] && skip+=(! -name '*.ckpt' ! -name '*.png')
mkdir -p "$results"
tmp=$(mktemp -d "$results/.keep.XXXXXX")
trap 'rm -rf "$tmp"' EXIT
(cd "$src" && find . -type f -size -"$((max_kb + 1))"k "${skip[@]}" -print0) |
  (cd "$src" && xargs -0 -r cp --parents -t "$tmp")
(cd "$src" && find . -type f -size +"$max_kb"k -printf "left out (over $max_kb KB): %p\n")
if [ "${FINISHED_LAST:-0}" != 1 ]; then
  refs=("$here")
  case "$results/" in "$here"/*) ;; *) refs+=("$results") ;; esac
  # every results/<name>/.../last.ckpt that a bench or a note names, read once
  named=$(grep -rhoE --include='*.md' --include='*.sh' --include='*.py' --include='*.yaml' --exclude-dir='.keep.*' \
    --exclude-dir=.git --exclude-dir='.venv*' --exclude-dir=node_modules \
    "results/${name//./\\.}/[A-Za-z0-9_./=-]*checkpoints/last\.ckpt" "${refs[@]}" | sort -u || true)
  (cd "$tmp" && find . -path '*/checkpoints/last.ckpt' -printf '%P\n') | sort | while IFS= read -r f; do
    [ -f "$tmp/${f%/checkpoints/last.ckpt}/summary.json" ] || continue  # unfinished: resumable, kept
    grep -qxF "results/$name/$f" <<< "$named" && continue                # named by a bench or a note: kept
    rm "$tmp/$f" && echo "left out (finished run, not resumed): $f"
  done
fi
rm -rf "$dest" && mv "$tmp" "$dest" && trap - EXIT
echo "kept: $dest ($(du -sh "$dest" | cut -f1))"
