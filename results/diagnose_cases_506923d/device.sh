#!/usr/bin/env bash
# the residual-loop scorecard on the lent machine's CPU cores (GPU hidden)
set -u
T0=$(date +%s)
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 3
export PYTHONPATH=/tmp/site:$PWD/src PYTHONUNBUFFERED=1
mkdir -p /tmp/bin && printf '#!/bin/sh\nexec python3 -m mpsim "$@"\n' > /tmp/bin/mpsim && chmod +x /tmp/bin/mpsim
export PATH=/tmp/bin:$PATH
{ nproc; python3 -c "import sys,torch; print(sys.version.split()[0], torch.__version__)"; cat .whl/HEAD; } > $OUT/env.txt 2>&1
CUDA_VISIBLE_DEVICES= OUT=/tmp/dcases JOBS=16 timeout 350 bash cli/diagnose_cases.sh > $OUT/scorecard_log.md 2>&1; echo "rc $? at $(( $(date +%s) - T0 )) s"
[ -f /tmp/dcases/scorecard.md ] || CASES=" " OUT=/tmp/dcases bash cli/diagnose_cases.sh > $OUT/partial.md 2>&1
cp /tmp/dcases/scorecard.md $OUT/ 2>/dev/null; for c in case2 b_vdp; do tail -c 3000 /tmp/dcases/$c.log > $OUT/$c.log 2>/dev/null; done
