#!/usr/bin/env bash
# Installs the system packages satsweep needs on Debian/Ubuntu, and nothing else:
#   pocl-opencl-icd  - PoCL, the CPU OpenCL implementation (the PyPI "pyopencl[pocl]" build lists a
#                      device but cannot compile kernels on current CPUs, so Debian's is used)
#   libtiff-dev      - only for the test oracle rpcm, whose dependency srtm4 compiles against libtiff
# Skips apt entirely when both are already installed. Uses sudo when not run as root.
set -euo pipefail
packages=(pocl-opencl-icd ocl-icd-libopencl1 libtiff-dev)
missing=()
for p in "${packages[@]}"; do
  dpkg -s "$p" >/dev/null 2>&1 || missing+=("$p")
done
if [ ${#missing[@]} -eq 0 ]; then
  echo "system packages present: ${packages[*]}"
  exit 0
fi
SUDO=""
if [ "$(id -u)" != "0" ]; then SUDO="sudo"; fi
echo "installing: ${missing[*]}"
$SUDO apt-get update -qq
DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
