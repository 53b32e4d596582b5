#!/usr/bin/env bash
# device check at HEAD: GPU tests and smoke on the GPU; the residual-loop scorecard on the CPU cores beside them
set -u
T0=$(date +%s); el() { echo $(( $(date +%s) - T0 )); }
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 3
export PYTHONPATH=/tmp/site:$PWD/src PYTHONUNBUFFERED=1
mkdir -p /tmp/bin && printf '#!/bin/sh\nexec python3 -m mpsim "$@"\n' > /tmp/bin/mpsim && chmod +x /tmp/bin/mpsim
export PATH=/tmp/bin:$PATH
{ nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv
  python3 -c "import sys,torch; print(sys.version.split()[0], torch.__version__, torch.cuda.is_available(), torch.cuda.get_device_name(0))"
  nproc; lscpu | grep "Model name"; cat .whl/HEAD; } > $OUT/env.txt 2>&1
mpsim --help > /dev/null 2> $OUT/import.log || { cat $OUT/import.log; exit 4; }
echo "setup done at $(el) s"
(CUDA_VISIBLE_DEVICES= OUT=/tmp/dcases JOBS=12 timeout 470 bash cli/diagnose_cases.sh > $OUT/diagnose_cases.log 2>&1; echo "diagnose_cases rc $? at $(el) s") &
D=$!
(timeout 300 python3 -m pytest -m gpu -n 0 -p no:cacheprovider -rA tests/training/test_distributed.py tests/bench/test_ddp_bench.py > $OUT/gpu_tests.log 2>&1; echo "gpu tests rc $? at $(el) s") &
P1=$!
(timeout 300 bash cli/smoke.sh > $OUT/smoke.log 2>&1; echo "smoke rc $? at $(el) s") &
P2=$!
wait $P1 $P2 $D
cp /tmp/dcases/scorecard.md $OUT/ 2>/dev/null
tar czf $OUT/dcases.tgz --exclude='*.ckpt' --exclude='*.pt' -C /tmp dcases 2>/dev/null; ls -la $OUT
echo "done at $(el) s"
