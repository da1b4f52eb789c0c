#!/usr/bin/env bash
# Re-resolves CropCraft's dependencies from pyproject.toml alone and writes every resolved
# version to deploy/constraints.txt, the lock that deploy/install.sh and docker/Dockerfile.cpu
# install from. Run it when pyproject.toml's dependencies change or to take newer releases on
# purpose, then rerun the tests and the demo: the fit's answer moves with the numeric libraries
# (benchmarks/RESULTS.md#demo), so a new lock is a change to commit and measure, not a refresh.
#   bash deploy/lock.sh            (about 4 minutes; needs the package index install.sh uses)
set -euo pipefail
cd "$(dirname "$0")/.."
py="${PYTHON:-python3.11}"
command -v "$py" >/dev/null || py=python3
tmp="$(mktemp -d)"
trap 'rm -rf "$tmp"' EXIT
"$py" -m venv "$tmp/venv"
"$tmp/venv/bin/python" -m pip install -q --upgrade pip >/dev/null
"$tmp/venv/bin/python" -m pip install -q "torch==2.13.0+cpu" \
  --extra-index-url https://download.pytorch.org/whl/cpu --retries 1  # as install.sh
"$tmp/venv/bin/python" -m pip install -q -e ".[dev]"
{
  echo "# CropCraft's lock: every package of a fresh '.[dev]' install, resolved by deploy/lock.sh"
  echo "# on $(date -u +%Y-%m-%d) with $("$tmp/venv/bin/python" -V 2>&1) on $(uname -m)."
  echo "# deploy/install.sh and docker/Dockerfile.cpu install with it as pip constraints"
  echo "# (-c), so every fresh machine computes with the same numeric libraries."
  # a local version label (torch's +cpu) is dropped so the pin also matches the index's build
  "$tmp/venv/bin/python" -m pip freeze --exclude-editable | sed -E 's/\+[A-Za-z0-9.]+$//' | sort -f
} > deploy/constraints.txt.tmp
mv deploy/constraints.txt.tmp deploy/constraints.txt
echo "wrote deploy/constraints.txt ($(grep -vc '^#' deploy/constraints.txt) packages)"
