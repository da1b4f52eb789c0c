"""The paper's NeRF stage (nerfacto) on a synthetic scene, in two halves for two machines.

``train`` (a CUDA host with nerfstudio): fits ``NerfactoSurfaces`` to a ``cropcraft synth``
scene's photos with their true poses, samples its point cloud, fits the rows (metric: the poses
are), makes the row camera's observation, renders a few of the photos' own views and scores them
against the scene's true per-view depth (``depth/*.npy``), and writes what the other half needs
into ``--out``: ``observation.npz``, ``row.json`` (the row camera in the truth frame and its
direction / lateral / height errors, timings, the pace ns-train logged, per-view scores),
``points.npz``, ``ns-train.log``. It needs neither Open3D nor the truth mesh, which a GPU
worker image may lack.

``compare`` (any host with the project installed): the same figures ``bench pipeline --poses
truth`` prints for the CPU backends, from the kept files: the depth histogram's L1 against the
true mesh's from the same camera, mask areas, depth errors, the point cloud's distance to the
true surfaces (``points``) and its share by height against the true surfaces the photos see
(``heights``: these two also where the train half's row fit failed), and with ``--fit
SEEDSxEVALS`` the fit and its traits against the truth (``bench_pipeline.fit_and_compare``).

    cropcraft bench nerfacto train --scene-dir DIR --iterations 5000 --out KEPT
    cropcraft bench nerfacto compare --scene-dir DIR --kept KEPT [--fit 10x300] [--json FILE]
"""

from __future__ import annotations

import argparse
import json
import re
import time
from pathlib import Path

import numpy as np
from PIL import Image

# The train half's imports, at the top so that importing this module checks a GPU host has them
# all (deploy/gpu_check_run.sh does, before anything starts); the compare half's (Open3D, the
# truth mesh) stay inside it.
from benchmarks.options import (
    at_least,
    existing_folder,
    output_file,
    parse_kv,
    seeds_by_evals,
    write_json,
)
from cropcraft_core.errors import CropCraftError
from cropcraft_core.observe import Observation
from cropcraft_core.rowfit import fit_rows_with_scale
from cropcraft_core.rowfit import preset as rowfit_preset
from cropcraft_core.rowfit.truth import camera_in_truth, row_fit_errors
from cropcraft_core.sfm import import_transforms_json
from cropcraft_core.surfaces import CROP_SURFACES, SurfacesConfig, make_backend, resolve_bbox

#: The third-party modules the train half and the GPU acceptance test (``tests/test_surfaces.py
#: -m gpu``) may import on a lent GPU host: what its image holds (CPython 3.12 with torch, numpy,
#: SciPy, OpenCV, numba, Pillow, PyYAML, fsspec, pytest, ...) and the wheels
#: ``deploy/gpu_check_prepare.sh`` carries there (nerfstudio and its needs, pydantic). An import
#: outside it dies on the host after the machine's start (session 82: pydantic, which the store's
#: records need); ``tests/test_cli.py`` checks it here.
GPU_HOST_MODULES = frozenset(
    {
        # the image's
        "PIL", "colorama", "cv2", "cython_runtime", "fsspec", "iniconfig", "llvmlite", "numba",
        "numpy", "pluggy", "py", "pygments", "pytest", "scipy", "torch", "torchgen", "tqdm",
        "typing_extensions", "yaml",
        # carried by gpu_check_prepare.sh
        "annotated_types", "nerfstudio", "pydantic", "pydantic_core", "typing_inspection",
    }
)  # fmt: skip

#: how many of the photos' own views ``train`` renders and scores against their true depth
VIEWS_SCORED = 8
#: a rendered depth within this much of the true one (m) counts as right (the scores' "within")
WITHIN_M = 0.02


