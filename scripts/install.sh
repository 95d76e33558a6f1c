#!/usr/bin/env bash
# Set up u4d-aug on a fresh machine: system library for open3d, CPU torch, the package with its dev extras.
# Safe to re-run: every step is skipped when already done.
set -euo pipefail
cd "$(dirname "$0")/.."

SUDO=""
if [ "$(id -u)" -ne 0 ] && command -v sudo >/dev/null 2>&1; then SUDO="sudo"; fi

# open3d imports libusb-1.0 at load time.
if ! ldconfig -p 2>/dev/null | grep -q "libusb-1.0.so.0"; then
  echo "[install] apt-get install libusb-1.0-0 (needed by open3d)"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq libusb-1.0-0 >/dev/null
fi

PY="${PYTHON:-python3}"
# torch first and pinned: an unpinned torch pulls a multi-GB CUDA build; 2.13.0 is a CPU build on this machine's disk.
if ! "$PY" -c "import torch" >/dev/null 2>&1; then
  echo "[install] pip install torch==2.13.0"
  "$PY" -m pip install -q "torch==2.13.0"
fi
if ! "$PY" -c "import u4d_aug, open3d, pytest, xdist, ruff, mypy" >/dev/null 2>&1 || [ "${U4D_REINSTALL:-0}" = "1" ]; then
  echo "[install] pip install -e .[dev]"
  "$PY" -m pip install -q -e ".[dev]"
fi
"$PY" -c "import torch, open3d; print(f'[install] ok: torch {torch.__version__}, open3d {open3d.__version__}')"
