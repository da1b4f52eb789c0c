"""The paper's visible surfaces: nerfstudio's Nerfacto (needs nerfstudio and a CUDA GPU).

``fit`` writes the photos and a nerfstudio ``transforms.json`` (OpenGL camera axes, camera to
world) into ``config.workdir`` and runs ``ns-train nerfacto`` (``config.nerf_iterations``, the
paper's 20K; near/far planes, MLP width and ``nerfstudio-data --orientation-method`` from the
config, see ``SurfacesConfig.for_crop``). ``render`` loads the trained pipeline through
nerfstudio's ``eval_setup`` and renders any ``PinholeCamera``, mapping it into nerfstudio's
normalised frame with the run's ``dataparser_transforms.json`` and the depth back to metres of
z-depth. ``point_cloud`` renders every fitted view at a quarter size and unprojects it (as the
paper samples its NeRF).

Without nerfstudio or CUDA the constructor raises ``SurfacesError`` naming the CPU backend.
"""

from __future__ import annotations

import importlib.util
import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from cropcraft_core.errors import InputError
from cropcraft_core.geometry.camera import PinholeCamera
from cropcraft_core.surfaces.base import (
    Progress,
    SurfaceBackend,
    SurfacesConfig,
    SurfacesError,
    check_inputs,
)

UNAVAILABLE = "nerfacto needs nerfstudio and a CUDA GPU; use the CPU backend: --surfaces tsdf"
#: OpenCV camera axes ↔ OpenGL (nerfstudio) camera axes
GL_FROM_CV = np.diag([1.0, -1.0, -1.0, 1.0])


def nerfacto_available() -> bool:
    """True where nerfstudio imports and torch sees a CUDA device."""
    if importlib.util.find_spec("nerfstudio") is None:
        return False
    try:
        import torch
    except ImportError:  # pragma: no cover - torch is a dependency
        return False
    return bool(torch.cuda.is_available())


def write_transforms(folder: Path, images: list[np.ndarray], cameras: list[PinholeCamera]) -> Path:
    """Write images/frame_NNNNN.png and a nerfstudio transforms.json (per-frame PINHOLE
    intrinsics, ``transform_matrix`` = camera-to-world in OpenGL axes) into ``folder``."""
    from PIL import Image

    (folder / "images").mkdir(parents=True, exist_ok=True)
    frames = []
    for i, (im, cam) in enumerate(zip(images, cameras, strict=True)):
        name = f"images/frame_{i:05d}.png"
        Image.fromarray(im).save(folder / name)
        frames.append(
            {
                "file_path": name,
                "fl_x": cam.fx, "fl_y": cam.fy, "cx": cam.cx, "cy": cam.cy,
                "w": cam.width, "h": cam.height,
                "transform_matrix": (cam.cam_to_world @ GL_FROM_CV).tolist(),
            }
        )  # fmt: skip
    path = folder / "transforms.json"
    path.write_text(json.dumps({"camera_model": "OPENCV", "frames": frames}, indent=1))
    return path


def train_command(cfg: SurfacesConfig, data: Path, out: Path) -> list[str]:
    """The ``ns-train nerfacto`` command line for ``cfg``."""
    cmd = [
        "ns-train", "nerfacto",
        "--data", str(data),
        "--output-dir", str(out),
        "--experiment-name", "cropcraft",
        "--timestamp", "run",
        "--max-num-iterations", str(int(cfg.nerf_iterations)),
        "--machine.seed", str(int(cfg.seed)),
        "--vis", "tensorboard",
        "--viewer.quit-on-train-completion", "True",
    ]  # fmt: skip
    if cfg.near_plane is not None:
        cmd += ["--pipeline.model.near-plane", str(cfg.near_plane)]
    if cfg.far_plane is not None:
        cmd += ["--pipeline.model.far-plane", str(cfg.far_plane)]
    if cfg.hidden_dim is not None:
        cmd += ["--pipeline.model.hidden-dim", str(int(cfg.hidden_dim))]
    cmd += ["nerfstudio-data", "--orientation-method", cfg.orientation]
    return cmd


