#!/usr/bin/env bash
# Check the system libraries that sceneforge's Python packages load at run time, install the
# missing ones when we are root on a Debian/Ubuntu machine, and name them otherwise.
#   libEGL + Mesa's EGL driver  pyrender's offscreen rendering (GPU driver or Mesa software)
#   Mesa's DRI drivers          swrast_dri.so, the software rasteriser EGL falls back to
#   libGL                       PyOpenGL
#   libusb-1.0                  Open3D (its Python module links it even without devices)
#   libgomp                     Open3D and embreex (OpenMP)
#   libLLVM 16+                 Mitsuba 3's CPU backend (Dr.Jit; LLVM 14 and 15 abort on its kernels)
set -euo pipefail
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
if [ ${#missing[@]} -eq 0 ]; then
  echo "system libraries: all present"
  exit 0
fi
mapfile -t missing < <(printf '%s\n' "${missing[@]}" | sort -u)
if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
  echo "system libraries: installing ${missing[*]}"
  apt-get update -qq
  DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${missing[@]}" >/dev/null
else
  echo "system libraries missing: ${missing[*]}" >&2
  echo "install them as root, e.g.: sudo apt-get install ${missing[*]}" >&2
  exit 1
fi
