"""Why nerfacto's surfaces come out far away: train it in this process and watch its density.

Session 29 found with it that nerfacto (nerfstudio 1.1.5, torch fallback) learns a textured
ground plane seen by the default synthetic scene's cameras within a few hundred steps, but on
that scene's canopy photos lets the density near the plot collapse within ~100 steps and paints
the photos on a far backdrop; a far plane at the scene kept the density at the canopy in CPU
runs (benchmarks/RESULTS.md#nerfacto-scene). This runs that experiment where anyone can
repeat it, on a GPU in minutes or on a CPU in an hour:

    python -m benchmarks.nerfacto_probe prepare --scene-dir SYNTH_SCENE --out PLANE --plane
    python -m benchmarks.nerfacto_probe train --scene-dir PLANE --steps 200 [--set far_plane=6.0]

``prepare --plane`` renders a control scene: the synth scene's cameras looking at a richly
textured plane z = 0 (its photos, nerfstudio's ``transforms.json`` in ``data/``, true z-depth
per view); without ``--plane`` the same files of the synth scene's own photos.
``train`` builds ``cropcraft-nerfacto`` on nerfstudio-data as ``NerfactoSurfaces`` does, trains
it step by step and every ``--every`` steps prints, for 256 fixed training rays with a known true
distance, the accumulated opacity within 6 scene units, where the density's weight peaks against
the truth (median relative error; 0 is right) and the density's size. A healthy radiance field's
peak error falls towards 0 within a few hundred steps. nerfstudio must be importable (see
``deploy/gpu_check_prepare.sh`` for its wheels; on a CPU-only host the torch fallback runs).
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

import numpy as np

#: probe rays (a fixed training batch's first ones) and their distance grid (scene units)
N_RAYS, GRID_FAR, GRID_N = 256, 6.0, 400


def plane_texture(x: np.ndarray, y: np.ndarray, seed: int = 0) -> np.ndarray:
    """RGB in [0, 1] at ground points (m): four scales (1 m to 2 cm) of bilinear colour noise
    over a 40 m square, so every patch is distinct."""
    rng = np.random.default_rng(seed)
    out = np.zeros(x.shape + (3,))
    scales = (1.0, 0.25, 0.06, 0.02)
    for s in scales:
        n = int(40 / s) + 2
        g = rng.random((n, n, 3))
        u, v = (x + 20) / s, (y + 20) / s
        i = np.clip(np.floor(u).astype(int), 0, n - 2)
        j = np.clip(np.floor(v).astype(int), 0, n - 2)
        fu, fv = (u - i)[..., None], (v - j)[..., None]
        out += (
            g[i, j] * (1 - fu) * (1 - fv)
            + g[i + 1, j] * fu * (1 - fv)
            + g[i, j + 1] * (1 - fu) * fv
            + g[i + 1, j + 1] * fu * fv
        )
    return out / len(scales)


def prepare(a: argparse.Namespace) -> dict:
    """``--out``: nerfstudio's ``data/`` (photos, transforms.json), the true z-depth per view in
    ``depth/`` and our ``transforms.json``: of the synth scene's own photos, or with ``--plane``
    of the control plane seen by the same cameras."""
    from PIL import Image

    from cropcraft_core.sfm import import_transforms_json
    from cropcraft_core.surfaces.nerfacto import write_transforms

    src, out = Path(a.scene_dir), Path(a.out)
    poses = import_transforms_json(src / "transforms.json")
    (out / "depth").mkdir(parents=True, exist_ok=True)
    images = []
    for (name, _), cam in zip(poses, poses.cameras, strict=True):
        stem = Path(name).stem
        if not a.plane:
            images.append(np.asarray(Image.open(src / "images" / Path(name).name).convert("RGB")))
            if (src / "depth" / f"{stem}.npy").exists():  # a GPU host gets a few views' only
                shutil.copy(src / "depth" / f"{stem}.npy", out / "depth" / f"{stem}.npy")
            continue
        dirs = cam.ray_directions(normalized=False)  # camera z = 1: t is the z-depth
        o = cam.center
        with np.errstate(divide="ignore", invalid="ignore"):
            z = -o[2] / dirs[..., 2]
        z[~(z > 0)] = np.nan
        p = o + dirs * np.nan_to_num(z)[..., None]
        img = np.rint(np.clip(plane_texture(p[..., 0], p[..., 1]), 0, 1) * 255).astype(np.uint8)
        img[~np.isfinite(z)] = 0
        images.append(img)
        np.save(out / "depth" / f"{stem}.npy", z.astype(np.float32))
    write_transforms(out / "data", images, poses.cameras)
    shutil.copy(src / "transforms.json", out / "transforms.json")
    return {"views": len(images), "out": str(out), "plane": bool(a.plane)}


def uniform_sampler(n: int):
    """A module to stand in for nerfacto's proposal sampler (``--uniform-samples``): ``n``
    samples spread evenly between the near and far planes, so the field alone decides where the
    surface is. The proposal levels nerfacto reports are the same samples with zero weights."""
    import torch
    from nerfstudio.model_components.ray_samplers import UniformSampler

    class Uniform(torch.nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.sampler = UniformSampler(num_samples=n, single_jitter=False)

        def forward(self, bundle, density_fns=None):
            samples = self.sampler(bundle)
            zero = torch.zeros(samples.frustums.starts.shape, device=bundle.origins.device)
            return samples, [zero, zero], [samples, samples]

    return Uniform()


def _setup(data: Path, rays: int, camera_opt: str, sets: list[str], far=None):
    from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig

    from cropcraft_core.surfaces.nerfacto_method import method

    cfg = method.config
    cfg.machine.device_type = "cuda" if _cuda() else "cpu"
    cfg.mixed_precision = False  # this loop has no autocast (fp32; precision did not matter)
    cfg.pipeline.datamanager.data = data
    cfg.pipeline.datamanager.dataparser = NerfstudioDataParserConfig(
        orientation_method="up", eval_mode="all"
    )
    if far is not None:  # (scale, far plane) as NerfactoSurfaces.fit sets them
        cfg.pipeline.datamanager.dataparser.auto_scale_poses = False
        cfg.pipeline.datamanager.dataparser.scale_factor = far[0]
        cfg.pipeline.model.far_plane = far[1]
    cfg.pipeline.datamanager.train_num_rays_per_batch = rays
    cfg.pipeline.model.camera_optimizer.mode = camera_opt
    model = cfg.pipeline.model
    for kv in sets:  # --set name=value on the model config, typed as the field's default
        k, v = kv.split("=", 1)
        if not hasattr(model, k):
            raise SystemExit(f"--set {kv}: nerfacto's model config has no {k!r}")
        cur = getattr(model, k)
        setattr(model, k, v if isinstance(cur, str) else type(cur)(json.loads(v)))
    device = cfg.machine.device_type
    return cfg, cfg.pipeline.setup(device=device, test_mode="val", world_size=1, local_rank=0)


def _cuda() -> bool:
    import torch

    return bool(torch.cuda.is_available())


def density_profile(pipe, bundle, true_t: np.ndarray) -> dict:
    """The field's density on a fixed grid along ``bundle``'s rays (bypassing nerfacto's
    samplers): opacity within :data:`GRID_FAR`, the weight peak's median relative error
    against ``true_t``, the largest density and the median of the rays' largest."""
    import torch
    from nerfstudio.cameras.rays import Frustums, RaySamples

    n, k = len(bundle), GRID_N - 1
    grid = torch.linspace(0.05, GRID_FAR, GRID_N, device=bundle.origins.device)
    st = grid[None, :-1, None].expand(n, -1, 1)
    en = grid[None, 1:, None].expand(n, -1, 1)
    fr = Frustums(
        origins=bundle.origins[:, None].expand(-1, k, -1),
        directions=bundle.directions[:, None].expand(-1, k, -1),
        starts=st, ends=en, pixel_area=bundle.pixel_area[:, None].expand(-1, k, -1),
    )  # fmt: skip
    samples = RaySamples(
        frustums=fr, camera_indices=bundle.camera_indices[:, None].expand(-1, k, -1),
        deltas=en - st,
    )  # fmt: skip
    with torch.no_grad():
        dens, _ = pipe.model.field.get_density(samples)
        w = samples.get_weights(dens)[..., 0].float().cpu().numpy()
    dens = dens[..., 0].float().cpu().numpy()
    mid = ((st + en) / 2)[..., 0].cpu().numpy()
    peak = mid[np.arange(n), w.argmax(1)]
    ok = np.isfinite(true_t)
    return {
        "opacity": float(w.sum(1).mean()),
        "peak_rel_err": float(np.median(np.abs(peak - true_t)[ok] / true_t[ok])),
        "density_max": float(dens.max()),
        "density_ray_max_median": float(np.median(dens.max(1))),
    }


