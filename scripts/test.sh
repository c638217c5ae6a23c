#!/usr/bin/env bash
# Run the test suite in the project's venv (made by scripts/setup.sh).
#   bash scripts/test.sh [pytest arguments]            # the whole suite
#   bash scripts/test.sh test/test_live.py [arguments]  # only these test files
#   bash scripts/test.sh --quick [arguments]            # without the tests marked ros or slow
#   bash scripts/test.sh --stress N [arguments]         # the tests marked ros, N times, with
#                                                       # every core kept busy by a CPU burner;
#                                                       # prints each failing test's count
# Markers (pytest.ini): ros = starts nodes or DDS participants, sends signals or depends on
# timing; slow = takes more than about a second.
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

mode=all runs=0
case "${1:-}" in
  --quick) mode=quick; shift ;;
  --stress)
    mode=stress
    runs=${2:-}
    if ! [[ "$runs" =~ ^[1-9][0-9]*$ ]]; then
      echo "--stress needs a number of runs, e.g. --stress 5" >&2
      exit 2
    fi
    shift 2 ;;
esac

# the whole suite, or only the test files/folders named among the arguments
paths=test
for arg in "$@"; do
  case "$arg" in test/*|./test/*) paths= ;; esac
done

if [ "$mode" = quick ]; then
  exec "$venv/bin/python" -m pytest $paths -m 'not ros and not slow' "$@"
elif [ "$mode" = all ]; then
  exec "$venv/bin/python" -m pytest $paths "$@"
fi

# --stress N: a burner process per core, killed however this script ends. The burners run at
# nice 19: the node's worker process runs under SCHED_IDLE (it yields to every normal task, so
# the wrench path never waits behind an analysis), and next to normal-priority spinners it would
# get ~0.3 % of a core; a burner at nice 19 keeps the cores busy and still lets it progress.
out=$(mktemp -d "${TMPDIR:-/tmp}/cdpr_stress.XXXXXX")
burners=()
stop_burners() {
  for pid in "${burners[@]}"; do kill "$pid" 2>/dev/null || true; done
  wait "${burners[@]}" 2>/dev/null || true
}
trap stop_burners EXIT
for _ in $(seq "$(nproc)"); do
  nice -n 19 "$venv/bin/python" -c 'while True: pass' &
  burners+=($!)
done
echo "stress: $runs runs of the ros tests beside $(nproc) CPU burners (nice 19); reports in $out"
status=0
for k in $(seq "$runs"); do
  start=$SECONDS
  "$venv/bin/python" -m pytest $paths -m ros -q -p no:cacheprovider \
    --junitxml="$out/run_$k.xml" "$@" >"$out/run_$k.log" 2>&1 || status=1
  echo "stress: run $k of $runs: $(tail -n 1 "$out/run_$k.log") ($((SECONDS - start)) s)"
done
"$venv/bin/python" - "$out" "$runs" <<'PY'
import collections
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

out, runs = Path(sys.argv[1]), int(sys.argv[2])
failed = collections.Counter()
seen = set()
for report in sorted(out.glob('run_*.xml')):
    for case in ET.parse(report).iter('testcase'):
        name = f"{case.get('classname')}::{case.get('name')}"
        seen.add(name)
        if case.find('failure') is not None or case.find('error') is not None:
            failed[name] += 1
print(f'stress: {len(seen)} tests, {runs} runs; failures per test:')
for name, count in failed.most_common():
    print(f'  {count} of {runs}  {name}')
if not failed:
    print('  none')
PY
exit $status
