"""The paper's visible surfaces: nerfstudio's Nerfacto (needs nerfstudio and a CUDA GPU).

``fit`` writes the photos and a nerfstudio ``transforms.json`` (OpenGL camera axes, camera to
world) into ``config.workdir`` and runs ``ns-train cropcraft-nerfacto`` (nerfacto without its
eager LPIPS download, ``cropcraft_core.surfaces.nerfacto_method``; ``config.nerf_iterations``,
the paper's 20K, or fewer by ``config.nerf_max_seconds``; near/far planes, MLP width and
``nerfstudio-data --orientation-method`` from the config, see ``SurfacesConfig.for_crop``; more
options in ``config.nerf_args``). ``render`` loads the trained pipeline through
nerfstudio's ``eval_setup`` and renders any ``PinholeCamera``, mapping it into nerfstudio's
normalised frame with the run's ``dataparser_transforms.json`` and the depth back to metres of
z-depth. ``point_cloud`` renders every fitted view at a quarter size and unprojects it (as the
paper samples its NeRF). ``save`` keeps the trained run with the surfaces (``RUN_FOLDER``: ~80 MB,
the last checkpoint's weights without the optimisers' state), so that they load on another
worker or after the training folder is gone; a temporary training folder (no
``config.workdir``) is removed when the object is collected or the process exits.

Without nerfstudio or CUDA the constructor raises ``SurfacesError`` naming the CPU backend.

Status (November 26, benchmarks/RESULTS.md#nerfacto-scene): it runs end to end on an H100/H200
(without tiny-cuda-nn). With nerfstudio's far plane (1000) it explained the default synthetic
scene's canopy photos by a far backdrop (surfaces ~14× too far); with the far plane at the scene
(``SurfacesConfig.nerf_far_margin``, the default since) the views' median depth is right within
0.4 % after 1,000 iterations on an H200, but thin leaves are still missing (mask area −11 %). The
CPU backends stay the default.
"""

from __future__ import annotations

import importlib.util
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
import weakref
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
    in_bbox,
)

#: the nerfstudio method ``fit`` trains (``cropcraft_core.surfaces.nerfacto_method``, which
#: imports nerfstudio) and its ``NERFSTUDIO_METHOD_CONFIGS`` registration
METHOD = "cropcraft-nerfacto"
METHOD_ENV = f"{METHOD}=cropcraft_core.surfaces.nerfacto_method:method"
#: the folder inside saved surfaces that holds the trained run (``NerfactoSurfaces.save``)
RUN_FOLDER = "nerfacto_run"
#: checkpoint interval (steps): what a ``nerf_max_seconds`` deadline can lose
SAVE_EVERY = 500
UNAVAILABLE = (
    "nerfacto needs nerfstudio and a CUDA GPU; use a CPU backend: surfaces.backend tsdf (the "
    "default; --set surfaces.backend=tsdf) or points"
)
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


def pose_scale(cameras: list[PinholeCamera]) -> float:
    """The scale CropCraft gives nerfstudio-data (``--scale-factor``, auto-scaling off) when it
    sets the far plane itself: the camera centres' largest distance from their mean becomes 1,
    as nerfstudio's own auto-scale nearly does (it divides by the largest coordinate after
    centring and orienting, an L∞ norm, where this is an L2 norm: never larger)."""
    c = np.array([cam.center for cam in cameras])
    r = float(np.linalg.norm(c - c.mean(axis=0), axis=1).max())
    if not r > 0:
        raise InputError("the cameras all sit at one point: nerfacto needs a baseline")
    return 1.0 / r


def scene_far(cameras: list[PinholeCamera], bbox: np.ndarray) -> float:
    """The farthest any camera centre is from a corner of ``bbox`` (2, 3): no point of the box
    lies farther along any ray (m)."""
    lo, hi = np.asarray(bbox, np.float64)
    corners = np.array(np.meshgrid(*zip(lo, hi, strict=True), indexing="ij")).reshape(3, -1).T
    c = np.array([cam.center for cam in cameras])
    return float(np.linalg.norm(c[:, None, :] - corners[None], axis=2).max())


def far_plane_setting(
    cameras: list[PinholeCamera], bbox: np.ndarray, margin: float
) -> tuple[float, float]:
    """``SurfacesConfig.nerf_far_margin``'s (scale, far plane): nerfstudio-data's scale factor
    (:func:`pose_scale`) and ``margin`` × :func:`scene_far` in the frame that scale makes."""
    scale = pose_scale(cameras)
    return scale, float(margin) * scene_far(cameras, bbox) * scale


