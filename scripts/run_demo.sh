#!/usr/bin/env bash
# The main job of README.md: set up the venv, then replay the bundled Ellis Island bag
# through the node's pipeline and print its accuracy against the ground truth in the bag.
# Extra arguments go to `rotavg replay` (e.g. bags/slam_false_loops to replay another bag).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup_venv.sh
bag="${1:-bags/ellis_island}"
[ $# -gt 0 ] && shift
mkdir -p out
exec "${ROTAVG_VENV:-.venv}/bin/rotavg" replay "$bag" \
  --output "out/$(basename "$bag")_replay" --overwrite "$@"
