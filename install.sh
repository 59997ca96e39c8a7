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

# System packages: libusb-1.0 and OpenMP for Open3D's wheel; for the tests (dev), Chromium and its
# driver, which open report.html headless as a user would see it.
packages=()
ldconfig -p | grep -q "libusb-1.0.so.0" || packages+=(libusb-1.0-0)
ldconfig -p | grep -q "libgomp.so.1" || packages+=(libgomp1)
# A C++ compiler and Python's headers for torch.compile's CPU backend (TSDFVolume's compiled fusion;
# without them it warns and fuses eagerly, slower).
command -v g++ >/dev/null || packages+=(g++)
"$PYTHON" -c "import os, sysconfig; assert os.path.exists(os.path.join(sysconfig.get_paths()['include'], 'Python.h'))" \
  2>/dev/null || packages+=("$("$PYTHON" -c 'import sys; print(f"python3.{sys.version_info.minor}-dev")')")
if [ "${1:-}" = "dev" ] && ! command -v chromedriver >/dev/null; then packages+=(chromium chromium-driver); fi
if [ ${#packages[@]} -gt 0 ]; then
  sudo=""
  [ "$(id -u)" -ne 0 ] && sudo="sudo"
  $sudo apt-get update -qq
  $sudo apt-get install -y -qq "${packages[@]}"
fi

# PyTorch: pinned, so that pip does not pull a multi-GB CUDA build onto a CPU machine. Machines
# with an NVIDIA GPU get the same release in its default (CUDA) build.
if ! "$PYTHON" -c "import torch" 2>/dev/null; then
  "$PYTHON" -m pip install "torch==2.13.0"
fi
"$PYTHON" -m pip install -e ".[$extras]"