def train_command(
    cfg: SurfacesConfig, data: Path, out: Path, scale: float | None = None,
    far: float | None = None,
) -> list[str]:  # fmt: skip
    """The ``ns-train cropcraft-nerfacto`` command line for ``cfg`` (run it with
    :func:`train_env`), as ``python -m`` by this interpreter: the one ``nerfacto_available``
    found nerfstudio in, also where nerfstudio was installed without its console scripts on the
    PATH (``pip install --target``). Every photo trains (``--eval-mode all``: nerfstudio's
    default holds 10 % of them out), and nerfstudio's own evaluation passes are off (they only
    report image metrics, and build LPIPS, see ``nerfacto_method``)."""
    never = str(int(cfg.nerf_iterations) + 1)
    cmd = [
        sys.executable, "-m", "nerfstudio.scripts.train", METHOD,
        "--data", str(data),
        "--output-dir", str(out),
        "--experiment-name", "cropcraft",
        "--timestamp", "run",
        "--max-num-iterations", str(int(cfg.nerf_iterations)),
        "--machine.seed", str(int(cfg.seed)),
        "--vis", "tensorboard",
        "--viewer.quit-on-train-completion", "True",
        "--steps-per-save", str(SAVE_EVERY),
        "--steps-per-eval-batch", never,
        "--steps-per-eval-image", never,
        "--steps-per-eval-all-images", never,
    ]  # fmt: skip
    if cfg.near_plane is not None:
        cmd += ["--pipeline.model.near-plane", str(cfg.near_plane)]
    far = cfg.far_plane if far is None else far
    if far is not None:
        cmd += ["--pipeline.model.far-plane", str(far)]
    if cfg.hidden_dim is not None:
        cmd += ["--pipeline.model.hidden-dim", str(int(cfg.hidden_dim))]
    cmd += list(cfg.nerf_args)
    cmd += ["nerfstudio-data", "--orientation-method", cfg.orientation, "--eval-mode", "all"]
    if scale is not None:
        cmd += ["--auto-scale-poses", "False", "--scale-factor", repr(float(scale))]
    return cmd


def train_env() -> dict[str, str]:
    """This process's environment with ``cropcraft-nerfacto`` registered for nerfstudio."""
    env = os.environ.copy()
    known = env.get("NERFSTUDIO_METHOD_CONFIGS", "")
    env["NERFSTUDIO_METHOD_CONFIGS"] = ",".join(x for x in (known, METHOD_ENV) if x)
    return env


def _default_sigint() -> None:
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def run_training(cmd: list[str], log, deadline_s: float | None) -> tuple[int, bool]:
    """Run ``cmd`` (ns-train) in its own process group, output to ``log``; past ``deadline_s``
    stop it as Ctrl-C does (its trainer keeps the checkpoints it saved), and kill it 120 s
    later if it has not gone. Whatever it leaves in its group (nerfstudio's data workers) is
    killed at the end, also when this process is interrupted. Returns (exit code, stopped at
    the deadline)."""
    proc = subprocess.Popen(
        cmd,
        stdout=log,
        stderr=subprocess.STDOUT,
        env=train_env(),
        start_new_session=True,
        # a worker that ignores SIGINT would pass that on and the deadline's Ctrl-C would go
        # unheard (Python installs its KeyboardInterrupt only where SIGINT is not ignored)
        preexec_fn=_default_sigint,
    )
    stopped = False
    try:
        try:
            return proc.wait(timeout=deadline_s), stopped
        except subprocess.TimeoutExpired:
            stopped = True
            os.killpg(proc.pid, signal.SIGINT)
            try:
                return proc.wait(timeout=120), stopped
            except subprocess.TimeoutExpired:
                proc.kill()
                return proc.wait(), stopped
    finally:
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        proc.wait()


def last_checkpoint(run: Path) -> Path | None:
    """The run's latest ``nerfstudio_models/step-NNNNNNNNN.ckpt`` (zero-padded: the names
    sort by step), or None."""
    steps = sorted(run.glob("nerfstudio_models/step-*.ckpt"))
    return steps[-1] if steps else None


def log_tail(log: Path, lines: int = 15) -> str:
    """The last ``lines`` lines of a training log (for an error message a Prefect run shows)."""
    try:
        text = log.read_text(errors="replace")
    except OSError as e:
        return f"(cannot read {log}: {e})"
    return "\n".join(text.rstrip().splitlines()[-lines:])


