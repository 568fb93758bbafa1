#!/usr/bin/env bash
# The tests as CI runs them (after ./setup.sh): everything but the timing-sensitive tests
# on two pytest-xdist workers (one file per worker at a time), then those (marked
# `serial`: real-time streams, timeouts) one at a time on an otherwise idle machine.
# Extra arguments go to both runs (e.g. -x, -k name).
set -euo pipefail
cd "$(dirname "$0")"
.venv/bin/python -m pytest -q -n 2 --dist loadfile -m "not serial" "$@"
.venv/bin/python -m pytest -q -p no:xdist -m serial "$@"
