#!/usr/bin/env bash
# CI check of the colcon path: build this package with colcon in a throwaway workspace, then
# start the installed rotavg_node, wait for its first log line, stop it with SIGINT and
# require exit status 0.
#
# colcon comes from PyPI (colcon-common-extensions, pinned below) and is installed into a
# folder of the throwaway workspace, not into the project venv: colcon-core pins
# setuptools<80, which would otherwise downgrade the venv's setuptools. colcon runs with the
# venv's python, so the installed scripts use that interpreter (as `python -m colcon build`
# in an activated venv does in docs/install.md). ROS itself comes from the venv's PyPI
# wheels here; on a real Jazzy install it comes from /opt/ros/jazzy.
set -euo pipefail
cd "$(dirname "$0")/.."
REPO="$PWD"
bash scripts/setup_venv.sh
PY="$(cd "${ROTAVG_VENV:-.venv}" && pwd)/bin/python"
# The meta-package and what the build depends on, pinned (versions of November 2026).
COLCON_PINS=(colcon-common-extensions==0.3.0 colcon-core==0.21.3 colcon-ros==0.5.0
             colcon-python-setup-py==0.2.9 colcon-library-path==0.2.1 catkin-pkg==1.1.1
             setuptools==79.0.1)
STARTUP_TIMEOUT_S="${ROTAVG_STARTUP_TIMEOUT_S:-60}"

WS="$(mktemp -d)"
NODE_PID=""
cleanup() {
  if [ -n "$NODE_PID" ] && kill -0 "$NODE_PID" 2>/dev/null; then kill -KILL "$NODE_PID"; fi
  rm -rf "$WS"
}
trap cleanup EXIT
t0=$(date +%s)
say() { echo "[check_colcon +$(( $(date +%s) - t0 ))s] $*" >&2; }

say "installing ${COLCON_PINS[0]} into $WS/colcon"
log="$WS/pip.log"
if ! "$PY" -m pip install -q --target "$WS/colcon" "${COLCON_PINS[@]}" >"$log" 2>&1; then
  grep -v "^WARNING: Location" "$log" | tail -30 >&2
  exit 1
fi

# The package as git sees it (tracked and untracked-but-not-ignored files): no .venv, no
# build outputs.
mkdir -p "$WS/ws/src/rotavg_ros"
git -C "$REPO" ls-files -co --exclude-standard -z \
  | (cd "$REPO" && tar --null -T - -cf -) | tar -xf - -C "$WS/ws/src/rotavg_ros"

say "colcon build"
cd "$WS/ws"
if ! PYTHONPATH="$WS/colcon" "$PY" -m colcon build >"$WS/build.log" 2>&1; then
  tail -40 "$WS/build.log" >&2
  say "FAIL: colcon build"
  exit 1
fi
NODE_BIN="install/rotavg_ros/lib/rotavg_ros/rotavg_node"
for f in "$NODE_BIN" install/rotavg_ros/lib/rotavg_ros/rotavg \
         install/rotavg_ros/share/rotavg_ros/package.xml \
         install/rotavg_ros/share/ament_index/resource_index/packages/rotavg_ros \
         install/rotavg_ros/share/rotavg_ros/config/rotavg.yaml \
         install/rotavg_ros/share/rotavg_ros/launch/rotavg.launch.py; do
  [ -e "$f" ] || { say "FAIL: $f not installed"; exit 1; }
done
SITE="$(echo install/rotavg_ros/lib/python3*/site-packages)"
[ -f "$SITE/rotavg_ros/msg_adapters/inputs.py" ] \
  || { say "FAIL: rotavg_ros.msg_adapters not installed"; exit 1; }
[ ! -e "$SITE/msg_adapters" ] || { say "FAIL: a top-level msg_adapters was installed"; exit 1; }

# colcon's setup scripts are not written for `set -u`.
set +u
# shellcheck disable=SC1091
source install/setup.bash
set -u
where="$("$PY" -c 'import rotavg_ros.msg_adapters as m; print(m.__file__)')"
case "$where" in
  "$WS/ws/install/"*) ;;
  *) say "FAIL: rotavg_ros imports from $where, not from the workspace's install/"; exit 1 ;;
esac

say "starting $NODE_BIN"
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
export ROS_DOMAIN_ID="${ROS_DOMAIN_ID:-$(( 100 + RANDOM % 100 ))}"
node_log="$WS/node.log"
# Job control on while it starts: a script's background job otherwise starts with SIGINT
# ignored, and rotavg_node keeps a SIGINT that its parent ignores ignored (as `nohup` wants).
set -m
"$NODE_BIN" >"$node_log" 2>&1 &
NODE_PID=$!
set +m
up=""
for _ in $(seq 1 $(( STARTUP_TIMEOUT_S * 10 ))); do
  if grep -q "\[rotavg_node\]" "$node_log"; then up=1; break; fi
  kill -0 "$NODE_PID" 2>/dev/null || break
  sleep 0.1
done
if [ -z "$up" ]; then
  cat "$node_log" >&2
  say "FAIL: rotavg_node logged nothing within ${STARTUP_TIMEOUT_S} s (or exited)"
  exit 1
fi
kill -INT "$NODE_PID"
rc=0
wait "$NODE_PID" || rc=$?
NODE_PID=""
if [ "$rc" -ne 0 ]; then
  cat "$node_log" >&2
  say "FAIL: rotavg_node exited with status $rc after SIGINT (expected 0)"
  exit 1
fi
head -1 "$node_log" >&2
say "OK: colcon build, installed rotavg_node started and exited 0 on SIGINT"
