#!/usr/bin/env bash
# Create (or reuse) the project venv with every pinned dependency and the package itself.
# Idempotent: re-installs only when a requirements file or setup.py changed.
set -euo pipefail
cd "$(dirname "$0")/.."
VENV="${ROTAVG_VENV:-.venv}"
PY="${PYTHON:-python3}"
stamp_now="$(cat requirements.txt requirements-dev.txt setup.py setup.cfg | sha256sum | cut -d' ' -f1)"
if [ ! -x "$VENV/bin/python" ]; then
  echo "[setup] creating $VENV with $($PY --version)" >&2
  "$PY" -m venv "$VENV"
fi
pip_quiet() {  # pip, with its output kept in a log that is shown only on failure
  local log
  log="$(mktemp)"
  if ! "$VENV/bin/python" -m pip "$@" >"$log" 2>&1; then
    grep -v "^WARNING: Location" "$log" | tail -40 >&2
    echo "[setup] pip $* failed" >&2
    exit 1
  fi
  rm -f "$log"
}
if [ "$(cat "$VENV/.rotavg_stamp" 2>/dev/null || true)" != "$stamp_now" ]; then
  echo "[setup] installing pinned requirements into $VENV (first run: ~2 min)" >&2
  pip_quiet install -q -r requirements-dev.txt
  pip_quiet install -q --no-deps -e .
  "$VENV/bin/python" -c "import torch, rclpy, rosbags, mcap, rotavg_ros" \
    || { echo "[setup] the installed environment does not import" >&2; exit 1; }
  echo "$stamp_now" > "$VENV/.rotavg_stamp"
fi
