#!/usr/bin/env bash
# Check the system libraries that sceneforge's Python packages load at run time, and the
# build tools of its optional Embree extension; install the missing ones when we are root
# on a Debian/Ubuntu machine, and name them otherwise.
#   libEGL + Mesa's EGL driver  pyrender's offscreen rendering (GPU driver or Mesa software)
#   Mesa's DRI drivers          swrast_dri.so, the software rasteriser EGL falls back to
#   libGL                       PyOpenGL
#   libusb-1.0                  Open3D (its Python module links it even without devices)
#   libgomp                     Open3D (OpenMP)
#   libLLVM 16+                 Mitsuba 3's CPU backend (Dr.Jit; LLVM 14 and 15 abort on its kernels)
# Build tools of the Embree extension (setup.py builds it when they are there; without them
# the install still succeeds and ray tracing runs on Open3D, only slower):
#   g++                         the C++ compiler
#   libembree-dev               Embree's headers and library (Embree 3 on Debian 12, 4 on 13)
#   python3-dev                 Python's headers, where the venv's Python is Debian's own
set -euo pipefail
PYTHON=${PYTHON:-python3}
declare -A LIBS=(
  [libEGL.so.1]=libegl1
  [libEGL_mesa.so.0]=libegl-mesa0
  [libGL.so.1]=libgl1
  [libusb-1.0.so.0]=libusb-1.0-0
  [libgomp.so.1]=libgomp1
)
missing=()
for lib in "${!LIBS[@]}"; do
  # not `ldconfig -p | grep -q`: grep's early exit kills ldconfig with SIGPIPE, which pipefail reports
  grep -q "$lib" <(ldconfig -p 2>/dev/null) || missing+=("${LIBS[$lib]}")
done
# DRI drivers live outside the linker's path
compgen -G "/usr/lib/*/dri/swrast_dri.so" >/dev/null || compgen -G "/usr/lib*/dri/swrast_dri.so" >/dev/null \
  || missing+=(libgl1-mesa-dri)
# LLVM 16 or newer: the newest libllvmNN package the distribution has
newest_llvm=$( (ls /usr/lib/*/libLLVM*.so* 2>/dev/null || true) | sed -nE 's/.*libLLVM(-|\.so\.)([0-9]+).*/\2/p' \
  | sort -n | tail -n 1)
if [ "${newest_llvm:-0}" -lt 16 ]; then
  llvm=$(apt-cache search --names-only '^libllvm[0-9]+$' 2>/dev/null | cut -d' ' -f1 | sort -V | tail -n 1)
  missing+=("${llvm:-libllvm19}")
fi

build=()
command -v c++ >/dev/null || command -v g++ >/dev/null || build+=(g++)
compgen -G "/usr/include/embree[34]/rtcore.h" >/dev/null || compgen -G "/usr/local/include/embree[34]/rtcore.h" >/dev/null \
  || [ -n "${EMBREE_ROOT:-}" ] || build+=(libembree-dev)
# Debian's python3 keeps its headers in python3-dev; other Pythons (pyenv, conda) ship them
if [ "$(command -v "$PYTHON" || true)" = /usr/bin/python3 ] \
   && ! "$PYTHON" -c 'import os, sysconfig, sys; sys.exit(not os.path.exists(os.path.join(sysconfig.get_paths()["include"], "Python.h")))'; then
  build+=(python3-dev)
fi

if [ ${#missing[@]} -eq 0 ] && [ ${#build[@]} -eq 0 ]; then
  echo "system libraries and build tools: all present"
  exit 0
fi
if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
  apt-get update -qq
  if [ ${#missing[@]} -gt 0 ]; then
    mapfile -t missing < <(printf '%s\n' "${missing[@]}" | sort -u)
    echo "system libraries: installing ${missing[*]}"
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${missing[@]}" >/dev/null
  fi
  if [ ${#build[@]} -gt 0 ]; then
    echo "build tools of the Embree extension: installing ${build[*]}"
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${build[@]}" >/dev/null \
      || echo "could not install ${build[*]}: the Embree extension will not be built, ray tracing uses Open3D" >&2
  fi
  exit 0
fi
if [ ${#build[@]} -gt 0 ]; then
  echo "build tools missing: ${build[*]}; the Embree extension will not be built and ray tracing uses Open3D" >&2
  echo "for the fast engine install them as root, e.g.: sudo apt-get install ${build[*]}" >&2
fi
if [ ${#missing[@]} -gt 0 ]; then
  mapfile -t missing < <(printf '%s\n' "${missing[@]}" | sort -u)
  echo "system libraries missing: ${missing[*]}" >&2
  echo "install them as root, e.g.: sudo apt-get install ${missing[*]}" >&2
  exit 1
fi
