#!/usr/bin/env bash
# Set up posecal on a fresh Debian/Ubuntu machine: system GL libraries for
# headless rendering (EGL on Mesa) and the PostgreSQL server (the tests start a
# throwaway one), then a virtualenv in .venv with posecal, its PostgreSQL driver
# and its test dependencies. Safe to run again; it only installs what is missing.
set -euo pipefail
cd "$(dirname "$0")"

packages=(libegl1 libegl-mesa0 libgl1-mesa-dri openssl  # openssl: deploy/make-lab-ca.sh (tests too)
          postgresql)  # initdb, pg_ctl: tests/test_pg_queue.py starts a throwaway server
if command -v dpkg >/dev/null 2>&1 && ! dpkg -s "${packages[@]}" >/dev/null 2>&1; then
  sudo=""
  if [ "$(id -u)" -ne 0 ]; then sudo="sudo"; fi
  export DEBIAN_FRONTEND=noninteractive
  $sudo apt-get update -qq
  $sudo apt-get install -y -qq --no-install-recommends "${packages[@]}" >/dev/null
fi

PYTHON=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  "$PYTHON" -m venv .venv
fi
.venv/bin/python -m pip install -q --disable-pip-version-check -U pip
.venv/bin/python -m pip install -q --disable-pip-version-check -e ".[test,eval,postgres]"
echo "posecal is set up in $(pwd)/.venv"
