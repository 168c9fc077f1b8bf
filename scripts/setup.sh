#!/usr/bin/env bash
# Install taichi-gs into .venv, with the system library open3d needs (libusb-1.0).
# Usage: bash scripts/setup.sh [--test]   (--test adds pytest, the evo test oracle, the web viewer's extra and,
# for its browser test, Debian's headless Chromium when apt-get may install it)
set -euo pipefail
cd "$(dirname "$0")/.."

extras=""
if [ "${1:-}" = "--test" ]; then extras="[test,oracle,viewer]"; fi

if ! ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then
  if command -v apt-get >/dev/null 2>&1 && [ "$(id -u)" = 0 ]; then
    echo "installing libusb-1.0-0 (open3d needs it)"
    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libusb-1.0-0 >/dev/null
  elif command -v apt-get >/dev/null 2>&1 && command -v sudo >/dev/null 2>&1; then
    echo "installing libusb-1.0-0 (open3d needs it) with sudo"
    sudo apt-get update -qq && sudo DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libusb-1.0-0 >/dev/null
  else
    echo "error: open3d needs libusb-1.0; install it first (Debian/Ubuntu: apt-get install libusb-1.0-0, Fedora: dnf install libusb1, macOS: brew install libusb)" >&2
    exit 2
  fi
fi

# The viewer test drives a real browser (Playwright on the system's Chromium; it downloads none). Without one it
# skips and says why.
if [ -n "$extras" ] && ! command -v chromium >/dev/null 2>&1; then
  if command -v apt-get >/dev/null 2>&1 && [ "$(id -u)" = 0 ]; then
    echo "installing chromium (the viewer test's headless browser)"
    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null \
      || echo "warning: chromium could not be installed; the viewer's browser test will skip" >&2
  else
    echo "note: no chromium found; the viewer's browser test will skip (Debian/Ubuntu: apt-get install chromium)" >&2
  fi
fi

python=${PYTHON:-python3}
if ! "$python" -c 'import sys; sys.exit(not ((3, 10) <= sys.version_info[:2] <= (3, 12)))'; then
  echo "error: taichi 1.7.4 needs Python 3.10-3.12; set PYTHON=/path/to/python3.x and rerun" >&2
  exit 2
fi
[ -x .venv/bin/python ] || "$python" -m venv .venv
.venv/bin/python -m pip install -q --upgrade pip
.venv/bin/python -m pip install -q -e ".$extras"
echo "taichi-gs installed in .venv ($(.venv/bin/taichi-gs --version))"
