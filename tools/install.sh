#!/usr/bin/env bash
# Installs what the project needs on a fresh Debian/Ubuntu machine: the system library open3d
# links against, a virtual environment, the CPU build of torch, then the project with its test
# extra and Ray (the cluster extra: the tests run `slam evaluate` on a local Ray runtime too).
set -euo pipefail
VENV=${1:-.venv}
PYTHON=${PYTHON:-python3}

if ! ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then
  SUDO=""
  if [ "$(id -u)" != "0" ]; then SUDO="sudo"; fi
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq libusb-1.0-0 libgl1 libgomp1 >/dev/null
fi

if [ ! -x "$VENV/bin/python" ]; then
  "$PYTHON" -m venv "$VENV"
fi
"$VENV/bin/python" -m pip install -q --upgrade pip
# The CPU build first: an unpinned torch would pull a multi-GB CUDA build.
"$VENV/bin/python" -m pip install -q "torch==2.13.0"
"$VENV/bin/python" -m pip install -q -e ".[dev,cluster]"
"$VENV/bin/python" -c "import torch, open3d, cv2, kornia, rerun, numba, gtsam, ray; print('environment ready: torch', torch.__version__, '| open3d', open3d.__version__, '| opencv', cv2.__version__)"
