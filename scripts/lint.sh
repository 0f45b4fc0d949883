#!/usr/bin/env bash
# Static checks run by CI after the tests: ruff (lint) and mypy (types) over the repository.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup_venv.sh
VENV="${ROTAVG_VENV:-.venv}"
"$VENV/bin/ruff" check .
"$VENV/bin/mypy" .
