#!/usr/bin/env bash
# Set up rgbdslam on a fresh machine: system library for Open3D, a virtual environment
# in .venv with the pinned dependencies, and the package installed in editable mode.
# Idempotent: a second call only checks and returns.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}

# Open3D's wheel links against libusb-1.0 (Debian package libusb-1.0-0).
if ! ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
    echo "setup: installing libusb-1.0-0 (needed by open3d)"
    (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libusb-1.0-0) >/dev/null
  else
    echo "setup: open3d needs libusb-1.0; install it with: sudo apt-get install libusb-1.0-0" >&2
    exit 1
  fi
fi

stamp=.venv/.setup-stamp
want=$(cat pyproject.toml | sha1sum | cut -d' ' -f1)
if [ -x .venv/bin/python ] && [ -f "$stamp" ] && [ "$(cat "$stamp")" = "$want" ]; then
  exit 0
fi
"$PY" -c 'import sys; sys.exit(0 if sys.version_info >= (3, 11) else 1)' \
  || { echo "setup: rgbdslam needs Python >= 3.11; set PYTHON=/path/to/python3.11" >&2; exit 1; }
[ -x .venv/bin/python ] || "$PY" -m venv .venv
log=.venv/setup.log
echo "setup: installing the pinned dependencies into .venv (a minute or two; log in $log)"
if ! { .venv/bin/python -m pip install -q --upgrade pip && .venv/bin/python -m pip install -q -e ".[test,realsense]"; } >"$log" 2>&1; then
  tail -n 20 "$log" >&2
  echo "setup: pip install failed (see $log); check the network access to PyPI and run this script again" >&2
  exit 1
fi
echo "$want" > "$stamp"
echo "setup: ready (.venv)"
