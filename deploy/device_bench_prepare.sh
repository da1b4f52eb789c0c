#!/usr/bin/env bash
# Stages a CPU benchmark (`cropcraft bench accuracy`) for a lent device host: 16 cores against
# this machine's 2, offline, CPython 3.12, with numpy, numba, scipy, OpenCV and fsspec of its
# own and a threadpoolctl older than the 3.8 that cropcraft_core.optimize.bo needs
# (OpenBLASController.clear_controlling_thread; session 39's first try died of it). The wheels
# go to build/device-whl/ (git-ignored; 3.6 MB, plus scipy's 35 MB with --scipy, for a host
# without one): threadpoolctl, put ahead of the host's packages, and pydantic and PyYAML, put
# behind them (used only where the host lacks them):
#   bash deploy/device_bench_prepare.sh [--scipy]
# then on the device host, from the repository root, carrying build/device-whl:
#   bash deploy/device_bench_run.sh SECONDS --crop maize --scenes 42 --first 30 --workers 16 ...
# (benchmarks/RESULTS.md#device-cpu: 16 workers fit maize seeds at ~60 s each, 5 scenes in 285 s).
set -euo pipefail
cd "$(dirname "$0")/.."
dest=build/device-whl
rm -rf "$dest" && mkdir -p "$dest/first" "$dest/last"
ver() { .venv/bin/python -c "import importlib.metadata as m; print(m.version('$1'))"; }
pip=(.venv/bin/python -m pip download -q --no-deps --only-binary=:all: --python-version 3.12
  --implementation cp --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64
  --platform manylinux2014_x86_64)
# ahead of the host's own packages: the threadpoolctl this project needs
"${pip[@]}" -d "$dest/first" "threadpoolctl==$(ver threadpoolctl)"
# behind them: what the host lacks, at this project's versions
extra=()
[ "${1:-}" = "--scipy" ] && extra+=("scipy==$(ver scipy)")
"${pip[@]}" -d "$dest/last" "pydantic==$(ver pydantic)" "pydantic-core==$(ver pydantic-core)" \
  "annotated-types==$(ver annotated-types)" "typing-inspection==$(ver typing-inspection)" \
  "pyyaml==$(ver pyyaml)" "${extra[@]}"
du -sh "$dest"