def view_scores(depth: np.ndarray, true: np.ndarray) -> dict:
    """A rendered z-depth against the true one of the same view (NaN where nothing): median
    absolute error, median ratio (a scale or a far background shows here), share within
    :data:`WITHIN_M`, and share of the truth's pixels left empty."""
    seen = np.isfinite(true)
    both = seen & np.isfinite(depth) & (true > 0)
    err = np.abs(depth[both] - true[both])
    return {
        "median_abs_err_m": float(np.median(err)) if err.size else float("nan"),
        "median_ratio": float(np.median(depth[both] / true[both])) if err.size else float("nan"),
        "within": float((err < WITHIN_M).mean()) if err.size else 0.0,
        "holes": float((seen & ~np.isfinite(depth)).sum() / max(int(seen.sum()), 1)),
    }


#: ANSI escapes (colours, cursor moves) in a log nerfstudio's rich console wrote
_ANSI = re.compile(r"\x1b\[[0-9;?]*[A-Za-z]")
#: nerfstudio's duration units (``writer.py``'s "2 d, 11 h, 44 m, 33 s, 12.000 ms")
_UNIT_S = {"d": 86400.0, "h": 3600.0, "m": 60.0, "s": 1.0, "ms": 1e-3}
_RATE = {"": 1.0, "K": 1e3, "M": 1e6, "G": 1e9}


def _duration_s(text: str) -> float | None:
    """Seconds of a nerfstudio duration ("1 s, 338.214 ms", "52.000 ms"), None if not one."""
    parts = [p.split() for p in text.split(",")]
    if not all(len(p) == 2 and p[1] in _UNIT_S for p in parts):
        return None
    try:
        return sum(float(v) * _UNIT_S[u] for v, u in parts)
    except ValueError:
        return None


def _rate(text: str) -> float | None:
    """A nerfstudio rate ("42.61 K", "12.47 M") as a number, None if not one."""
    v, _, unit = text.strip().partition(" ")
    try:
        return float(v) * _RATE[unit.strip()]
    except (ValueError, KeyError):
        return None


def train_pace(log: str) -> dict:
    """The training pace ``ns-train``'s console table reports (its "Train Iter (time)" column:
    the mean of its recent steps, printed every few steps; "Train Rays / Sec"), from its log:
    how many rows were read, the last step, and the medians over the rows (the first rows hold
    CUDA's warm-up, the median passes over them). Columns are found by the table's header, so
    a viewer's extra column does not shift them (a cell that fills its 20 characters runs into
    the next, as the warm-up row's ETA does: neither is read). The writer reprints its last
    rows each time (cursor up, in a terminal), so a log holds each row several times: a step
    counts once. {} when the log has no such table."""
    rows, cols = {}, None
    for raw in log.splitlines():
        line = _ANSI.sub("", raw).rstrip()
        if "Train Iter (time)" in line:
            cols = [c.strip() for c in re.split(r"\s{2,}", line.strip())]
            continue
        m = re.match(r"\s*(\d+) \(\s*[\d.]+%\)\s{2,}(.*)$", line)
        if cols is None or m is None:
            continue
        cells = dict(zip(cols[1:], re.split(r"\s{2,}", m.group(2).strip()), strict=False))
        it = _duration_s(cells.get("Train Iter (time)", ""))
        if it is not None:
            rows[int(m.group(1))] = (it, _rate(cells.get("Train Rays / Sec", "")))
    if not rows:
        return {}
    rays = [r for _, r in rows.values() if r is not None]
    return {
        "rows": len(rows),
        "last_step": max(rows),
        "median_iter_ms": 1e3 * float(np.median([t for t, _ in rows.values()])),
        "median_rays_per_s": float(np.median(rays)) if rays else None,
    }


