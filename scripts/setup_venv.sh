#!/usr/bin/env bash
# Create (or reuse) the project venv with every pinned dependency and the package itself.
# Idempotent: re-installs only when a requirements file, setup.py or ROTAVG_TORCH_INDEX changed.
# ROTAVG_TORCH_INDEX=URL installs torch (the pinned version) from that package index alone,
# e.g. https://download.pytorch.org/whl/cpu for the CPU-only build (a 190 MB wheel, where
# PyPI's Linux torch is the CUDA build with GBs of nvidia-* wheels); unset, torch comes from
# the default index like the rest.
set -euo pipefail
cd "$(dirname "$0")/.."
VENV="${ROTAVG_VENV:-.venv}"
PY="${PYTHON:-python3}"
TORCH_INDEX="${ROTAVG_TORCH_INDEX:-}"
stamp_now="$( (cat requirements.txt requirements-colcon.txt requirements-dev.txt setup.py setup.cfg
               echo "torch index: $TORCH_INDEX") | sha256sum | cut -d' ' -f1)"
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
  if [ -n "$TORCH_INDEX" ]; then
    torch_pin="$(grep -E '^torch==' requirements-colcon.txt)"
    echo "[setup] $torch_pin from $TORCH_INDEX" >&2
    # --no-deps: torch's own dependencies come from the default index with the rest;
    # --upgrade: replaces a build of the same version from another index (2.13.0+cpu > 2.13.0).
    pip_quiet install -q --upgrade --no-deps --index-url "$TORCH_INDEX" "$torch_pin"
  fi
  pip_quiet install -q -r requirements-dev.txt
  pip_quiet install -q --no-deps -e .
  "$VENV/bin/python" -c "import torch, rclpy, rosbags, mcap, rotavg_ros" \
    || { echo "[setup] the installed environment does not import" >&2; exit 1; }
  echo "$stamp_now" > "$VENV/.rotavg_stamp"
fi
