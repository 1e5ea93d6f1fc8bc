#!/usr/bin/env bash
# Install everything depthstation needs on a Debian machine: system libraries, a virtual
# environment in .venv and the package with its test tools. Safe to run again.
set -euo pipefail
cd "$(dirname "$0")/.."

SUDO=""
if [ "$(id -u)" != 0 ]; then SUDO="sudo"; fi
pkgs="libusb-1.0-0 libgl1 libgomp1 libglib2.0-0 python3-venv"
missing=""
for p in $pkgs; do dpkg -s "$p" >/dev/null 2>&1 || missing="$missing $p"; done
if [ -n "$missing" ]; then
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq $missing >/dev/null
fi

# Python 3.10 to 3.13. pyrealsense2 (the live camera) is the extra [camera]: its wheels exist for
# Linux x86_64 and Windows, elsewhere the extra installs nothing and offline evaluation, simulation
# and explain run without it. E57/LAS/LAZ references come with the extra [tls].
PY=""
for cand in python3.11 python3.12 python3.13 python3.10 python3; do
  if command -v "$cand" >/dev/null 2>&1 &&
     "$cand" -c 'import sys; sys.exit(0 if (3, 10) <= sys.version_info[:2] <= (3, 13) else 1)'; then
    PY="$cand"; break
  fi
done
if [ -z "$PY" ]; then
  echo "install.sh: needs Python 3.10 to 3.13; install python3.11 and retry" >&2
  exit 2
fi

if [ ! -x .venv/bin/python ]; then "$PY" -m venv .venv; fi
.venv/bin/python -m pip install -q --upgrade pip >/dev/null
.venv/bin/python -m pip install -q -e '.[dev,camera,tls]'
# mypy and editors do not follow the editable install's import hook: they see the stage folders
# as depthstation.<stage> through links in build/typecheck (made here, never committed)
.venv/bin/python scripts/typecheck_layout.py
if ! .venv/bin/python -c 'import pyrealsense2' >/dev/null 2>&1; then
  echo "install.sh: no pyrealsense2 wheel for this platform: offline evaluation, simulation and explain" \
       "work; for a live camera build librealsense with its Python bindings" >&2
fi
echo "depthstation installed in .venv ($(.venv/bin/python --version))" >&2
