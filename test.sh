#!/usr/bin/env bash
# The tests as CI runs them (after ./setup.sh): everything but the timing-sensitive tests
# on two pytest-xdist workers (one file per worker at a time), then those (marked
# `serial`: real-time streams, timeouts) one at a time on an otherwise idle machine.
# Extra arguments go to both runs (e.g. -x, -k name).
#
# A worker that dies in native code (segfault, abort) fails the test it was running with
# no traceback; tests/conftest.py keeps each worker's native and Python stacks under
# .pytest-crash/. They are printed here, and when crashes were the only failures the
# crashed tests run once more, alone: the run passes only if they pass.
set -euo pipefail
cd "$(dirname "$0")"
rm -rf .pytest-crash
status=0
.venv/bin/python -m pytest -q -n 2 --dist loadfile -m "not serial" "$@" || status=$?
if [ -s .pytest-crash/crashed.txt ]; then
  for log in .pytest-crash/gw*.log; do
    if [ -s "$log" ]; then echo "== $log: the stacks of a crashed test worker"; head -n 60 "$log"; fi
  done
  if [ "$status" -ne 0 ] && [ ! -s .pytest-crash/failed.txt ]; then
    mapfile -t crashed < <(sort -u .pytest-crash/crashed.txt)
    echo "== a test worker crashed in: ${crashed[*]}; those tests once more, alone"
    status=0
    .venv/bin/python -m pytest -q -p no:xdist "${crashed[@]}" || status=$?
  fi
fi
[ "$status" -eq 0 ] || exit "$status"
.venv/bin/python -m pytest -q -p no:xdist -m serial "$@"
