#!/usr/bin/env bash
# S-MNN solver benchmark (paper Table 1 layout): forward+backward time and peak memory vs T and batch for the
# banded, cyclic-reduction, dense S-MNN and dense MNN solvers, then paper Table 3 (the six linear ODEs). CPU-sized
# default grid: about 8 minutes on 2 cores.
# Extra arguments are Hydra overrides; the full grid:
#   cli/smnn_bench.sh 'bench.lengths=[5,10,50,100,500,1000,5000,10000]' 'bench.batches=[64,512,4096]' \
#     bench.full_grid=true bench.per_sample_max_length=null
set -euo pipefail
OUT=${OUT:-outputs/smnn_bench}
RUN=$OUT/run_$(date +%Y%m%d_%H%M%S)
# one torch thread: the sweeps are sequential anyway, and on a shared 2-core machine a second intra-op thread
# mostly waits for a busy core (threads=2 doubled the T = 50 times under load); raise it on an idle machine
mpsim bench bench=smnn threads=1 hydra.run.dir="$RUN" "$@"
mpsim bench bench=smnn_table3 threads=1 hydra.run.dir="$RUN/table3"
echo "tables: $RUN/bench.md (Table 1 layout, exponents), $RUN/table3/bench.md (Table 3); plot: $RUN/plots/smnn_scaling.png"
