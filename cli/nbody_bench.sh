#!/usr/bin/env bash
# N-body scaling benchmark (docs/results_nbody.md): graph construction time and edges per particle vs N (100 … 100 000)
# for the full, 15-NN and quadtree-hierarchy graphs; DeltaGN forward time vs N per graph kind with fitted
# exponents and peak memory; simulator time per base step and energy drift vs N. About 10 minutes on one thread.
# Extra arguments are Hydra overrides, e.g. threads=2 (the targets are for 2 cores), or the full grid:
#   cli/nbody_bench.sh 'bench.forward_sizes=[100,300,1000,3000,10000,30000,100000]' \
#     'bench.sim_sizes=[100,300,1000,3000]' bench.full_max=10000 bench.full_forward_max=2000
set -euo pipefail
OUT=${OUT:-outputs/nbody_bench}
RUN=$OUT/run_$(date +%Y%m%d_%H%M%S)
mpsim bench bench=nbody hydra.run.dir="$RUN" paths.output_root="$OUT" "$@"
echo "table: $RUN/bench.md, plot: $RUN/plots/nbody_scaling.png"
