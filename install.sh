#!/usr/bin/env bash
# Install neuralsurf and everything it needs on a Debian/Ubuntu machine with Python 3.11.
#   ./install.sh        the library, its dependencies and the sample data (the Stanford bunny)
#   ./install.sh dev    the same plus the test tools
# Set PYTHON to choose the interpreter (default: python3). Safe to run again.
set -euo pipefail
cd "$(dirname "$0")"
PYTHON="${PYTHON:-python3}"
extras="data"
[ "${1:-}" = "dev" ] && extras="data,dev"

# System libraries of Open3D's wheel: libusb-1.0 and OpenMP.
if ! ldconfig -p | grep -q "libusb-1.0.so.0" || ! ldconfig -p | grep -q "libgomp.so.1"; then
  sudo=""
  [ "$(id -u)" -ne 0 ] && sudo="sudo"
  $sudo apt-get update -qq
  $sudo apt-get install -y -qq libusb-1.0-0 libgomp1
fi

# PyTorch: pinned, so that pip does not pull a multi-GB CUDA build onto a CPU machine. Machines
# with an NVIDIA GPU get the same release in its default (CUDA) build.
if ! "$PYTHON" -c "import torch" 2>/dev/null; then
  "$PYTHON" -m pip install "torch==2.13.0"
fi
"$PYTHON" -m pip install -e ".[$extras]"
