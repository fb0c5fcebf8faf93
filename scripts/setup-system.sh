#!/usr/bin/env bash
# Installs the Debian packages gpuslice needs at run time, skipping those already present:
#   binutils libgcc-12-dev libc6-dev  PoCL (pip's pocl-binary-distribution) links every kernel with the system ld;
#                                     without them the process aborts on the first kernel build.
#   pocl-opencl-icd                   Debian's PoCL 3.1 (LLVM 15), a second CPU platform: the PoCL 3.0 (LLVM 14) in
#                                     PyOpenCL's wheels cannot build for CPUs its LLVM does not know (AMD Zen 5:
#                                     "unknown target CPU 'generic'"); gpuslice then picks this one by default.
#   libegl1 libegl-mesa0 libgl1 libgl1-mesa-dri   headless OpenGL (EGL + Mesa llvmpipe) for the moderngl rasteriser.
#   chromium                          the headless browser the viewer's test drives (through playwright).
#   oclgrind                          the OpenCL simulator tests/kernels/test_oclgrind.py runs every kernel under
#                                     (races, out-of-bounds, uninitialised values) through its own ICD file.
# Needs root (or sudo). Idempotent; prints what it installed.
set -euo pipefail
pkgs="binutils libgcc-12-dev libc6-dev pocl-opencl-icd libegl1 libegl-mesa0 libgl1 libgl1-mesa-dri chromium oclgrind"
need=""
for p in $pkgs; do
  dpkg -s "$p" >/dev/null 2>&1 || need="$need $p"
done
if [ -z "$need" ]; then
  echo "setup-system: all present ($pkgs)"
  exit 0
fi
SUDO=""
[ "$(id -u)" -eq 0 ] || SUDO="sudo"
echo "setup-system: installing$need"
$SUDO apt-get update -qq
DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends $need >/dev/null
echo "setup-system: done"
