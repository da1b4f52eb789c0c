#!/usr/bin/env bash
# Installs everything CropCraft needs on a fresh Debian machine with Python 3.11:
# system libraries (apt-get), then a virtual environment in .venv with the project in it.
#   bash deploy/install.sh          runtime only
#   bash deploy/install.sh --dev    plus the test tools (pytest, ruff, pyhelios3d, moto)
set -euo pipefail
cd "$(dirname "$0")/.."
extra=""
[ "${1:-}" = "--dev" ] && extra="[dev]"

# Open3D's CPU wheel links libusb, libgomp and libGL at import time; pyhelios3d (tests) links
# libSM, libICE, libX11 and libXext; the virtual environment needs python3-venv.
need=()
for pkg in libusb-1.0-0 libgomp1 libgl1 libegl1 libsm6 libice6 libx11-6 libxext6 python3-venv; do
  dpkg -s "$pkg" >/dev/null 2>&1 || need+=("$pkg")
done
if [ ${#need[@]} -gt 0 ]; then
  sudo_cmd=""; [ "$(id -u)" -ne 0 ] && sudo_cmd="sudo"
  $sudo_cmd apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $sudo_cmd apt-get install -y -qq "${need[@]}" >/dev/null
fi

py="${PYTHON:-python3.11}"
command -v "$py" >/dev/null || py=python3
[ -x .venv/bin/python ] || "$py" -m venv .venv
stamp=".venv/.installed${extra}"
if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ] || [ deploy/constraints.txt -nt "$stamp" ]; then
  # torch is pinned first on its own so that nothing pulls a CUDA build. Every package comes
  # at the version deploy/constraints.txt locks (deploy/lock.sh re-resolves it): the fit's
  # answer moves with the numeric libraries, so every fresh machine gets the same ones.
  .venv/bin/python -m pip install -q --upgrade pip >/dev/null
  # The CPU build by name: PyPI's torch==2.13.0 is the CUDA one (gigabytes of nvidia-*
  # wheels and triton), which a constraints file cannot keep out. Its index is extra, so a
  # machine with the wheel in its own find-links or mirror takes it from there.
  .venv/bin/python -m pip install -q "torch==2.13.0+cpu" -c deploy/constraints.txt \
    --extra-index-url https://download.pytorch.org/whl/cpu --retries 1
  .venv/bin/python -m pip install -q -e ".${extra}" -c deploy/constraints.txt
  touch "$stamp"
fi
