#!/usr/bin/env bash
# LLVM 19 for Mitsuba's vectorised llvm_ad_rgb variant (irradiance ground truth of imports,
# training-data renders). Debian/Ubuntu: apt's libllvm19; LLVM 15/16 fail with a codegen error.
# Does nothing when the library is already there; uses sudo when not root.
set -euo pipefail
lib=/usr/lib/x86_64-linux-gnu/libLLVM-19.so
if [ -e "$lib" ] || [ -n "${DRJIT_LIBLLVM_PATH:-}" ]; then
  exit 0
fi
bash "$(dirname "$0")/apt_install.sh" libllvm19 \
  "install LLVM 19 with your package manager and set DRJIT_LIBLLVM_PATH to its libLLVM .so"
echo "installed libllvm19 ($lib)"
