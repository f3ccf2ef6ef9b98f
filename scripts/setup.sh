#!/usr/bin/env bash
# Set up kpcn on a fresh Debian machine: LLVM 19 for Mitsuba's llvm_ad_rgb
# variant and the X11/GL libraries Blender's bpy module links against (each
# installed only when missing), a virtual environment in .venv, and the package
# with its test and Blender extras. Safe to run again; does nothing that is done.
set -euo pipefail
cd "$(dirname "$0")/.."

SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
APT_UPDATED=""
apt_install() {  # apt_install PACKAGE...: quietly, running apt-get update once
  if [ -z "$APT_UPDATED" ]; then $SUDO apt-get update -qq; APT_UPDATED=1; fi
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq "$@" >/dev/null
}

# the linker cache, read once (grep -q on a pipe could stop ldconfig early: a failed pipeline under pipefail)
LDCACHE=$(ldconfig -p 2>/dev/null || true)
if ! grep -q 'libLLVM.so.19\|libLLVM-19' <<<"$LDCACHE"; then
  echo "[setup] installing Debian's libllvm19 (Mitsuba's llvm_ad_rgb needs LLVM >= 17)"
  apt_install libllvm19
fi

# bpy (the `blender` extra) links against these system libraries (soname:Debian package)
BPY_LIBS="libX11.so.6:libx11-6 libXext.so.6:libxext6 libXrender.so.1:libxrender1 libXfixes.so.3:libxfixes3
libXi.so.6:libxi6 libxkbcommon.so.0:libxkbcommon0 libSM.so.6:libsm6 libICE.so.6:libice6 libGL.so.1:libgl1"
missing=""
for pair in $BPY_LIBS; do
  grep -q "${pair%%:*} " <<<"$LDCACHE" || missing="$missing ${pair#*:}"
done
if [ -n "$missing" ]; then
  echo "[setup] installing libraries Blender's bpy needs:$missing"
  apt_install $missing
fi

PY=${PYTHON:-python3.11}
command -v "$PY" >/dev/null || PY=python3
if [ ! -x .venv/bin/python ]; then
  echo "[setup] creating .venv with $PY"
  "$PY" -m venv .venv
fi
# torch is pinned to 2.13.0, whose CPU wheel lies on this machine's disk; a looser
# pin would pull a CUDA build of several GB.
# --no-cache-dir: a fresh machine gains nothing from pip's cache, and keeping a second copy of every downloaded
# wheel (bpy alone ~375 MB) has run a nearly full disk out of space before the install finished
.venv/bin/python -m pip install -q --no-cache-dir --upgrade pip >/dev/null
# the `blender` extra (bpy 5.0.1, ~375 MB download) lets the Cycles tests run; bpy pins numpy < 2
.venv/bin/python -m pip install -q --no-cache-dir -e ".[dev,blender]"
echo "[setup] ok: $(.venv/bin/python -c 'import torch, mitsuba, bpy; print("torch", torch.__version__, "mitsuba", mitsuba.__version__, "bpy", bpy.app.version_string)')"
# the native kernels (kpcn/ops/native), compiled for this CPU now rather than on the first denoise; without a C
# compiler the PyTorch paths run instead, and this line says so
echo "[setup] native kernels: $(.venv/bin/python -W ignore -c 'from kpcn.ops import native; print(native.status())')"