class NerfactoSurfaces(SurfaceBackend):
    """nerfstudio Nerfacto trained on the posed photos (CUDA)."""

    name = "nerfacto"

    def __init__(self, config: SurfacesConfig | None = None) -> None:
        super().__init__(config or SurfacesConfig(backend="nerfacto"))
        if not nerfacto_available():
            raise SurfacesError(UNAVAILABLE)
        self.run_dir: Path | None = None
        self._pipeline = None
        self._transform = np.eye(4)
        self._scale = 1.0

    # ------------------------------------------------------------------ fit
    def fit(self, images, cameras, bbox=None, progress: Progress | None = None) -> None:
        imgs, cams, box = check_inputs(images, cameras, bbox)
        cfg = self.config
        work = Path(cfg.workdir or tempfile.mkdtemp(prefix="cropcraft_nerfacto_"))
        data, out = work / "data", work / "outputs"
        write_transforms(data, imgs, cams)
        exe = shutil.which("ns-train") or str(Path(sys.executable).parent / "ns-train")
        cmd = train_command(cfg, data, out)
        cmd[0] = exe
        if progress:
            progress("nerfacto", 0.0)
        log = work / "ns-train.log"
        with open(log, "w") as fh:
            rc = subprocess.run(cmd, stdout=fh, stderr=subprocess.STDOUT, env=os.environ.copy())
        if rc.returncode != 0:
            raise SurfacesError(f"ns-train failed (exit {rc.returncode}); see {log}")
        self.run_dir = out / "cropcraft" / "nerfacto" / "run"
        self.cameras, self.bbox = cams, box
        self._read_run()
        if progress:
            progress("nerfacto", 1.0)

    def _read_run(self) -> None:
        if self.run_dir is None or not (self.run_dir / "config.yml").exists():
            raise SurfacesError(f"no trained nerfacto run in {self.run_dir}")
        meta = json.loads((self.run_dir / "dataparser_transforms.json").read_text())
        t = np.eye(4)
        t[:3, :4] = np.asarray(meta["transform"], np.float64)
        self._transform, self._scale = t, float(meta["scale"])
        self._pipeline = None

    def _load_pipeline(self):
        if self._pipeline is None:
            from nerfstudio.utils.eval_utils import eval_setup

            _, self._pipeline, _, _ = eval_setup(self.run_dir / "config.yml", test_mode="inference")
        return self._pipeline

    # ------------------------------------------------------------------ queries
    def render(self, camera: PinholeCamera) -> tuple[np.ndarray, np.ndarray]:
        self._require_fitted()
        import torch
        from nerfstudio.cameras.cameras import Cameras, CameraType

        pipe = self._load_pipeline()
        c2w = self._transform @ camera.cam_to_world @ GL_FROM_CV
        c2w[:3, 3] *= self._scale
        cams = Cameras(
            camera_to_worlds=torch.tensor(c2w[None, :3, :4], dtype=torch.float32),
            fx=float(camera.fx), fy=float(camera.fy), cx=float(camera.cx), cy=float(camera.cy),
            width=int(camera.width), height=int(camera.height),
            camera_type=CameraType.PERSPECTIVE,
        ).to(pipe.device)  # fmt: skip
        with torch.no_grad():
            outs = pipe.model.get_outputs_for_camera(cams)
        dist = outs["depth"][..., 0].float().cpu().numpy() / self._scale  # along unit rays
        rgb = outs["rgb"].float().cpu().numpy()
        norm = np.linalg.norm(camera.ray_directions(normalized=False), axis=-1)
        depth = (dist / norm).astype(np.float32)
        depth[~np.isfinite(depth) | (depth <= 0)] = np.nan
        return depth, np.clip(np.rint(rgb * 255), 0, 255).astype(np.uint8)

    def point_cloud(self, n_max: int = 100_000) -> tuple[np.ndarray, np.ndarray]:
        return self.rendered_point_cloud(n_max)

    # ------------------------------------------------------------------ persistence
    def _save_payload(self, folder: Path) -> dict:
        return {"run_dir": str(self.run_dir)}

    def _load_payload(self, folder: Path, meta: dict) -> None:
        if not nerfacto_available():
            raise SurfacesError(UNAVAILABLE)
        if "run_dir" not in meta:
            raise InputError(f"{folder}: saved nerfacto surfaces name no training run")
        self.run_dir = Path(meta["run_dir"])
        self._read_run()
