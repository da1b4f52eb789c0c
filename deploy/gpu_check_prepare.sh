#!/usr/bin/env bash
# Stages a nerfacto check for an offline CUDA host that already has torch, numpy, OpenCV, numba,
# tensorboard and torchmetrics (CPython 3.12, x86-64), such as the lent GPU machines: the wheels
# of nerfstudio 1.1.5 and of those of its needs `ns-train` imports (23 MB) into .whl/, and a
# `cropcraft synth` scene (photos, transforms.json, scene.json, the depth of the views
# `bench nerfacto train` scores) into .gpu/SCENE_NAME/. Both folders must be git-ignored.
#   bash deploy/gpu_check_prepare.sh SCENE_DIR
# then on the GPU host (carrying .whl and .gpu), from the repository root, the acceptance test
# and a training run side by side with their small outputs in $OUT (--alone: training only):
#   bash deploy/gpu_check_run.sh SCENE_NAME SECONDS [--alone] [bench nerfacto train options]
# or by hand:
#   pip install --no-index --no-deps --target /tmp/site .whl/*.whl
#   PYTHONPATH=/tmp/site:$PWD python3 -m benchmarks.bench_nerfacto train \
#       --scene-dir .gpu/SCENE_NAME --max-seconds 330 --out OUT
# and back here: cropcraft bench nerfacto compare --scene-dir SCENE_DIR --kept OUT
# (benchmarks/RESULTS.md#nerfacto-gpu, #nerfacto-far-plane: what the runs found). The far plane
# sits at the scene box by default (surfaces.nerf_far_margin 1.5); --far-margin off gives
# nerfstudio's own (1000). Three runs side by side share the GPU (~1,200 steps each in 270 s);
# beside the acceptance test one run reached 2,000 steps in 370 s (H100), alone 3,000 in 285 s
# (H200, start-up included); the acceptance test passes (session 35), so a device session that
# asks how far more training goes can run `bench nerfacto train` alone;
# $OUT returns files of a few MB (row.json, observation.npz, points.npz), not a tarball of them
# all. To watch the density form step by
# step instead (benchmarks/RESULTS.md#nerfacto-scene), on the GPU host:
#   python3 -m benchmarks.nerfacto_probe prepare --scene-dir .gpu/SCENE_NAME --out /tmp/s
#   python3 -m benchmarks.nerfacto_probe train --scene-dir /tmp/s --rays 4096 --steps 1000 \
#       --every 100 --max-seconds 200 [--far-margin 1.1] [--set NAME=VALUE]
# (prepare --plane makes the textured control plane from the same cameras). The acceptance test
# (nerfacto fits a synthetic arc of 14 views; 2,000 iterations, a few minutes alone):
#   PYTHONPATH=/tmp/site:$PWD python3 -m pytest tests/test_surfaces.py -o addopts= -m gpu -rA
set -euo pipefail
cd "$(dirname "$0")/.."
scene="${1:?usage: deploy/gpu_check_prepare.sh SCENE_DIR}"
[ -f "$scene/transforms.json" ] || { echo "$scene: no transforms.json (a cropcraft synth scene?)" >&2; exit 2; }
pip=(.venv/bin/python -m pip download -q --no-deps -d .whl)
mkdir -p .whl
"${pip[@]}" nerfstudio==1.1.5 tyro==0.8.14 shtab docstring-parser appdirs dill pathos ppft \
  gsplat==1.4.0 nerfacc==0.5.2 pyquaternion pytorch-msssim splines==0.3.0 tensorly viser==0.2.7
# pytest, for the acceptance test (tests/test_surfaces.py -m gpu; it needs no Open3D);
# pydantic, which the store's records (cropcraft_core.store) are made of and the device's image
# lacks (session 82: the train half's first import died on it); versions as deploy/constraints.txt
"${pip[@]}" pytest pluggy iniconfig pygments packaging \
  pydantic==2.14.4 annotated-types typing-inspection
# compiled ones for the host's CPython 3.12; rawpy, not newrawpy (built against numpy 1)
"${pip[@]}" --only-binary=:all: --python-version 3.12 --implementation cp \
  --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 \
  --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 --platform manylinux1_x86_64 \
  fpsample==0.3.3 msgspec==0.22.0 rawpy==0.28.0 websockets pydantic_core==2.50.5

name="$(basename "$scene")"
dest=".gpu/$name"
rm -rf "$dest" && mkdir -p "$dest/depth"
cp -r "$scene/images" "$scene/transforms.json" "$scene/scene.json" "$dest/"
# the true depth of the views bench_nerfacto.train scores
.venv/bin/python - "$scene" "$dest" <<'EOF'
import shutil, sys
from pathlib import Path
from benchmarks.bench_nerfacto import scored_views
from cropcraft_core.sfm import import_transforms_json
src, dest = Path(sys.argv[1]), Path(sys.argv[2])
for name, _ in scored_views(import_transforms_json(src / "transforms.json")):
    shutil.copy(src / "depth" / f"{Path(name).stem}.npy", dest / "depth")
EOF
du -sh .whl "$dest"
