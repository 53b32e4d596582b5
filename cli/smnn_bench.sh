#!/usr/bin/env bash
# S-MNN solver benchmark (paper Table 1 layout): forward+backward time and peak memory vs T and batch for the
# banded, cyclic-reduction, dense S-MNN and dense MNN solvers. CPU-sized default grid: a few minutes on 2 cores.
# Extra arguments are Hydra overrides; the full grid:
#   cli/smnn_bench.sh 'bench.lengths=[5,10,50,100,500,1000,5000,10000]' 'bench.batches=[64,512,4096]' \
#     bench.full_grid=true bench.per_sample_max_length=null
set -euo pipefail
OUT=${OUT:-outputs/smnn_bench}
RUN=$OUT/run_$(date +%Y%m%d_%H%M%S)
mpsim bench bench=smnn hydra.run.dir="$RUN" "$@"
echo "table: $RUN/bench.md, plot: $RUN/plots/smnn_scaling.png"
