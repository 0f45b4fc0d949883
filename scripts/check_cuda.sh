#!/usr/bin/env bash
# The CUDA checks, for a machine with an NVIDIA GPU (CI and the development machine have none).
#
#   bash scripts/check_cuda.sh OUTDIR
#
# In order, each writing its output to OUTDIR as it goes (a run cut short keeps what it did):
#   1. pytest.log   tests/test_cuda.py (GPU against ground truth and against the CPU) and the
#                   solver tests, which also run there;
#   2. ellis.txt    Ellis Island in a fresh process on CUDA, beside pycolmap if installed;
#   3. scale.txt    10,000 nodes and 100,000 edges on CUDA: wall time and GPU peak memory;
#   4. regimes_cuda.{md,json}  the regime benchmark's `ours` on CUDA (accuracy: compare the
#                   per-case figures with a CPU run of the same commit).
# PYTHON (default python3) must have torch with CUDA, numpy and scipy, and this package
# installed (`pip install --no-deps -e .`: the node's solver-process test imports
# rotavg_ros.msg_adapters, which only the install maps); pycolmap is optional. The shared data
# comes from ../shared or $ROTAVG_SHARED as for every benchmark. Exit status: 1 if a step failed.
set -uo pipefail
out=${1:?usage: bash scripts/check_cuda.sh OUTDIR}
py=${PYTHON:-python3}
export PYTHONUNBUFFERED=1
mkdir -p "$out"
"$py" -c "import torch; assert torch.cuda.is_available(), 'torch sees no CUDA device'
print('torch', torch.__version__, 'on', torch.cuda.get_device_name())" || exit 1
"$py" -c "import rotavg_ros.msg_adapters" 2>/dev/null \
    || { echo "rotavg_ros is not installed for $py: pip install --no-deps -e ." >&2; exit 1; }
rc=0
step() { echo "== $* ($(date -u +%T))"; }

step pytest
"$py" -m pytest -q -p no:cacheprovider tests/test_cuda.py tests/test_solver.py \
    tests/test_dmf.py tests/test_sparse_fit.py tests/test_robust.py 2>&1 \
    | tee "$out/pytest.log" || rc=1
step ellis
"$py" -m benchmarks.paper --graphs ellis --profiles default --peers --device cuda 2>&1 | tee "$out/ellis.txt" || rc=1
step scale
"$py" -m benchmarks.bench_scale --device cuda --sizes 10000 2>&1 | tee "$out/scale.txt" || rc=1
step regimes
"$py" -m benchmarks.regimes --methods ours --device cuda --timeout 120 \
    --json "$out/regimes_cuda.json" --markdown "$out/regimes_cuda.md" 2>&1 | tail -n 45 || rc=1
step "done, status $rc"
exit $rc
