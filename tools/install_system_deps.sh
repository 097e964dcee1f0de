#!/usr/bin/env bash
# Installs the system packages satsweep needs on Debian/Ubuntu, and nothing else:
#   pocl-opencl-icd  - PoCL, the CPU OpenCL implementation (the PyPI "pyopencl[pocl]" build lists a
#                      device but cannot compile kernels on current CPUs, so Debian's is used)
#   libtiff-dev      - only for the test oracle rpcm, whose dependency srtm4 compiles against libtiff
#   python3-venv     - only when this python3 cannot create virtual environments (Debian's own
#                      python3 ships venv without ensurepip)
# Skips apt entirely when everything is already there. Uses sudo when not run as root.
set -euo pipefail
packages=(pocl-opencl-icd ocl-icd-libopencl1 libtiff-dev)
missing=()
for p in "${packages[@]}"; do
  dpkg -s "$p" >/dev/null 2>&1 || missing+=("$p")
done
if ! python3 -c "import ensurepip, venv" >/dev/null 2>&1; then
  missing+=("python3-venv")
fi
if [ ${#missing[@]} -eq 0 ]; then
  echo "system packages present: ${packages[*]} (and python3 can create venvs)"
  exit 0
fi
SUDO=""
if [ "$(id -u)" != "0" ]; then SUDO="sudo"; fi
echo "installing: ${missing[*]}"
$SUDO apt-get update -qq
DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
