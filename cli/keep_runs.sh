#!/usr/bin/env bash
# Keep a recipe's runs in the repository: copies the small files of a recipe's output directory (per-epoch
# metrics.csv, summary.json, train.log, the Hydra record, checkpoints, reports) into results/<name>/, so the
# numbers in docs/ can be checked against the runs that produced them, and an interrupted paper-sized run can be
# resumed from another checkout.
#   cli/keep_runs.sh /work/runs/table1_paper            → results/table1_paper/
# Files over MAX_KB (default 2048) are left out (simulated data, trajectory dumps) and listed. CHECKPOINTS=0 keeps
# only the record (metrics, summaries, logs, Hydra record): for finished runs nobody needs to resume or reload.
# To go on with them, copy the folder anywhere and run the recipe again with the same settings and OUT pointing at
# the copy: finished runs are kept, interrupted ones resume there (a resumed run takes new paths.*), e.g.
#   cp -r results/table1_paper /tmp/ && OUT=/tmp/table1_paper PAPER=1 cli/table1.sh
set -euo pipefail
src=${1:?usage: cli/keep_runs.sh <recipe output directory> [name]}
name=${2:-$(basename "$src")}
[ -d "$src" ] || { echo "keep_runs: $src is not a directory" >&2; exit 2; }
case "$name" in *[!A-Za-z0-9_.-]*|.*) echo "keep_runs: name '$name' must be [A-Za-z0-9_.-]" >&2; exit 2;; esac
here=$(cd "$(dirname "$0")/.." && pwd)
dest="$here/results/$name"
max_kb=${MAX_KB:-2048}
skip=(! -name '*.tmp' ! -name '*.lock')
[ "${CHECKPOINTS:-1}" = 0 ] && skip+=(! -name '*.ckpt' ! -name '*.png')
mkdir -p "$here/results"
tmp=$(mktemp -d "$here/results/.keep.XXXXXX")
trap 'rm -rf "$tmp"' EXIT
(cd "$src" && find . -type f -size -"$((max_kb + 1))"k "${skip[@]}" -print0) |
  (cd "$src" && xargs -0 -r cp --parents -t "$tmp")
(cd "$src" && find . -type f -size +"$max_kb"k -printf "left out (over $max_kb KB): %p\n")
rm -rf "$dest" && mv "$tmp" "$dest" && trap - EXIT
echo "kept: $dest ($(du -sh "$dest" | cut -f1))"
