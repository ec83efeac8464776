#!/usr/bin/env bash
# Set up foamlab on a fresh Debian/Ubuntu machine: system packages the tests use
# (mbpoll: an independent Modbus client; poppler-utils: the PDF report read back; Qt's runtime libraries for the offscreen
# GUI tests), then a virtual environment in .venv with foamlab and its dev tools.
set -euo pipefail
cd "$(dirname "$0")/.."

# poppler-utils: pdftoppm/pdftotext read the test report back (tests/test_report.py);
# the xcb ones are for the desktop window on a real display (tests draw offscreen)
APT_PACKAGES="mbpoll poppler-utils libegl1 libgl1 libxkbcommon0 libxkbcommon-x11-0 libfontconfig1 libdbus-1-3 libglib2.0-0 libxcb-cursor0 libxcb-icccm4 libxcb-keysyms1"
missing=""
for p in $APT_PACKAGES; do
  dpkg -s "$p" >/dev/null 2>&1 || missing="$missing $p"
done
if [ -n "$missing" ]; then
  SUDO=""
  [ "$(id -u)" -ne 0 ] && SUDO="sudo"
  echo "setup: installing system packages:$missing"
  $SUDO apt-get update -qq || true
  $SUDO apt-get install -y -qq $missing
fi

PYTHON=${PYTHON:-python3}
[ -x .venv/bin/python ] || "$PYTHON" -m venv .venv
.venv/bin/python -m pip install -q --upgrade pip
.venv/bin/python -m pip install -q -e ".[dev]"
echo "setup: done (.venv)"