def train(a: argparse.Namespace) -> list:
    from nerfstudio.engine.callbacks import TrainingCallbackAttributes, TrainingCallbackLocation
    from nerfstudio.engine.optimizers import Optimizers

    from cropcraft_core.sfm import import_transforms_json

    root = Path(a.scene_dir)
    data = root / "data"
    if not (data / "transforms.json").exists():
        raise SystemExit(f"{data}: no nerfstudio transforms.json (make one with `prepare`)")
    poses = import_transforms_json(root / "transforms.json")
    stems = [Path(n).stem for n, _ in poses]
    far = None
    if a.far_margin is not None:  # the surfaces config's nerf_far_margin on the crop's box
        from cropcraft_core.surfaces import resolve_bbox
        from cropcraft_core.surfaces.nerfacto import far_plane_setting

        box = resolve_bbox("auto", a.crop)
        far = far_plane_setting(list(poses.cameras), box, a.far_margin)
        print(f"scale {far[0]:.4f}, far plane {far[1]:.3f} (nerfstudio's frame)", flush=True)
    cfg, pipe = _setup(data, a.rays, a.camera_optimizer, a.set, far)
    opt = Optimizers(cfg.optimizers, pipe.get_param_groups())
    attrs = TrainingCallbackAttributes(
        optimizers=opt, grad_scaler=None, pipeline=pipe, trainer=None
    )
    callbacks = pipe.get_training_callbacks(attrs)
    if a.uniform_samples:
        pipe.model.proposal_sampler = uniform_sampler(a.uniform_samples).to(pipe.device)
        callbacks = []  # they anneal and step the proposal sampler
    scale = pipe.datamanager.train_dataparser_outputs.dataparser_scale
    bundle, batch = pipe.datamanager.next_train(0)
    bundle, idx = bundle[:N_RAYS], batch["indices"][:N_RAYS].cpu().numpy()
    true_t = np.empty(len(idx))
    for r, (c, y, x) in enumerate(idx):
        cam = poses.cameras[c]
        known = root / "depth" / f"{stems[c]}.npy"
        z = np.load(known)[y, x] if known.exists() else np.nan  # NaN: not scored
        ray = [(x + 0.5 - cam.cx) / cam.fx, (y + 0.5 - cam.cy) / cam.fy, 1.0]
        true_t[r] = z * np.linalg.norm(ray) * scale  # along the unit ray, nerfstudio's units
    rows, t0 = [], time.perf_counter()
    for step in range(a.steps + 1):
        for cb in callbacks:
            cb.run_callback_at_location(step, TrainingCallbackLocation.BEFORE_TRAIN_ITERATION)
        opt.zero_grad_all()
        _, losses, metrics = pipe.get_train_loss_dict(step=step)
        sum(losses.values()).backward()
        opt.optimizer_step_all()
        opt.scheduler_step_all(step)
        for cb in callbacks:
            cb.run_callback_at_location(step, TrainingCallbackLocation.AFTER_TRAIN_ITERATION)
        late = a.max_seconds is not None and time.perf_counter() - t0 > a.max_seconds
        if step % a.every == 0 or late or step == a.steps:
            row = {"step": step, "seconds": time.perf_counter() - t0}
            row["psnr"] = float(metrics["psnr"])
            row.update(density_profile(pipe, bundle, true_t))
            rows.append(row)
            print(
                f"{step:6d} {row['seconds']:7.0f}s psnr {row['psnr']:5.2f} "
                f"opacity {row['opacity']:.3f} peak err {row['peak_rel_err']:.3f} "
                f"density max {row['density_max']:.3g}",
                flush=True,
            )
            if a.json:
                Path(a.json).write_text(json.dumps(rows, indent=1))
        if late:
            break
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="nerfacto_probe", description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    pl = sub.add_parser("prepare", help="nerfstudio data of a synth scene, or of the plane")
    pl.add_argument("--scene-dir", required=True, help="a cropcraft synth scene")
    pl.add_argument("--out", required=True)
    pl.add_argument("--plane", action="store_true", help="the textured plane, not the photos")
    tr = sub.add_parser("train", help="train nerfacto in this process and watch its density")
    tr.add_argument("--scene-dir", required=True, help="a `prepare` output folder")
    tr.add_argument("--steps", type=int, default=200)
    tr.add_argument("--every", type=int, default=20)
    tr.add_argument("--rays", type=int, default=1024, help="rays per step (nerfacto: 4096)")
    tr.add_argument("--camera-optimizer", default="off", choices=["off", "SO3xR3", "SE3"])
    tr.add_argument("--set", action="append", default=[], metavar="NAME=VALUE")
    tr.add_argument("--uniform-samples", type=int, default=0, help="no proposal sampler")
    tr.add_argument(
        "--far-margin", type=float, default=None,
        help="far plane at this margin times the farthest camera-to-box distance "
        "(surfaces.nerf_far_margin; the box: the crop's scene box, metric poses)",
    )  # fmt: skip
    tr.add_argument("--crop", default="soybean", help="whose scene box --far-margin uses")
    tr.add_argument("--max-seconds", type=float, default=None, help="stop after this long")
    tr.add_argument("--json", default=None, help="also write the rows here (at every report)")
    a = ap.parse_args(argv)
    if a.cmd == "prepare":
        print(json.dumps(prepare(a)))
        return 0
    train(a)
    return 0


if __name__ == "__main__":
    sys.exit(main())