def checkpoint_globals():
    """A ``torch.serialization.safe_globals`` context that lets nerfstudio 1.1's checkpoint
    loading (a bare ``torch.load``) read its own checkpoints under torch >= 2.6, whose
    ``weights_only`` default refuses the numpy scalars and dtypes nerfstudio saves in them
    (the step counter). Only numpy's scalar and dtype types are allowed, nothing that runs
    code."""
    import torch

    core = getattr(np, "_core", None) or np.core
    allowed = [core.multiarray.scalar, np.dtype]
    allowed += [getattr(np.dtypes, n) for n in getattr(np.dtypes, "__all__", ())]
    return torch.serialization.safe_globals(allowed)


class NerfactoSurfaces(SurfaceBackend):
    """nerfstudio Nerfacto trained on the posed photos (CUDA)."""

    name = "nerfacto"

    def __init__(self, config: SurfacesConfig | None = None) -> None:
        super().__init__(config or SurfacesConfig(backend="nerfacto"))
        if not nerfacto_available():
            raise SurfacesError(UNAVAILABLE)
        self.run_dir: Path | None = None
        self._relocated = False  # loaded from saved surfaces (``_relocate``)
        self._cleanup: weakref.finalize | None = None  # removes fit's own temporary folder
        self._pipeline = None
        self._transform = np.eye(4)
        self._scale = 1.0

    # ------------------------------------------------------------------ fit
    def fit(self, images, cameras, bbox=None, progress: Progress | None = None) -> None:
        imgs, cams, box = check_inputs(images, cameras, bbox)
        cfg = self.config
        scale = far = None
        if cfg.far_plane is None and cfg.nerf_far_margin is not None:
            if box is None:
                raise SurfacesError(
                    "surfaces nerf_far_margin needs a bounding box of the scene in the poses' "
                    "frame (surfaces.bbox), to put the far plane at; set nerf_far_margin to "
                    "null for nerfstudio's far plane (1000), or give far_plane"
                )
            scale, far = far_plane_setting(cams, box, cfg.nerf_far_margin)
            self.timings["nerf_far_plane"] = far  # in nerfstudio's frame
        if cfg.workdir:
            work = Path(cfg.workdir)
        else:  # a folder of its own (photos, checkpoints: hundreds of MB), gone with this object
            work = Path(tempfile.mkdtemp(prefix="cropcraft_nerfacto_"))
            self._cleanup = weakref.finalize(self, shutil.rmtree, str(work), True)
        data, out = work / "data", work / "outputs"
        write_transforms(data, imgs, cams)
        cmd = train_command(cfg, data, out, scale, far)
        if progress:
            progress("nerfacto", 0.0)
        log = work / "ns-train.log"
        t0 = time.perf_counter()
        with open(log, "w") as fh:
            rc, stopped = run_training(cmd, fh, cfg.nerf_max_seconds)
        if rc != 0 and not stopped:
            self._keep_workdir()
            raise SurfacesError(f"ns-train failed (exit {rc}); see {log}:\n{log_tail(log)}")
        self.timings["nerf_train"] = time.perf_counter() - t0
        self.run_dir = out / "cropcraft" / METHOD / "run"
        last = last_checkpoint(self.run_dir)
        if last is None:
            self._keep_workdir()
            raise SurfacesError(
                f"ns-train stopped before its first checkpoint; see {log}:\n{log_tail(log)}"
            )
        self.timings["nerf_iterations_done"] = int(last.stem.split("-")[1]) + 1
        self.cameras, self.bbox = cams, box
        self._read_run()
        if progress:
            progress("nerfacto", 1.0)

    def _keep_workdir(self) -> None:
        """A failed fit keeps its temporary folder: its ns-train.log is what says why."""
        if self._cleanup is not None:
            self._cleanup.detach()
            self._cleanup = None

    def _read_run(self) -> None:
        meta = json.loads((self._require_run() / "dataparser_transforms.json").read_text())
        t = np.eye(4)
        t[:3, :4] = np.asarray(meta["transform"], np.float64)
        self._transform, self._scale = t, float(meta["scale"])
        self._pipeline = None

    def _load_pipeline(self):
        if self._pipeline is None:
            from nerfstudio.configs.method_configs import all_methods
            from nerfstudio.utils.eval_utils import eval_setup

            from cropcraft_core.surfaces.nerfacto_method import method

            all_methods.setdefault(METHOD, method.config)  # eval_setup looks the run's up
            with checkpoint_globals():
                _, self._pipeline, _, _ = eval_setup(
                    self.run_dir / "config.yml",
                    test_mode="inference",
                    update_config_callback=self._relocate if self._relocated else None,
                )
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

    def render_supported(self, camera: PinholeCamera) -> np.ndarray:
        """``render``'s depth where it lies inside the bounding box: outside it a ray met what
        the field put beyond the scene (the backdrop at the far plane, where it saw past the
        soil), not a surface of the plot."""
        depth = self.render(camera)[0]
        if self.bbox is None:
            return depth
        seen = np.isfinite(depth)
        points = camera.unproject(np.where(seen, depth, 0.0)).reshape(-1, 3)
        inside = in_bbox(points, self.bbox).reshape(depth.shape)
        return np.where(seen & inside, depth, np.nan).astype(np.float32)

    def point_cloud(self, n_max: int = 100_000) -> tuple[np.ndarray, np.ndarray]:
        return self.rendered_point_cloud(n_max)

    # ------------------------------------------------------------------ persistence
    def _save_payload(self, folder: Path) -> dict:
        """Copy what rendering needs into ``folder/RUN_FOLDER`` so that the saved surfaces load
        on another host, or after the training folder is gone: the run's ``config.yml`` and
        ``dataparser_transforms.json``, the dataset's ``transforms.json`` (nerfstudio's data
        parser reads it to build the model; no photo is read) and the last checkpoint with the
        pipeline's weights only (the optimisers' state, about two thirds of the file, dropped)."""
        import torch

        run = self._require_run()
        last = last_checkpoint(run)
        if last is None:
            raise SurfacesError(f"no nerfacto checkpoint in {run / 'nerfstudio_models'}")
        dest = folder / RUN_FOLDER
        (dest / "nerfstudio_models").mkdir(parents=True, exist_ok=True)
        (dest / "data").mkdir(exist_ok=True)
        for name in ("config.yml", "dataparser_transforms.json"):
            shutil.copyfile(run / name, dest / name)
        shutil.copyfile(self._data_dir() / "transforms.json", dest / "data" / "transforms.json")
        with checkpoint_globals():
            state = torch.load(last, map_location="cpu")
        slim = {"pipeline": state["pipeline"], "step": int(state["step"])}
        tmp = dest / "nerfstudio_models" / (last.name + ".tmp")
        torch.save(slim, tmp)
        os.replace(tmp, dest / "nerfstudio_models" / last.name)
        return {"run": RUN_FOLDER, "step": slim["step"]}

    def _load_payload(self, folder: Path, meta: dict) -> None:
        if not nerfacto_available():
            raise SurfacesError(UNAVAILABLE)
        self._relocated, self._cleanup = False, None  # (load does not run __init__)
        if "run" in meta:
            self.run_dir = folder / str(meta["run"])
            self._relocated = True
        elif "run_dir" in meta:  # saved before the run was kept with the surfaces
            self.run_dir = Path(meta["run_dir"])
        else:
            raise InputError(f"{folder}: saved nerfacto surfaces name no training run")
        self._read_run()

    def _require_run(self) -> Path:
        if self.run_dir is None or not (self.run_dir / "config.yml").exists():
            raise SurfacesError(f"no trained nerfacto run in {self.run_dir}")
        return self.run_dir

    def _data_dir(self) -> Path:
        """The nerfstudio dataset the run was trained on (its ``transforms.json``): beside the
        run when loaded from saved surfaces, else ``fit``'s workdir/data (the run is
        workdir/outputs/cropcraft/METHOD/run, as :func:`train_command` lays it out)."""
        run = self._require_run()
        return run / "data" if self._relocated else run.parents[3] / "data"

    def _relocate(self, config):
        """``eval_setup``'s callback for a run loaded from saved surfaces: the checkpoint and the
        dataset are where ``save`` put them, not where training wrote them, and no photo is
        opened (nerfstudio-data's automatic downscale reads the first; training used 1). The
        checkpoint folder is given as an absolute path, which nerfstudio's
        ``base_dir / relative_model_dir`` then is."""
        run = self._require_run().resolve()
        config.relative_model_dir = run / "nerfstudio_models"
        dm = config.pipeline.datamanager
        dm.data = run / "data"
        dm.dataparser.data = run / "data"
        dm.dataparser.downscale_factor = 1
        return config
