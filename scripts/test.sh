#!/usr/bin/env bash
# Run the whole test suite in the project's venv (made by scripts/setup.sh).
#   bash scripts/test.sh [pytest arguments]            # the whole suite
#   bash scripts/test.sh test/test_live.py [arguments]  # only these test files
set -euo pipefail
cd "$(dirname "$0")/.."
venv="$(pwd)/.venv"
if [ ! -x "$venv/bin/python" ]; then
  echo "no venv at $venv: run 'bash scripts/setup.sh' first" >&2
  exit 2
fi
export AMENT_PREFIX_PATH="$venv${AMENT_PREFIX_PATH:+:$AMENT_PREFIX_PATH}"
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
export PATH="$venv/bin:$PATH"
# the whole suite, or only the test files/folders named among the arguments
paths=test
for arg in "$@"; do
  case "$arg" in test/*|./test/*) paths= ;; esac
done
exec "$venv/bin/python" -m pytest $paths "$@"
