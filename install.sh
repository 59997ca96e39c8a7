#!/usr/bin/env bash
# Install neuralsurf into a project virtual environment on a Debian/Ubuntu machine with Python 3.11.
#   ./install.sh        the library, its dependencies and the sample data (the Stanford bunny, from the GPL-3
#                       pymeshlab wheel: the `data` extra, which the demo experiment=bunny_sdf needs)
#   ./install.sh dev    the same plus the test tools
#   ./install.sh lean   the library and its dependencies only: no GPL code, no bunny
# Uses the active virtual environment if there is one, else makes ./.venv with python3 (PEP 668
# systems refuse pip on the system interpreter). PYTHON chooses the interpreter that makes .venv.
# Safe to run again.
set -euo pipefail
cd "$(dirname "$(readlink -f "$0")")"
PYTHON="${PYTHON:-python3}"
fail() { echo "install.sh: $*" >&2; exit 1; }
case "${1:-}" in
  "") extras="[data]" ;;
  dev) extras="[data,dev]" ;;
  lean) extras="" ;;
  *) fail "unknown argument '$1': run ./install.sh, ./install.sh dev or ./install.sh lean" ;;
esac
command -v "$PYTHON" >/dev/null || fail "no $PYTHON found; install Python 3.11 (Debian/Ubuntu: apt-get install python3) or set PYTHON"
"$PYTHON" -c "import sys; sys.exit(sys.version_info < (3, 11))" \
  || fail "$("$PYTHON" --version 2>&1) is too old; neuralsurf needs Python 3.11 or newer (set PYTHON=python3.11)"

# System packages: libusb-1.0 and OpenMP for Open3D's wheel; a C++ compiler and Python's headers for
# torch.compile's CPU backend (the compiled TSDF fusion; without them it fuses eagerly, slower);
# venv when the interpreter lacks it; for the tests (dev), Chromium and its driver, which open
# report.html headless as a user would see it.
minor="$("$PYTHON" -c 'import sys; print(sys.version_info.minor)')"
packages=()
ldconfig -p | grep -q "libusb-1.0.so.0" || packages+=(libusb-1.0-0)
ldconfig -p | grep -q "libgomp.so.1" || packages+=(libgomp1)
command -v g++ >/dev/null || packages+=(g++)
"$PYTHON" -c "import os, sysconfig; assert os.path.exists(os.path.join(sysconfig.get_paths()['include'], 'Python.h'))" \
  2>/dev/null || packages+=("python3.$minor-dev")
if [ -z "${VIRTUAL_ENV:-}" ] && [ ! -x .venv/bin/python ] && ! "$PYTHON" -c "import ensurepip, venv" 2>/dev/null; then
  packages+=("python3.$minor-venv")
fi
if [ "${1:-}" = "dev" ] && ! command -v chromedriver >/dev/null; then packages+=(chromium chromium-driver); fi
if [ ${#packages[@]} -gt 0 ]; then
  sudo=""
  [ "$(id -u)" -ne 0 ] && sudo="sudo"
  command -v apt-get >/dev/null || fail "missing system packages: ${packages[*]}; install them with your package manager and run again"
  echo "install.sh: installing system packages: ${packages[*]}"
  $sudo apt-get update -qq || fail "apt-get update failed; install ${packages[*]} by hand and run again"
  DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq "${packages[@]}" \
    || fail "apt-get could not install ${packages[*]}; install them by hand and run again"
fi

# The interpreter to install into: the active virtual environment, else ./.venv (made once).
if [ -n "${VIRTUAL_ENV:-}" ]; then
  python="$VIRTUAL_ENV/bin/python"
else
  [ -x .venv/bin/python ] || "$PYTHON" -m venv .venv || fail "could not make .venv with $PYTHON -m venv"
  python=".venv/bin/python"
fi

# PyTorch, pinned: on a machine without an NVIDIA GPU (no nvidia-smi), PyTorch's CPU index is added so
# that pip takes the CPU build instead of PyPI's multi-GB CUDA build; with a GPU, PyPI's (CUDA) build.
if ! "$python" -c "import torch" 2>/dev/null; then
  cpu_index=()
  command -v nvidia-smi >/dev/null || cpu_index=(--extra-index-url https://download.pytorch.org/whl/cpu)
  "$python" -m pip install "torch==2.13.0" "${cpu_index[@]}" || fail "pip could not install torch==2.13.0 (see above)"
fi
"$python" -m pip install -e ".$extras" || fail "pip could not install neuralsurf$extras (see above)"

if [ -z "${VIRTUAL_ENV:-}" ]; then
  echo "install.sh: neuralsurf is installed in $(pwd)/.venv: run .venv/bin/python train.py ..., or" \
       "'source .venv/bin/activate' once per shell and then python, neuralsurf-train, neuralsurf-score, ..."
else
  echo "install.sh: neuralsurf is installed in the active environment $VIRTUAL_ENV"
fi