def scored_views(poses) -> list:
    """The (name, camera) pairs of ``poses`` that ``train`` scores: every
    ``len // VIEWS_SCORED``-th, at most :data:`VIEWS_SCORED` of them."""
    return list(poses)[:: max(len(poses) // VIEWS_SCORED, 1)][:VIEWS_SCORED]


def train(a: argparse.Namespace) -> dict:
    root, out = Path(a.scene_dir), Path(a.out)
    settings = parse_kv(a.surfaces)  # a bad KEY=VALUE stops the run before the photos load
    crop = json.loads((root / "scene.json").read_text())["crop"]
    unknown = sorted(set(settings) - set(SurfacesConfig.__dataclass_fields__))
    if unknown:  # a traceback, after an empty --out was made
        raise SystemExit(f"--surfaces {unknown[0]}: not a setting of the surfaces")
    poses = import_transforms_json(root / "transforms.json")
    images = [
        np.asarray(Image.open(root / "images" / Path(n).name).convert("RGB")) for n, _ in poses
    ]
    # nerfacto: the paper's settings per crop; a CPU backend (to check this benchmark without a
    # GPU): the scene flow's settings
    extra = {} if a.backend == "nerfacto" else CROP_SURFACES[crop]
    cfg = SurfacesConfig.for_crop(
        crop,
        **{
            **extra,
            "backend": a.backend,
            "nerf_iterations": a.iterations,
            "nerf_max_seconds": a.max_seconds,
            "nerf_args": a.nerf_arg,
            "nerf_far_margin": a.far_margin,
            "workdir": str(out / "work"),
            **settings,
        },
    )
    backend = make_backend(cfg)  # nerfacto without a GPU is refused before --out is made
    out.mkdir(parents=True, exist_ok=True)
    sec: dict[str, float] = {}
    t = time.perf_counter()
    # the crop's scene box, as the scene flow gives (the poses are the truth's, metric)
    box = resolve_bbox("auto", crop)
    backend.fit(images, poses.cameras, box)
    sec["train"] = time.perf_counter() - t
    log = out / "work" / "ns-train.log"
    pace = {}
    if log.exists():
        text = log.read_text(errors="replace")
        (out / "ns-train.log").write_text(text[-200_000:])
        pace = train_pace(text)

    def keep() -> dict:  # row.json as it stands: each stage adds to it
        (out / "row.json").write_text(json.dumps(rec, indent=1, default=float))
        return rec

    rec = {
        "scene_dir": str(root),
        "crop": crop,
        "backend": a.backend,
        "iterations": a.iterations,
        "nerf_args": list(a.nerf_arg),
        "surfaces": settings,
        "planes": {"near": cfg.near_plane, "far": cfg.far_plane},  # set ones, nerfstudio's frame
        "seconds": sec,
        "surfaces_timings": backend.timings,
        "pace": pace,
    }

    # the photos' own views first: they judge the radiance field even where no rows are found
    t = time.perf_counter()
    scored = {}
    for name, cam in scored_views(poses):
        true = root / "depth" / f"{Path(name).stem}.npy"
        if true.exists():  # a GPU host may be sent only these views' depth
            scored[true.stem] = view_scores(backend.render(cam)[0], np.load(true))
    sec["views_scored"] = time.perf_counter() - t
    rec["views"] = scored
    if scored:
        first = next(iter(scored.values()))
        rec["views_mean"] = {k: float(np.mean([v[k] for v in scored.values()])) for k in first}
    keep()

    t = time.perf_counter()
    points, colors = backend.point_cloud(100_000)
    sec["point_cloud"] = time.perf_counter() - t
    np.savez_compressed(out / "points.npz", points=points, colors=colors)

    t = time.perf_counter()
    from benchmarks.bench_pipeline import scene_layout

    layout = scene_layout(root, crop)  # the scene's own rows, not the crop's default
    pre = rowfit_preset(crop, row_spacing=layout.row_spacing, box_center=None, box_size=None)
    try:
        fit = fit_rows_with_scale(
            points, colors, crop, pre, rng=0, metric_scale=1.0,
            known_row_spacing=layout.row_spacing,
        )  # fmt: skip
    except CropCraftError as e:  # a wrong radiance field: its views' scores above say how
        fit, rec["error"] = None, f"row fit: {e}"
    sec["rowfit"] = time.perf_counter() - t
    if fit is None:
        return keep()
    t = time.perf_counter()
    # as the scene flow's observe stage (bench_pipeline._observe, whose module needs Open3D)
    obs = Observation.from_surfaces(
        crop, backend.render, fit.camera, fit.camera_in_scene(), fit.scale, fit.render_height
    )
    sec["observe"] = time.perf_counter() - t
    obs.save(out / "observation.npz")
    rec["camera_truth"] = camera_in_truth(fit, np.eye(4)).to_dict()
    rec["row_errors"] = row_fit_errors(fit, np.eye(4), layout).to_dict()  # targets 2°/3 cm/3 %
    rec["row_fit"] = fit.to_dict()
    return keep()


def compare(a: argparse.Namespace) -> dict:
    from benchmarks.bench_pipeline import depth_errors, fit_and_compare, observation_vs_truth
    from benchmarks.bench_surfaces import _truth_mesh
    from cropcraft_core.geometry.camera import PinholeCamera
    from cropcraft_core.surfaces.base import in_bbox

    root, kept = Path(a.scene_dir), Path(a.kept)
    rec = json.loads((kept / "row.json").read_text())
    keys = ("scene_dir", "crop", "backend", "iterations", "seconds", "surfaces_timings")
    keys += ("views_mean", "surfaces", "planes")
    out = {k: rec[k] for k in keys if k in rec}
    out["pace"] = rec.get("pace", {})  # train halves from before session 38 lack it
    truth_mesh = _truth_mesh(root)
    # the point cloud first: it is there even where the row fit failed
    if (kept / "points.npz").exists():
        with np.load(kept / "points.npz") as z:
            out["points"] = points_vs_truth(z["points"], truth_mesh)
            box = resolve_bbox("auto", rec["crop"])
            seen = visible_truth_points(root)
            out["heights"] = height_profile(z["points"], seen[in_bbox(seen, box)])
    if "camera_truth" not in rec:  # no observation: what the train half found, and stop
        out["error"] = rec.get("error") or f"{kept / 'row.json'}: no observation"
        return out
    obs = Observation.load(kept / "observation.npz")
    truth = make_backend(SurfacesConfig(backend="truth"), mesh=truth_mesh)
    d_true, _ = truth.render(PinholeCamera.from_dict(rec["camera_truth"]))
    d_true = np.where(np.isfinite(d_true), d_true, np.nan)
    h_obs, h_true, area = observation_vs_truth(obs, d_true)
    if "row_errors" in rec:  # train halves from before it was recorded lack it
        out["row_errors"] = rec["row_errors"]
    out["hist_l1"] = float(np.abs(h_obs - h_true).sum())
    out["mask_area"] = area
    out["holes"] = float((~np.isfinite(obs.depth) & np.isfinite(d_true)).mean())
    out.update(depth_errors(obs, d_true))
    if a.fit:
        out["fit"] = fit_and_compare(obs, root, a.fit, d_true)
    return out


def points_vs_truth(points: np.ndarray, mesh) -> dict:
    """The point cloud (n, 3) m (truth frame) against the true scene: each point's distance to
    the nearest true surface, the canopy ``mesh`` or the soil (z = 0): the share within
    :data:`WITHIN_M` and the median."""
    import open3d as o3d

    from cropcraft_core.render.raycast import build_scene

    if not len(points):
        return {"n": 0, "within": 0.0, "median_dist_m": float("nan")}
    p = np.asarray(points, np.float64)
    dist = build_scene(mesh.vertices, mesh.faces).compute_distance(
        o3d.core.Tensor(p.astype(np.float32))
    )
    d = np.minimum(dist.numpy().astype(np.float64), np.abs(p[:, 2]))
    return {
        "n": len(p),
        "within": float((d < WITHIN_M).mean()),
        "median_dist_m": float(np.median(d)),
    }


def visible_truth_points(root: Path, step: int = 4) -> np.ndarray:
    """The true surfaces the photos see: each view's true z-depth (``depth/*.npy``, as ``cropcraft
    synth`` writes it) unprojected through its true camera (``transforms.json``), every
    ``step``-th pixel each way; (n, 3) m in the truth frame. Views without a depth file are
    skipped (a GPU host is sent only the scored views')."""
    pts = []
    for name, cam in import_transforms_json(root / "transforms.json"):
        f = root / "depth" / f"{Path(name).stem}.npy"
        if not f.exists():
            continue
        xyz = cam.unproject(np.load(f))[::step, ::step].reshape(-1, 3)
        pts.append(xyz[np.isfinite(xyz).all(axis=1)])
    return np.concatenate(pts) if pts else np.zeros((0, 3))


#: ``height_profile``: a point this close to the soil (|z|, m) is the soil's
SOIL_M = 0.03


def height_profile(points: np.ndarray, truth: np.ndarray, band_m: float = 0.1) -> dict:
    """How a point cloud's points share out by height against the true surfaces the photos see
    (:func:`visible_truth_points`), both in the truth frame (soil at z = 0): the soil
    (|z| < :data:`SOIL_M`), then bands of ``band_m`` from :data:`SOIL_M` (the first band is
    shorter) up to the highest true point, and a last one for anything above it (or under the
    soil). A reconstruction that loses the low leaves and the soil seen through the canopy's
    gaps shows it here, where the median distance to a true surface does not."""
    p, t = np.asarray(points, np.float64)[:, 2], np.asarray(truth, np.float64)[:, 2]
    top = float(t.max()) if len(t) else 0.0
    edges = np.arange(band_m, top + band_m, band_m)
    edges = np.concatenate([[-SOIL_M, SOIL_M], edges[edges > SOIL_M]])
    labels = ["soil"] + [
        f"{lo:.2f}-{hi:.2f}" for lo, hi in zip(edges[1:-1], edges[2:], strict=True)
    ]

    def shares(z: np.ndarray) -> list[float]:
        n = np.histogram(z, edges)[0].astype(np.float64)
        other = len(z) - n.sum()  # under the soil, or above the highest true point
        return [float(v) for v in np.append(n, other) / max(len(z), 1)]

    return {"bands": labels + ["other"], "truth": shares(t), "cloud": shares(p)}


def print_compare(out: dict) -> None:
    """``compare``'s figures, then the table against #4's targets (``bench_pipeline``'s)."""
    from benchmarks.bench_pipeline import print_checks, print_rules

    t = out.get("surfaces_timings", {})
    head = f"{out['backend']} surfaces of {out['scene_dir']}"
    if out["backend"] == "nerfacto":
        far = t.get("nerf_far_plane")  # from the scene box (nerf_far_margin)
        far_set = (out.get("planes") or {}).get("far")  # given (maize's paper setting)
        head += f": {t.get('nerf_iterations_done', '?')} iterations, far plane " + (
            f"{far:.3f} (nerfstudio's frame, from the scene box)"
            if far is not None
            else f"{far_set:g} (nerfstudio's frame, set)"
            if far_set is not None
            else "nerfstudio's (1000)"
        )
        if out.get("surfaces"):
            head += f"; settings {out['surfaces']}"
    print(head)
    pace = out.get("pace") or {}
    if pace:
        # what the steps' own pace leaves of the training wall time: start-up, checkpoints
        steps_s = pace["last_step"] * pace["median_iter_ms"] / 1e3
        rays = pace.get("median_rays_per_s")
        print(
            f"  training pace: {pace['median_iter_ms']:.1f} ms per iteration"
            + (f" ({rays / 1e3:.1f} K rays/s)" if rays else "")
            + f", median of {pace['rows']} logged rows to step {pace['last_step']}"
            + (
                f"; {t['nerf_train'] - steps_s:.0f} s of the {t['nerf_train']:.0f} s "
                "training outside the steps"
                if "nerf_train" in t
                else ""
            )
        )
    v, pts = out.get("views_mean"), out.get("points", {})
    if v:  # none when the scene had no true depth maps to score the views against
        print(
            f"  the photos' own views: median depth ratio {v['median_ratio']:.3f}, error "
            f"{100 * v['median_abs_err_m']:.1f} cm, {100 * v['within']:.0f} % within "
            f"{100 * WITHIN_M:.0f} cm, {100 * v['holes']:.1f} % empty"
        )
    else:
        print("  the photos' own views: not scored (the scene has no true depth maps)")
    if pts:
        print(
            f"  point cloud: {100 * pts['within']:.1f} % of {pts['n']} points within "
            f"{100 * WITHIN_M:.0f} cm of a true surface "
            f"(median {1000 * pts['median_dist_m']:.1f} mm)"
        )
    hts = out.get("heights")
    if hts:
        print("  heights (m): share of the point cloud / of the true surfaces the photos see")
        for band, c, t in zip(hts["bands"], hts["cloud"], hts["truth"], strict=True):
            if c or t:
                print(f"    {band:>10}  {100 * c:5.1f} %  / {100 * t:5.1f} %")
    if "error" in out:  # the train half made no observation
        print(f"  no observation: {out['error']}")
        return
    m = out["mask_area"]
    print(f"  mask area {m['observation']:.3f} (truth {m['truth']:.3f}), holes {out['holes']:.3f}")
    print_checks(out.get("row_errors"), out["hist_l1"], out.get("fit"))
    if out.get("fit"):
        f = out["fit"]
        traits = ", ".join(
            f"{k} {row['estimated']:.3g} (true {row['true']:.3g})" for k, row in f["traits"].items()
        )
        print(f"  fit {f['budget']} in {f['seconds']:.0f} s: {traits}; miss: {f['loss']['whose']}")
        print_rules(f)


def _margin(text: str) -> float | None:
    """``--far-margin``: a number, or 'off' for nerfstudio's own far plane."""
    if text.lower() in ("off", "none", "null"):
        return None
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"a number or 'off', not {text!r}") from None


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="cropcraft bench nerfacto", description=__doc__.splitlines()[0]
    )
    sub = ap.add_subparsers(dest="half", required=True)
    tr = sub.add_parser("train", help="the CUDA half: nerfacto → rows → observation")
    tr.add_argument(
        "--scene-dir",
        required=True,
        type=existing_folder("scene.json", "transforms.json"),
        help="a cropcraft synth scene",
    )
    tr.add_argument("--iterations", type=at_least(1), default=20_000, help="the paper's 20K")
    tr.add_argument(
        "--max-seconds", type=float, default=None, help="training deadline (nerf_max_seconds)"
    )
    tr.add_argument(
        "--nerf-arg",
        action="append",
        default=[],
        help="an ns-train option or value (nerf_args), e.g. "
        "--nerf-arg=--pipeline.model.camera-optimizer.mode --nerf-arg=off",
    )
    tr.add_argument(
        "--far-margin", type=_margin, default=SurfacesConfig.nerf_far_margin,
        help="surfaces.nerf_far_margin: far plane at this margin times the farthest "
        "camera-to-scene-box distance (default %(default)s); 'off': nerfstudio's far plane",
    )  # fmt: skip
    tr.add_argument(
        "--surfaces", action="append", default=[], metavar="KEY=VALUE",
        help="a SurfacesConfig setting over the crop's paper settings (value JSON, else text), "
        "e.g. far_plane=null for the far plane at --far-margin instead of maize's 6.0",
    )  # fmt: skip
    tr.add_argument("--out", required=True, help="folder for the compare half's files")
    tr.add_argument(
        "--backend",
        default="nerfacto",
        help="surfaces backend (default nerfacto; a CPU one checks this benchmark without a GPU)",
    )
    co = sub.add_parser("compare", help="the CPU half: against the truth, optionally fit")
    co.add_argument("--scene-dir", required=True, type=existing_folder("scene.json"))
    co.add_argument(
        "--kept", required=True, type=existing_folder("row.json"), help="the train half's --out"
    )
    co.add_argument(
        "--fit", type=seeds_by_evals, default=None, metavar="SEEDSxEVALS", help="also fit"
    )
    co.add_argument("--json", type=output_file, default=None)
    a = ap.parse_args(argv)
    out = train(a) if a.half == "train" else compare(a)
    if a.half == "train":  # the device's log: every figure, the CPU half reads row.json
        print(json.dumps({k: v for k, v in out.items() if k != "row_fit"}, indent=1, default=float))
    else:
        print_compare(out)
    if getattr(a, "json", None):
        write_json(a.json, out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
