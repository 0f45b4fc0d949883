#!/usr/bin/env bash
# The test command of README.md (and of CI): set up the venv, then run the whole suite.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup_venv.sh
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
# Two test workers on 2 cores: one BLAS thread each (rotavg_ros.BLAS_THREADS_VARIABLES).
export OPENBLAS_NUM_THREADS="${OPENBLAS_NUM_THREADS:-1}"
exec "${ROTAVG_VENV:-.venv}/bin/python" -m pytest -n 2 -q "$@"
