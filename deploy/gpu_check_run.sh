#!/usr/bin/env bash
# The device half of a nerfacto check, staged by deploy/gpu_check_prepare.sh SCENE_DIR: run on
# the lent CUDA host from the repository root, with $OUT the folder whose files come back
# (a few files of a few MB each: a tarball of the outputs is too big to come back).
#   bash deploy/gpu_check_run.sh SCENE_NAME SECONDS [--alone] [bench nerfacto train options...]
# `bench nerfacto train` on .gpu/SCENE_NAME with a training deadline of SECONDS (checkpoints
# every 500 steps), and in parallel the GPU acceptance test (tests/test_surfaces.py -m gpu:
# nerfacto on a 14-view arc, then rendered again from its saved copy; 240 s on an H200 beside a
# failed train half, session 82), unless --alone: training alone gets the whole GPU (session 44:
# 6,500 iterations of the 1.1 m canopy in 500 s on an H200; the call took 541 s, 572 s of device
# time with the machine's start; session 82: SA's 3,001 iterations in 272 s, the call 317 s).
# Back on the CPU machine: cropcraft bench nerfacto compare --scene-dir SCENE_DIR --kept <files_at>.
set -uo pipefail
name="${1:?usage: gpu_check_run.sh SCENE_NAME SECONDS [--alone] [train options]}"
seconds="${2:?usage: gpu_check_run.sh SCENE_NAME SECONDS [--alone] [train options]}"
shift 2
alone=0
if [ "${1:-}" = "--alone" ]; then alone=1; shift; fi
out="${OUT:?OUT must name the folder whose files come back}"
t0=$(date +%s)
pip install -q --no-index --no-deps --target /tmp/site .whl/*.whl > /tmp/pip.log 2>&1 \
  || { tail -n 20 /tmp/pip.log > "$out/pip.log"; exit 3; }
export PYTHONPATH="/tmp/site:$PWD" PYTHONUNBUFFERED=1
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader > "$out/gpu.txt"
# the train half imports all it needs at its top: a module the host lacks stops the call here,
# named in $OUT/preflight.log, before the acceptance test and the training start
python3 -c "import benchmarks.bench_nerfacto, cropcraft_core.surfaces.nerfacto" \
  > "$out/preflight.log" 2>&1 || { cat "$out/preflight.log"; exit 4; }
if [ "$alone" = 0 ]; then
  ( python3 -m pytest tests/test_surfaces.py -o addopts= -m gpu -q -rA -p no:cacheprovider \
      > "$out/acceptance.log" 2>&1
    echo "rc=$? at $(( $(date +%s) - t0 )) s" >> "$out/acceptance.log" ) &
fi
( mkdir -p /tmp/train
  python3 -m benchmarks.bench_nerfacto train --scene-dir ".gpu/$name" --iterations 20000 \
    --max-seconds "$seconds" --out /tmp/train "$@" > /tmp/train/stdout.log 2>&1
  echo "rc=$? at $(( $(date +%s) - t0 )) s" >> /tmp/train/stdout.log
  # points.npz comes back even where the row fit failed (compare reads it without the rest)
  for f in row.json observation.npz points.npz; do
    [ -f "/tmp/train/$f" ] && cp "/tmp/train/$f" "$out/$f"
  done
  tail -c 4000 /tmp/train/stdout.log > "$out/train.tail" ) &
wait
echo "all done $(( $(date +%s) - t0 )) s" >> "$out/gpu.txt"
cat "$out/gpu.txt" "$out/train.tail"
