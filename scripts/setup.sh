#!/usr/bin/env bash
# Set up kpcn on a fresh Debian machine: LLVM 19 for Mitsuba's llvm_ad_rgb
# variant (installed only when missing), a virtual environment in .venv, and the
# package with its test extras. Safe to run again; does nothing that is done.
set -euo pipefail
cd "$(dirname "$0")/.."

if ! ldconfig -p 2>/dev/null | grep -q 'libLLVM.so.19\|libLLVM-19'; then
  echo "[setup] installing Debian's libllvm19 (Mitsuba's llvm_ad_rgb needs LLVM >= 17)"
  SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq libllvm19 >/dev/null
fi

PY=${PYTHON:-python3.11}
command -v "$PY" >/dev/null || PY=python3
if [ ! -x .venv/bin/python ]; then
  echo "[setup] creating .venv with $PY"
  "$PY" -m venv .venv
fi
# torch is pinned to 2.13.0, whose CPU wheel lies on this machine's disk; a looser
# pin would pull a CUDA build of several GB.
.venv/bin/python -m pip install -q --upgrade pip >/dev/null
.venv/bin/python -m pip install -q -e ".[dev]"
echo "[setup] ok: $(.venv/bin/python -c 'import torch, mitsuba; print("torch", torch.__version__, "mitsuba", mitsuba.__version__)')"
