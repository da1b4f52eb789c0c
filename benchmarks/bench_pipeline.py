"""Photos → observation, measured against the truth of a ``cropcraft synth`` scene.

    cropcraft bench pipeline [--crop soybean|maize] [--trajectory walk|drone] [--views 50]
                             [--resolution 640x480] [--scene-dir DIR] [--poses sfm|truth]
                             [--sfm K=V ...] [--surfaces K=V ...] [--fit SEEDSxEVALS]
                             [--fit-true-mesh] [--image-scale S] [--json FILE] [--keep DIR]

The same core calls, in the same order, as the scene flow's stages (ingest → poses → surfaces →
rowfit → observe), without Prefect, each timed; scene synthesis is timed apart (not pipeline).
A new scene is a ``cropcraft synth`` scene of the crop (soybean walked around, maize seen from
a drone, by default); a reused ``--scene-dir`` keeps its own crop. Poses come from structure
from motion (``--poses sfm``, the default: the issue's setting), levelled by ``level_poses``
(provisional scale from the crop's capture height: 1.4 m soybean, 13 m maize) with the metric
scale then measured from the fitted rows against the known row spacing; ``--poses
truth`` imports the scene's metric ``transforms.json`` instead (a phone's AR poses). The
surfaces are fitted inside the crop's scene box (``--bbox auto``), as in the scene flow.

Against the truth (the SfM frame is tied to the true one by a similarity fitted to the camera
centres, used only for scoring):

* row fit: best-row direction error (target ≤ 2°), the row camera's lateral offset from the
  nearest true row (≤ 3 cm), its relative height error above the true ground (≤ 3 %); with SfM
  poses these are also given against the reconstructed surfaces (``register_to_truth``: the
  model's points near the row camera moved onto the true mesh and ground by ICP from the
  camera-centre similarity), whose difference from the camera-centre figures is how far the
  model's points sit off its cameras -- an SfM error that no row fit can see, since it places
  the camera among the reconstructed plants; the depth-histogram L1 is given in both frames;
* observation: L1 distance (target ≤ 0.15) between the observation's depth histogram (the one the
  loss uses: the crop's bins up to the fitted render height, the observation's mask) and the
  histogram the same statistics give for the true mesh rendered from the same row camera placed
  in the truth frame (no background, the observation's height/lateral clauses), both normalised
  to sum 1; the two mask areas are reported beside it, and as a yardstick the L1 the true
  depth scores against itself moved by 0.5 % of the render height (a sixth of the height
  target);
* coverage (CPU surfaces): the share of the row camera's view with no reconstructed surface
  where the true mesh has one, and where those holes were lost (``hole_breakdown``: seen by
  fewer than two photos, no stereo match, dropped by the consistency filter, lost in fusion);
* with ``--fit``: LAI, leaf angle, nodes and internode of the fitted canopy against the truth's
  (LAI target: within 15 %), and whose miss a wrong answer is (``loss_attribution``): the loss
  of the answer and of the true parameters, and of their basins' floors, on the same fresh
  canopies, against the observation and against the true mesh from the same camera;
* with ``--fit-true-mesh`` as well: the true mesh seen from the same row camera
  (:func:`true_mesh_observation`: a perfect reconstruction) fitted at the same budget and
  seeds. Its LAI error is the method's own from this view (the statistics of one row of one
  random draw of the canopy); the rest of the pipeline's is the reconstruction's. Its
  answer's and the truth's basins are compared on the true mesh alone
  (``loss_attribution(..., observation_side=False)``): the truth's deeper is the optimiser's
  miss, otherwise the view's (this draw of the canopy looks like the answer).
* speed: images → observation ≤ 8 minutes on the 2-core machine (50 images at 640 × 480).
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.bench_surfaces import _truth_mesh, add_scene_arguments
from benchmarks.options import output_file, parse_kv, positive, seeds_by_evals, write_json
from cropcraft_core.fit.select import reevaluation_seeds

TARGETS = {
    "direction_deg": 2.0,
    "lateral_m": 0.03,
    "height_rel": 0.03,
    "hist_l1": 0.15,
    "images_to_observation_s": 480.0,
    "lai_rel_err": 0.15,
}


#: A new scene's capture per crop: a person walks around soybean; maize is too tall, a drone flies.
DEFAULT_TRAJECTORY = {"soybean": "walk", "maize": "drone"}


def scene_crop(root: Path, asked: str | None) -> str:
    """The crop of the scene at ``root``: its ``scene.json``'s where the scene exists (a
    different ``asked`` crop is an error), else ``asked`` (default soybean)."""
    f = root / "scene.json"
    if f.is_file():
        crop = json.loads(f.read_text())["crop"]
        if asked and asked != crop:
            raise SystemExit(f"{f}: the scene is {crop}, not {asked} (use another --scene-dir)")
        return crop
    return asked or "soybean"


def check_settings(ap: argparse.ArgumentParser, a: argparse.Namespace) -> None:
    """The settings the run reads after the scene, ingest and SfM, checked before any of them:
    ``--sfm`` and ``--surfaces`` keys, ``--bbox``, ``--prediction-blur``, and a reused scene's
    true traits where ``--fit`` scores against them."""
    import inspect

    from cropcraft_core.errors import CropCraftError
    from cropcraft_core.observe import check_prediction_blur
    from cropcraft_core.sfm import run_sfm
    from cropcraft_core.surfaces import CROP_SURFACES, SurfacesConfig, resolve_bbox

    root = Path(a.scene_dir) if a.scene_dir else None
    crop = scene_crop(root, a.crop) if root else a.crop or "soybean"
    sfm_keys = set(inspect.signature(run_sfm).parameters) - {"image_dir", "work_dir"}
    try:
        sfm = parse_kv(a.sfm)
        unknown = sorted(set(sfm) - sfm_keys)
        if unknown:
            raise ValueError(f"--sfm {unknown[0]}: not a setting of run_sfm")
        SurfacesConfig(**{**CROP_SURFACES[crop], **parse_kv(a.surfaces)})
        resolve_bbox(a.bbox, crop)
        check_prediction_blur(a.prediction_blur)
    except (CropCraftError, TypeError, ValueError) as e:
        ap.error(str(e))
    if a.fit and root is not None and (root / "scene.json").is_file():
        truth_metrics(root)


def scene_layout(root: Path, crop: str):
    """The planting layout the scene at ``root`` was made with (its ``scene.json``'s: ``cropcraft
    synth --row-spacing/--density/--plot``), else ``crop``'s default: the row fit's known
    spacing, the row errors' true rows and the fitted canopy are all of it."""
    from cropcraft_core.config import default_layout
    from cropcraft_core.config.layout import CanopyLayout

    f = root / "scene.json"
    given = json.loads(f.read_text()).get("layout") if f.is_file() else None
    return CanopyLayout(**given) if given else default_layout(crop)


#: Depth shift (fraction of the render height) whose L1 the bench prints as the metric's scale.
SHIFT_REL = 0.005


def observation_vs_truth(obs, d_true: np.ndarray) -> tuple[np.ndarray, np.ndarray, dict]:
    """The observation's depth histogram and the one the same statistics give for the true
    canopy mesh's depth ``d_true`` (NaN where no leaf) from the same camera, both normalised to
    sum 1 (shape; the mask areas are returned beside them). The truth gets what a perfect
    reconstruction would (:func:`truth_stats`)."""
    st_true = truth_stats(obs, d_true)

    def unit(h: np.ndarray) -> np.ndarray:
        return h / max(float(h.sum()), 1e-12)

    area = {"observation": obs.stats.mask_area, "truth": st_true.mask_area}
    return unit(obs.stats.depth), unit(st_true.depth), area


#: Blur widths (metres at the observed canopy's median depth) :func:`blur_match` tries.
BLUR_MATCH_SIGMAS_M = (0.0, 0.0015, 0.003, 0.0045, 0.006, 0.009, 0.012)


def blur_match(obs, d_true: np.ndarray, sigmas_m=BLUR_MATCH_SIGMAS_M) -> dict:
    """Whether a blur of the predictions can stand in for this reconstruction's errors: the
    loss between the observation's statistics and the true mesh's (``d_true``,
    :func:`truth_mask`) with the true depth blurred by each width of ``sigmas_m``
    (``blur_depth``, as ``prediction_blur_m`` blurs the predictions), and the width that brings
    them closest (``best_m``; 0: the truth unblurred is closest). Measured against the same
    draw of the canopy: against other draws (the procedural model's, even at the true
    parameters) a blur lowers the loss on sharp reconstructions too, by smoothing
    draw-to-draw differences. On six soybean canopies only the 1.1 m one's best is not 0
    (6 mm), mostly through the derivative term: its reconstruction lost the deep leaves seen
    through gaps and with them the steepest steps, which the blur removes alike
    (RESULTS *#blur-match*)."""
    import dataclasses

    from cropcraft_core.observe import with_overrides

    mask = truth_mask(obs, d_true)
    # the true depth scored as a prediction blurred by s (Observation.loss_of, with its mask)
    losses = [
        dataclasses.replace(obs, preset=with_overrides(obs.preset, prediction_blur_m=s))
        .loss_of(d_true, mask)
        .total
        for s in sigmas_m
    ]
    return {
        "sigmas_m": list(sigmas_m),
        "losses": [round(float(v), 6) for v in losses],
        "best_m": float(sigmas_m[int(np.argmin(losses))]),
    }


def blur_match_line(match: dict) -> str:
    """:func:`blur_match` on one line."""
    widths = "/".join(f"{1e3 * s:g}" for s in match["sigmas_m"])
    losses = " ".join(f"{v:.4f}" for v in match["losses"])
    return (
        f"  blur match: loss against the true mesh blurred by {widths} mm: {losses} "
        f"(closest at {1e3 * match['best_m']:g} mm)"
    )


def depth_errors(obs, d_true: np.ndarray) -> dict:
    """The observation's depth against the true mesh's ``d_true`` from the same camera:
    ``median_abs_depth_err_m`` where both have a surface, and ``plant_depth_err_m`` (median,
    p25, p75 of observation − truth: + = reconstructed too deep, i.e. low) where both see
    plants (absent if nowhere)."""
    both = np.isfinite(obs.depth) & np.isfinite(d_true)
    out = {"median_abs_depth_err_m": float(np.median(np.abs(obs.depth[both] - d_true[both])))}
    plant = both & obs.mask
    if plant.any():
        err = obs.depth[plant] - d_true[plant]
        out["plant_depth_err_m"] = {
            "median": float(np.median(err)),
            "p25": float(np.percentile(err, 25)),
            "p75": float(np.percentile(err, 75)),
        }
    return out


def truth_mask(obs, d_true: np.ndarray) -> np.ndarray:
    """The foreground a perfect reconstruction would give from the observation's camera: the
    true mesh's depth ``d_true`` (NaN where no leaf) where finite, no background, cut by the
    observation's own height and lateral clauses where its mask has them (``box_mask``)."""
    from cropcraft_core.observe.observation import predicted_mask

    box = (obs.camera, obs.preset) if obs.box_mask else (None, None)
    return predicted_mask(d_true, *box)


def cover_errors(obs, d_true: np.ndarray) -> dict:
    """Where the observation's foreground and a perfect reconstruction's (:func:`truth_mask`)
    differ, as shares of the truth's: ``missed`` (a true leaf pixel outside the observation's
    mask), of which ``missed_deeper`` (the observation has a surface there, farther than the
    leaf: the soil or a lower leaf seen where the leaf was lost) and ``missed_empty`` (no
    surface: the holes' side; the rest hold a nearer surface the mask left out), and
    ``extra`` (observation foreground where the truth has none). A lost leaf over the soil is
    no hole, so the holes figure cannot see it (``benchmarks/RESULTS.md``, *#sparse-77*)."""
    tm = truth_mask(obs, d_true)
    n = max(int(tm.sum()), 1)
    missed = tm & ~obs.mask
    return {
        "truth": float(tm.mean()),
        "observation": float(obs.mask.mean()),
        "missed": float(missed.sum() / n),
        "missed_deeper": float((missed & (obs.depth > d_true)).sum() / n),  # NaN: not deeper
        "missed_empty": float((missed & np.isnan(obs.depth)).sum() / n),
        "extra": float((obs.mask & ~tm).sum() / n),
    }


def cover_line(c: dict) -> str:
    """:func:`cover_errors` as the bench prints it."""
    return (
        f"  row-view cover: the observation's mask {c['observation']:.3f} against the truth's "
        f"{c['truth']:.3f}; {100 * c['missed']:.1f} % of the true leaf pixels not in it "
        f"({100 * c['missed_deeper']:.1f} % show a surface behind the leaf, "
        f"{100 * c['missed_empty']:.1f} % none), extra {100 * c['extra']:.1f} %"
    )


def truth_stats(obs, d_true: np.ndarray):
    """Statistics of the true canopy mesh's depth ``d_true`` from the observation's camera,
    as a perfect reconstruction would give them (:func:`truth_mask`; not blurred as the
    observation's predictions may be)."""
    from cropcraft_core.observe import compute_stats

    return compute_stats(d_true, obs.camera, truth_mask(obs, d_true), obs.preset)


def true_mesh_observation(obs, d_true: np.ndarray):
    """The observation a perfect reconstruction would give: the true mesh's depth ``d_true``
    (NaN where nothing) as ``obs``'s camera sees it, with ``obs``'s preset (its depth bins
    included; its predictions not blurred, as nothing softened the true mesh) and
    :func:`truth_mask`; its statistics are :func:`truth_stats`'s."""
    from cropcraft_core.observe import Observation, with_overrides

    return Observation(
        obs.crop,
        obs.camera,
        d_true,
        truth_mask(obs, d_true),
        preset=with_overrides(obs.preset, prediction_blur_m=0.0),
        meta={**obs.meta, "source": "the true mesh from the observation's camera"},
        box_mask=obs.box_mask,
    )


def _scene_from_true(poses, truth_poses) -> np.ndarray:
    """(4, 4) similarity truth → SfM frame from the registered cameras' centres."""
    from cropcraft_core.sfm import umeyama

    true = {Path(n).stem: c.center for n, c in truth_poses}
    names = [n for n, _ in poses if Path(n).stem in true]
    src = np.array([true[Path(n).stem] for n in names])
    dst = np.array([poses.camera(n).center for n in names])
    s, r, t = umeyama(src, dst)
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = s * r, t
    return m


def run(a: argparse.Namespace) -> dict:

    from cropcraft_core.rowfit import fit_rows_with_scale
    from cropcraft_core.rowfit import preset as rowfit_preset
    from cropcraft_core.rowfit.truth import row_fit_errors
    from cropcraft_core.sfm import (
        Poses,
        import_transforms_json,
        ingest_images,
        level_poses,
        pinhole_photos,
        run_sfm,
    )
    from cropcraft_core.sfm.frame import PRIOR_CAMERA_HEIGHT_M
    from cropcraft_core.surfaces import CROP_SURFACES, SurfacesConfig, make_backend, resolve_bbox
    from cropcraft_core.surfaces.consistency import photo_consistency
    from cropcraft_core.synth import make_scene

    w, h = a.resolution
    root = Path(a.scene_dir) if a.scene_dir else Path(tempfile.mkdtemp(prefix="bench_pipe_"))
    out: dict = {"views": a.views, "resolution": [w, h], "poses": a.poses, "seconds": {}}
    sec = out["seconds"]
    crop = scene_crop(root, a.crop)
    if not (root / "scene.json").exists():
        t = time.perf_counter()
        trajectory = a.trajectory or DEFAULT_TRAJECTORY[crop]
        make_scene(crop, root, views=a.views, resolution=(w, h), seed=a.seed, trajectory=trajectory)
        out["synthesis_s (not pipeline)"] = time.perf_counter() - t
    made = json.loads((root / "scene.json").read_text())  # a reused scene's own, not the flags
    out["views"], out["resolution"] = len(made["images"]), list(made["resolution"])
    out["scene_dir"] = str(root)
    out["crop"] = crop
    layout = scene_layout(root, crop)
    truth_poses = import_transforms_json(root / "transforms.json")

    with tempfile.TemporaryDirectory(prefix="bench_pipe_work_") as tmp:
        work = Path(tmp)
        t = time.perf_counter()
        manifest = ingest_images(root / "images", work / "images")
        sec["ingest"] = time.perf_counter() - t

        t = time.perf_counter()
        if a.poses == "sfm":
            sfm_dir = Path(a.sfm_dir) if a.sfm_dir else work / "sfm"
            if (sfm_dir / "model" / "images.txt").is_file():  # an earlier run's, for iterating
                import pycolmap

                from cropcraft_core.sfm import import_colmap

                found = import_colmap(sfm_dir / "model")
                rec = pycolmap.Reconstruction(str(sfm_dir / "model"))
                sparse = np.array([p.xyz for p in rec.points3D.values()])
                out["sfm"] = {"reused": str(sfm_dir / "model"), "n_registered": len(found)}
            else:
                sfm = run_sfm(work / "images", sfm_dir, **parse_kv(a.sfm))
                found, sparse = sfm.poses, sfm.points
                out["sfm"] = {k: v for k, v in sfm.summary().items() if k != "model_dir"}
            poses, _, frame = level_poses(
                found, sparse, prior_camera_height_m=PRIOR_CAMERA_HEIGHT_M[crop]
            )
            out["frame"] = frame.summary()
        else:
            poses = truth_poses
        sec["poses"] = time.perf_counter() - t
        by_stem = {Path(im.name).stem: im.name for im in manifest.images}

        t = time.perf_counter()
        ingested = Poses(  # the photos as the flow reads them: undistorted where SfM found a lens
            tuple((by_stem[Path(n).stem], c) for n, c in poses),
            {by_stem[Path(n).stem]: d for n, d in poses.distortion.items()},
        )
        images = pinhole_photos(work / "images", ingested)
        backend = make_backend(SurfacesConfig(**{**CROP_SURFACES[crop], **parse_kv(a.surfaces)}))
        backend.fit(images, poses.cameras, resolve_bbox(a.bbox, crop))
        points, colors = backend.point_cloud(100_000)
        sec["surfaces"] = time.perf_counter() - t
        out["surfaces_breakdown"] = {
            k: round(float(v), 2) for k, v in backend.timings.items() if isinstance(v, float)
        }

        t = time.perf_counter()
        metric = a.poses == "truth"
        pre = rowfit_preset(crop, row_spacing=layout.row_spacing, box_center=None, box_size=None)
        fit = fit_rows_with_scale(
            points,
            colors,
            crop,
            pre,
            rng=0,
            metric_scale=1.0 if metric else None,
            known_row_spacing=layout.row_spacing,
        )
        sec["rowfit"] = time.perf_counter() - t
        if a.keep:
            keep = Path(a.keep)
            keep.mkdir(parents=True, exist_ok=True)
            np.savez_compressed(keep / "points.npz", points=points, colors=colors)
            (keep / "rowfit.json").write_text(json.dumps(fit.to_dict(), indent=1, default=float))
            backend.save(keep / "surfaces")

        t = time.perf_counter()
        obs = _observe(crop, fit, backend, a.image_scale, a.prediction_blur)
        sec["observe"] = time.perf_counter() - t
    sec["images_to_observation"] = sum(
        sec[k] for k in ("ingest", "poses", "surfaces", "rowfit", "observe")
    )

    scene_from_true = np.eye(4) if metric else _scene_from_true(poses, truth_poses)
    true_scale = 1.0 / float(np.cbrt(np.linalg.det(scene_from_true[:3, :3])))
    out["scale"] = {
        "fitted": fit.scale,
        "source": fit.scale_source,
        "true": true_scale,
        "rel_err": fit.scale / true_scale - 1.0,
    }
    out["rowfit"] = row_fit_errors(fit, scene_from_true, layout).to_dict()
    true_mesh = _truth_mesh(root)
    truth = make_backend(SurfacesConfig(backend="truth"), mesh=true_mesh)
    d_true = _truth_depth(truth, fit, scene_from_true, a.image_scale)
    depth_m = obs.depth
    h_obs, h_true, area = observation_vs_truth(obs, d_true)
    out["hist_l1"] = float(np.abs(h_obs - h_true).sum())
    if not metric:
        by_surfaces, registration = _content_frame(points, fit, scene_from_true, true_mesh, crop)
        out["registration"] = registration.to_dict()
        out["rowfit_content"] = row_fit_errors(fit, by_surfaces, layout).to_dict()
        _, h_c, _ = observation_vs_truth(obs, _truth_depth(truth, fit, by_surfaces, a.image_scale))
        out["hist_l1_content"] = float(np.abs(h_obs - h_c).sum())
    # the metric's own tightness: the true depth against itself moved down by a sliver of the
    # render height (a sixth of the height target) -- what a perfect reconstruction seen from a
    # camera that far off would score
    _, h_moved, _ = observation_vs_truth(obs, d_true + SHIFT_REL * obs.preset.render_height)
    out["hist_l1_shift"] = {"rel": SHIFT_REL, "l1": float(np.abs(h_moved - h_true).sum())}
    out["hist_observation"] = h_obs.round(4).tolist()
    out["hist_truth"] = h_true.round(4).tolist()
    out["depth_bins"] = list(obs.preset.depth_range)
    out["mask_area"] = area
    out["cover"] = cover_errors(obs, d_true)
    # the surfaces against the photos at the photos' cameras (the flow's consistency stage),
    # beside the truth's figures: how far its net cover follows the reconstruction's miss
    t = time.perf_counter()
    cons = photo_consistency(
        backend.render,
        images,
        poses.cameras,
        fit.ground_normal,
        fit.ground_offset,
        scale=fit.scale,
        bbox=backend.bbox,
        plant_a_below=fit.preset.plant_a_below,
    ).to_dict()
    out["consistency"] = {
        **{k: cons[k] for k in ("photo_plant", "holes", "unreconstructed", "extra", "net")},
        "views": len(cons["views"]),
        "seconds": time.perf_counter() - t,
    }
    if getattr(backend, "raw_depth_maps", None):
        out["holes"] = _holes(
            root, poses, truth_poses, backend, fit, scene_from_true, a.image_scale, d_true, obs
        )
    out.update(depth_errors(obs, d_true))
    out["blur_match"] = blur_match(obs, d_true)
    if a.keep:
        np.savez_compressed(Path(a.keep) / "depths.npz", observation=depth_m, truth=d_true)
        obs.save(Path(a.keep) / "observation.npz")
    if not metric:
        true_fit = fit_rows_with_scale(points, colors, crop, pre, rng=0, metric_scale=true_scale)
        ts_obs, ts_true, _ = observation_vs_truth(
            _observe(crop, true_fit, backend, a.image_scale, a.prediction_blur),
            _truth_depth(truth, true_fit, scene_from_true, a.image_scale),
        )
        # what the L1 would be with a perfect scale cue: the reconstruction's own share of it
        out["hist_l1_true_scale"] = float(np.abs(ts_obs - ts_true).sum())
    out["_observation"] = obs

    if a.fit:
        seeds_dir = Path(a.keep) / "seeds" if a.keep else None
        out["fit"] = fit_and_compare(obs, root, a.fit, d_true, seeds_dir)
        if a.fit_true_mesh:
            # the same camera, budget and seeds on a perfect reconstruction: the LAI error the
            # method itself makes from this view (one draw of the canopy, one row), and whether
            # the true mesh prefers the truth's basin to that answer's (the optimiser's miss)
            out["fit_true_mesh"] = fit_and_compare(
                true_mesh_observation(obs, d_true),
                root,
                a.fit,
                d_true,
                seeds_dir / "true-mesh" if seeds_dir else None,
                attribute="true-mesh",
            )
    return out


#: ICP matching distances (m), coarse to fine, by crop: maize's drone models sit up to ~10 cm
#: off their cameras; soybean's walk-round ones millimetres to a centimetre or two
CONTENT_ICP_DISTANCES = {"soybean": (0.1, 0.03, 0.015), "maize": (0.3, 0.1, 0.05)}


def _content_frame(points, fit, scene_from_true, true_mesh, crop: str):
    """``register_to_truth`` of the reconstructed points near the row camera (within 0.6 of the
    render height of its ground point) onto the true mesh and the true ground (z = 0 under the
    mesh's extent): the truth frame as the reconstruction's own surfaces give it."""
    from cropcraft_core.fit.geometry import sample_mesh
    from cropcraft_core.rowfit.truth import camera_in_truth, register_to_truth

    radius = 0.6 * fit.render_height
    world = fit.to_world(points)
    near = np.hypot(*(world[:, :2] - fit.camera.center[:2]).T) < radius
    # the truth's surfaces, densely, a little beyond the same disc (a sparse sampling's own
    # spacing would read as distance: 22 % of a maize model matched at 5 cm, 80 % densely)
    rng = np.random.default_rng(0)
    c = camera_in_truth(fit, scene_from_true).center[:2]
    leaves = sample_mesh(true_mesh, 2_000_000, rng)
    leaves = leaves[np.hypot(*(leaves[:, :2] - c).T) < radius + 0.5]
    lo, hi = true_mesh.vertices[:, :2].min(0), true_mesh.vertices[:, :2].max(0)
    ground = np.c_[
        rng.uniform(
            np.maximum(lo, c - radius - 0.5),
            np.minimum(hi, c + radius + 0.5),
            (len(leaves) // 2, 2),
        ),
        np.zeros(len(leaves) // 2),
    ]
    return register_to_truth(
        points[near], scene_from_true, np.r_[leaves, ground], CONTENT_ICP_DISTANCES[crop]
    )


def _observe(crop: str, fit, backend, image_scale: float, prediction_blur=0.0):
    """The observation the scene flow's observe stage makes from this row fit (its
    predictions blurred as the stage's ``prediction_blur`` says)."""
    from cropcraft_core.observe import Observation
    from cropcraft_core.surfaces import prediction_blur_m

    return Observation.from_surfaces(
        crop,
        backend.render,
        fit.camera,
        fit.camera_in_scene(),
        fit.scale,
        fit.render_height,
        image_scale=image_scale,
        preset_overrides={
            "prediction_blur_m": prediction_blur_m(backend, fit.scale, prediction_blur)
        },
    )


#: Where the row camera's holes were lost, in pipeline order (``hole_breakdown``).
HOLE_CAUSES = ("unseen", "no_stereo", "inconsistent", "fusion")
#: What the stereo found on a ``no_stereo`` hole's pixels (``hole_breakdown``).
NO_STEREO_SPLIT = ("no_stereo_empty", "no_stereo_front", "no_stereo_behind")


def hole_breakdown(
    points: np.ndarray,
    true_cams: list,
    true_depths: list[np.ndarray],
    stereo_cams: list,
    raw_maps: list[np.ndarray],
    fused_maps: list[np.ndarray],
    scene_from_true: np.ndarray,
    rel: float = 0.02,
) -> dict:
    """Why the true surface behind each of the row camera's holes is missing, as fractions of
    the holes (in pipeline order, each point counted once, at its first loss):

    * ``unseen``: fewer than two photos see the point (its true depth in the view agrees within
      1 cm + 0.5 %): no reconstruction could place it;
    * ``no_stereo``: seen, but no view's stereo depth map has it (within ``rel``);
    * ``inconsistent``: some stereo map has it, but the consistency filter dropped it in all;
    * ``fusion``: a filtered depth map has it, and the fused surface still lost it.

    The ``no_stereo`` points are split further by what the stereo put on their pixels in the
    photos that see them (``NO_STEREO_SPLIT``, also fractions of the holes, summing to
    ``no_stereo``): ``no_stereo_empty``, no depth in any of them (no plane scored
    ``min_ncc``, the winner was the sweep's first or last plane, or no source saw the pixel);
    ``no_stereo_front`` / ``no_stereo_behind``, a depth, but the one closest to the point's lies
    in front of it (a nearer surface won, as leaf edges fattened into gaps do) / behind it.

    points: (n, 3) true surface points (truth frame) behind the holes; true_cams/true_depths:
    the photos' true cameras and z-depth maps; stereo_cams: the backend's cameras at its depth
    maps' size (scene frame, same order); ``scene_from_true``: the 4×4 similarity to it."""
    from cropcraft_core.surfaces.tsdf import sample_depth

    n = len(points)
    if n == 0:
        return {"holes": 0, **{k: 0.0 for k in HOLE_CAUSES + NO_STEREO_SPLIT}}
    seen = np.zeros(n, np.int64)
    raw_ok = np.zeros(n, bool)
    fused_ok = np.zeros(n, bool)
    nearest = np.full(n, np.inf)  # the raw depth closest to the point's, relative, signed
    p_scene = points @ scene_from_true[:3, :3].T + scene_from_true[:3, 3]
    for tc, td, sc, rm, fm in zip(
        true_cams, true_depths, stereo_cams, raw_maps, fused_maps, strict=True
    ):
        dv, z = sample_depth(td, tc, points)
        with np.errstate(invalid="ignore"):
            vis = np.abs(dv - z) < 0.01 + 0.005 * z
        seen += vis
        ds, zs = sample_depth(rm, sc, p_scene)
        with np.errstate(invalid="ignore", divide="ignore"):
            e = np.where(vis, (ds - zs) / zs, np.nan)
            raw_ok |= np.abs(e) < rel
        closer = np.isfinite(e) & (np.abs(e) < np.abs(nearest))
        nearest[closer] = e[closer]
        ds, zs = sample_depth(fm, sc, p_scene)
        with np.errstate(invalid="ignore"):
            fused_ok |= vis & (np.abs(ds - zs) < rel * zs)
    cause = np.select([seen < 2, ~raw_ok, ~fused_ok], list(HOLE_CAUSES[:3]), default=HOLE_CAUSES[3])
    no_stereo = cause == "no_stereo"
    split = np.select(
        [~np.isfinite(nearest), nearest < 0], list(NO_STEREO_SPLIT[:2]), default=NO_STEREO_SPLIT[2]
    )
    return {
        "holes": n,
        **{k: float(np.mean(cause == k)) for k in HOLE_CAUSES},
        **{k: float(np.mean(no_stereo & (split == k))) for k in NO_STEREO_SPLIT},
    }


def _holes(
    root: Path, poses, truth_poses, backend, fit, scene_from_true, image_scale, d_true, obs
) -> dict:
    """The row camera's holes (no reconstructed surface where the true mesh has one): their
    share of the view, the share without a fully supported surface (``render_supported``) and
    :func:`hole_breakdown` of the true points behind the holes."""
    from cropcraft_core.rowfit.truth import camera_in_truth

    cam = camera_in_truth(fit, scene_from_true)
    if image_scale != 1.0:
        cam = cam.scaled(image_scale)
    hole = ~np.isfinite(obs.depth) & np.isfinite(d_true)
    true_cam = {Path(n).stem: c for n, c in truth_poses}
    stems = [Path(n).stem for n, _ in poses]
    s = float(backend.config.mvs_scale)
    parts = hole_breakdown(
        cam.unproject(d_true)[hole],
        [true_cam[k] for k in stems],
        [np.load(root / "depth" / f"{k}.npy") for k in stems],
        [c.scaled(s) for c in backend.cameras],
        backend.raw_depth_maps,
        backend.depth_maps,
        scene_from_true,
    )
    cam_scene = fit.camera_in_scene()
    if image_scale != 1.0:
        cam_scene = cam_scene.scaled(image_scale)
    bare = ~np.isfinite(backend.render_supported(cam_scene)) & np.isfinite(d_true)
    return {"fraction": float(hole.mean()), "unsupported": float(bare.mean()), **parts}


def _truth_depth(truth, fit, scene_from_true: np.ndarray, image_scale: float) -> np.ndarray:
    """The true mesh's depth (NaN where no leaf) from the fit's row camera placed in the truth
    frame by the similarity ``scene_from_true``."""
    from cropcraft_core.rowfit.truth import camera_in_truth

    cam = camera_in_truth(fit, scene_from_true)
    if image_scale != 1.0:
        cam = cam.scaled(image_scale)
    d, _ = truth.render(cam)
    return np.where(np.isfinite(d), d, np.nan)


def fit_rules(
    obs, budget: str, checkpoint_dir: Path | None = None, layout=None, **options
) -> tuple[dict, dict]:
    """BO at ``SEEDSxEVALS`` on ``obs``, its seeds combined by every rule at no extra fitting
    cost (``bench_accuracy.rules``: the crop's default first as ``bo``, then the other rules as
    ``bo-<rule>`` and the re-scoring's unpolished answer), as ``bench accuracy`` compares them:
    ``({row: params}, {"params_std": the seeds' spread, "seeds": each seed's best point and
    loss})``. Each seed resumes from ``checkpoint_dir/seed-N.json`` where given, so a killed run
    continues where it stopped. ``layout``: the scene's planting layout (None: the crop's
    default). ``options``: further ``FitConfig`` fields (e.g. the re-scoring's
    ``reevaluate_canopies``)."""
    from benchmarks.bench_accuracy import combine_scene, rules, seed_seconds
    from cropcraft_core.fit import FitConfig, fit_seed
    from cropcraft_core.optimize.bo import aggregate

    seeds, evals = (int(x) for x in budget.lower().split("x"))
    cfg = FitConfig(n_seeds=seeds, n_evals=evals, n_initial=max(evals * 2 // 5, 5), **options)
    if checkpoint_dir is not None:
        checkpoint_dir.mkdir(parents=True, exist_ok=True)
    results = [
        fit_seed(obs, s, cfg, layout, checkpoint_dir / f"seed-{s}.json" if checkpoint_dir else None)
        for s in range(seeds)
    ]
    seconds = sum(seed_seconds(r) for r in results)
    answers = combine_scene(obs.crop, rules(obs.crop, "bo", cfg), results, seconds, obs, layout)
    box = cfg.param_box(obs.crop)
    seeds_rec = [
        {"seed": r.seed, "params": box.params(r.reported_x), "loss": float(r.best_y)}
        for r in results
    ]
    spread = {"params_std": box.spread(aggregate(results).std_x), "seeds": seeds_rec}
    return {row: params for row, (params, _) in answers.items()}, spread


def truth_metrics(root: Path) -> Path:
    """The scene's ``truth/metrics.json``, which a fit is scored against; a scene made without
    it (``bench surfaces`` makes its scenes so) is named before any fitting."""
    f = root / "truth" / "metrics.json"
    if not f.is_file():
        raise SystemExit(
            f"{f} is missing: the scene was made without its true traits (as bench surfaces "
            "makes them); --fit needs a scene made by cropcraft synth or bench pipeline"
        )
    return f


#: The sides ``fit_and_compare`` can ask whose miss an answer is of.
ATTRIBUTE_SIDES = ("both", "true-mesh", None)

#: The traits ``fit_and_compare`` compares with the truth's.
FIT_TRAITS = ("lai", "leaf_angle_mean_deg", "leaf_angle_std_deg", "node_count", "internode_mean_m")


def fit_and_compare(
    obs,
    root: Path,
    budget: str,
    d_true: np.ndarray,
    checkpoint_dir: Path | None = None,
    attribute: str | None = "both",
    **options,
) -> dict:
    """Fit the observation at ``SEEDSxEVALS`` (:func:`fit_rules`), compare the default
    answer's canopy traits with the truth and say whose miss it is against the true mesh's
    depth ``d_true`` from the same camera (:func:`loss_attribution`), asked of ``attribute``'s
    sides: ``"both"`` (the observation and the true mesh), ``"true-mesh"`` (the true mesh
    alone: for a fit of the true mesh itself) or None (not asked: its polishes are the costly
    part). The other rules' answers and traits (``rules``)
    and every seed's best point (``seeds``) ride along, so one fit compares the rules on a
    photo observation as ``bench accuracy`` does on renders. ``options``: further
    ``FitConfig`` fields (:func:`fit_rules`)."""
    from cropcraft_core.metrics import canopy_metrics
    from cropcraft_core.procedural import generate_canopy

    if attribute not in ATTRIBUTE_SIDES:
        raise ValueError(f"attribute must be one of {ATTRIBUTE_SIDES}, got {attribute!r}")
    true = json.loads(truth_metrics(root).read_text())  # before the fit: it may be missing
    true_params = json.loads((root / "truth" / "params.json").read_text())
    layout = scene_layout(root, obs.crop)
    t = time.perf_counter()
    answers, spread = fit_rules(obs, budget, checkpoint_dir, layout, **options)
    seconds = time.perf_counter() - t

    def traits(params: dict) -> dict:
        canopy = generate_canopy(obs.crop, params, layout, seed=0)
        est = canopy_metrics(canopy, gap_fraction=False)
        return {k: {"estimated": est.get(k), "true": true.get(k)} for k in FIT_TRAITS if k in true}

    def lai_err(rows: dict) -> float | None:
        lai = rows.get("lai")
        return (lai["estimated"] - lai["true"]) / lai["true"] if lai else None

    per_rule = {}
    for row, params in answers.items():
        rows = traits(params)
        per_rule[row] = {"params": params, "traits": rows, "lai_rel_err": lai_err(rows)}
    main = per_rule.pop("bo")
    out = {
        "budget": budget,
        "seconds": seconds,
        "params": main["params"],
        "params_std": spread["params_std"],
        "true_params": true_params,
        "traits": main["traits"],
        "lai_rel_err": main["lai_rel_err"],
        "rules": per_rule,
        "seeds": spread["seeds"],
    }
    if attribute:
        out["loss"] = loss_attribution(
            obs,
            d_true,
            main["params"],
            true_params["params"],
            observation_side=attribute == "both",
        )
    return out


#: Where the canopy seeds of :func:`loss_attribution` start in the re-scoring's sequence: past
#: its first 1,000, so no optimiser seed and no re-scoring (up to 1,000 canopies) draws them.
ATTRIBUTION_FROM = 1_000
_ATTRIBUTION_CANOPIES = reevaluation_seeds(ATTRIBUTION_FROM + 7 * 16)[ATTRIBUTION_FROM:]
#: Canopies on which :func:`loss_attribution` polishes the answer and the truth to their basins'
#: floors.
POLISH_SEEDS = tuple(_ATTRIBUTION_CANOPIES[:16])
#: Nelder-Mead evaluations (each on :data:`POLISH_SEEDS`) that take a point to its basin's floor.
#: On canopy E of RESULTS (true poses; answer 12.4 nodes against 8) 80 took the answer from 0.0346
#: to 0.0239 and the truth from 0.0297 to 0.0235 on the observation (16 canopies).
FLOOR_EVALS = 80
#: Groups of ``len(POLISH_SEEDS)`` fresh canopies, disjoint from the polish's, on which every
#: point is scored. A floor scored on the canopies it was polished on is biased low by the
#: polish (on E the two floors' order on the true mesh flipped between two sets of 16; on 128
#: fresh canopies it held); six groups give each point's mean and the paired differences'
#: standard error.
SCORE_GROUPS = tuple(tuple(_ATTRIBUTION_CANOPIES[i : i + 16]) for i in range(16, 7 * 16, 16))
#: A floor is deeper than the other when the paired difference exceeds this many standard errors.
SIGNIFICANT_SE = 2.0


def loss_attribution(
    obs,
    d_true: np.ndarray,
    answer: dict,
    truth: dict,
    floor_evals: int = FLOOR_EVALS,
    polish_seeds: tuple[int, ...] = POLISH_SEEDS,
    score_groups: tuple[tuple[int, ...], ...] = SCORE_GROUPS,
    observation_side: bool = True,
) -> dict:
    """Whose miss a wrong answer is, asked on two sides: the observation, and the true mesh's
    depth ``d_true`` seen by the same camera with the same rules (what a perfect reconstruction
    would give). On each side the fit's ``answer`` and the ``truth``'s parameters are polished
    to their basin's *floor* under that side's loss (Nelder-Mead, ``select.polish``,
    ``floor_evals`` evaluations averaged over the ``polish_seeds`` canopies); then the points
    and the floors are scored on the ``score_groups`` of fresh canopies: per point the mean
    over the groups, per side the answer's floor minus the truth's, paired by group, with its
    standard error.

    Points alone mislead: an answer that combines several seeds (their median) sits off its
    basin's floor and can score worse than the truth while its basin is as deep. Floors must be
    polished on the side they are compared on: from the truth, the observation's loss can slide
    into the reconstruction's preferred basin, whose point the true mesh then rejects as it
    rejects the answer. The verdict (``whose``) counts a difference beyond
    :data:`SIGNIFICANT_SE` standard errors:

    * ``optimiser``: the truth's basin is deeper on the observation; the fit missed it.
    * ``reconstruction``: the observation ties the basins or prefers the answer's, the true mesh
      prefers the truth's: the reconstruction moved (or flattened) the loss's minimum.
    * ``loss``: neither side prefers the truth's basin (a valley the statistics cannot resolve,
      or a draw of the canopy its parameters rarely give).

    A side whose polish took one point out of its basin, to the other's floor, prefers the
    other's basin (``floor_left_basin``; :func:`whose_miss`).

    The verdict is about a wrong answer: one in the truth's basin also reads ``loss``.

    Without ``observation_side`` only the true mesh is asked (``obs`` is then the true mesh's
    own observation, :func:`true_mesh_observation`): ``optimiser`` where it prefers the
    truth's basin, else ``loss``."""
    from dataclasses import replace

    from cropcraft_core.config.params import bounds, params_from_vector, params_to_vector
    from cropcraft_core.fit.forward import ForwardModel
    from cropcraft_core.fit.select import polish
    from cropcraft_core.observe import loss

    sides = {"observation": obs, "true_mesh": replace(obs, stats=truth_stats(obs, d_true))}
    if not observation_side:
        del sides["observation"]
    # the predicted statistics depend on the camera and the mask rules, not on the reference:
    # each point's canopies are rendered once and scored against both sides
    fm = ForwardModel(obs)

    def scores(params: dict) -> dict[str, np.ndarray]:
        st = [fm.stats(params, g) for g in score_groups]
        return {
            side: np.asarray([loss(o.stats, s, o.preset).total for s in st])
            for side, o in sides.items()
        }

    points = {"answer": answer, "truth": truth}
    b = bounds(obs.crop)

    def unit(p: dict) -> np.ndarray:
        return (params_to_vector(obs.crop, p) - b[:, 0]) / (b[:, 1] - b[:, 0])

    at_points = {k: scores(p) for k, p in points.items()}
    out: dict = {"floor_params": {}, "floor_difference": {}, "floor_left_basin": {}}
    for side, o in sides.items():
        side_fm = ForwardModel(o)
        per = {k: v[side] for k, v in at_points.items()}
        floors = {}
        for k, p in points.items():
            x, _, _ = polish(side_fm, params_to_vector(obs.crop, p), polish_seeds, floor_evals)
            floors[k] = params_from_vector(obs.crop, x)
            per[f"{k}_floor"] = scores(floors[k])[side]
        d = per["answer_floor"] - per["truth_floor"]
        out[side] = {k: float(v.mean()) for k, v in per.items()}
        out["floor_params"][side] = floors
        u = {k: unit(f) for k, f in floors.items()}
        out["floor_left_basin"][side] = {
            k: bool(np.linalg.norm(u[k] - u[other]) < np.linalg.norm(u[k] - unit(points[k])))
            for k, other in (("answer", "truth"), ("truth", "answer"))
        }
        out["floor_difference"][side] = {
            "mean": float(d.mean()),
            "se": float(d.std(ddof=1) / np.sqrt(d.size)) if d.size > 1 else 0.0,
        }
    out["whose"] = whose_miss(out["floor_difference"], out["floor_left_basin"])
    return out


def whose_miss(
    diff: dict, left_basin: dict | None = None, significant: float = SIGNIFICANT_SE
) -> str:
    """The verdict of :func:`loss_attribution` from the floors' paired differences (answer's
    minus truth's: ``{"observation": {"mean", "se"}, "true_mesh": {...}}``) and, per side,
    which polish left its start's basin (``{"observation": {"answer": bool, "truth": bool},
    ...}``): a floor that ends nearer the other point's floor than its own start (in the unit
    parameter box) found no basin of its own there, so that side prefers the other point's
    basin whatever the floors' losses say. (On a 1.1 m canopy the answer, 0.31 from the truth,
    scored 0.128 on the true mesh against the truth's 0.026; polished there it moved 0.30, to
    the truth's leaf size, and ended 0.005 below the truth's floor.)"""

    def deeper_at_truth(against: str) -> bool:
        left = (left_basin or {}).get(against, {})
        if left.get("answer") != left.get("truth"):
            return bool(left.get("answer"))
        d = diff[against]
        return d["mean"] > significant * d["se"] and d["mean"] > 0.0

    if "observation" not in diff:  # the true mesh asked alone: a perfect reconstruction's fit
        return "optimiser" if deeper_at_truth("true_mesh") else "loss"
    if deeper_at_truth("observation"):
        return "optimiser"
    return "reconstruction" if deeper_at_truth("true_mesh") else "loss"


def print_checks(
    row: dict | None, hist_l1: float, fit: dict | None, extra: list | tuple = ()
) -> None:
    """The table of #4's measures against :data:`TARGETS`: the row fit's errors (``row``:
    ``RowFitErrors.to_dict()``, or None), the depth histogram's L1, ``extra`` (label, value,
    target key) rows, and the LAI error of ``fit`` (``fit_and_compare``'s record, or None)."""
    checks = []
    if row is not None:
        checks += [
            ("row direction error (deg)", row["direction_deg"], "direction_deg"),
            ("row lateral offset (m)", row["lateral_m"], "lateral_m"),
            ("render-height error (rel)", row["height_rel"], "height_rel"),
        ]
    checks += [("depth histogram L1", hist_l1, "hist_l1"), *extra]
    if fit:
        checks.append(("LAI relative error", abs(fit["lai_rel_err"]), "lai_rel_err"))
    print(f"  {'measure':<28}{'value':>10}{'target':>10}  met")
    for label, v, k in checks:
        print(f"  {label:<28}{v:>10.4f}{TARGETS[k]:>10.3f}  {'yes' if v <= TARGETS[k] else 'NO'}")


def print_rules(fit: dict) -> None:
    """The other combination rules' answers from the same seeds (``fit_and_compare``'s
    ``rules``): LAI error, leaf angle, nodes."""
    for row, r in fit.get("rules", {}).items():
        t = r["traits"]
        print(
            f"  {row + ':':<28}LAI {100 * r['lai_rel_err']:+.1f} %, leaf angle "
            f"{t['leaf_angle_mean_deg']['estimated']:.1f}°, "
            f"{t['node_count']['estimated']:.1f} nodes"
        )


def _print(out: dict) -> None:
    from cropcraft_core.surfaces.consistency import describe

    sec = out["seconds"]
    print(f"photos → observation, {out['views']} views {out['resolution']}, poses {out['poses']}")
    print(f"  {'stage':<24}{'seconds':>10}")
    for k, v in sec.items():
        print(f"  {k:<24}{v:>10.1f}")
    if "sfm" in out and "reused" in out["sfm"]:
        print(f"  SfM: reused {out['sfm']['reused']} (its time is not in the table)")
    elif "sfm" in out:
        s = out["sfm"]
        print(
            f"  SfM: {s['n_registered']}/{s['n_images']} registered, "
            f"{s['mean_reprojection_error_px']:.2f} px, {s['n_points']} points, {s['seconds']}"
        )
    sc = out["scale"]
    print(
        f"  scale {sc['fitted']:.4f} m/unit from {sc['source']} "
        f"(true {sc['true']:.4f}: {100 * sc['rel_err']:+.2f} %)"
    )
    print_checks(
        out["rowfit"],
        out["hist_l1"],
        out.get("fit"),
        [("images → observation (s)", sec["images_to_observation"], "images_to_observation_s")],
    )
    if "registration" in out:
        r, c = out["registration"], out["rowfit_content"]
        print(
            "  against the reconstructed surfaces (the model moved onto the truth by ICP: "
            + " ".join(f"{100 * x:+.1f}" for x in r["shift_m"])
            + f" cm, {r['rotation_deg']:.2f}°; {100 * r['fitness']:.0f} % matched at "
            f"{100 * r['rmse_m']:.1f} cm): direction {c['direction_deg']:.2f}°, lateral "
            f"{100 * c['lateral_m']:.2f} cm, height {100 * c['height_rel']:.2f} %, "
            f"depth histogram L1 {out['hist_l1_content']:.4f}"
        )
    print(
        f"  depth histogram L1 of the true depth against itself moved by "
        f"{100 * out['hist_l1_shift']['rel']:.1f} % of the render height: "
        f"{out['hist_l1_shift']['l1']:.4f} (how tight the L1 target is)"
    )
    if "cover" in out:
        print(cover_line(out["cover"]))
    if "blur_match" in out:
        print(blur_match_line(out["blur_match"]))
    if "hist_l1_true_scale" in out:
        print(
            f"  depth histogram L1 with the true scale instead of the rows': "
            f"{out['hist_l1_true_scale']:.4f} (the reconstruction's share)"
        )
    c = out.get("consistency")
    if c and c["net"] is not None:
        print(
            f"  surfaces against {c['views']} photos: {describe(c['unreconstructed'], c['extra'])}"
        )
    if out.get("holes"):
        h = out["holes"]
        print(
            f"  holes: {100 * h['fraction']:.1f} % of the row camera's view has no surface where "
            f"the truth has one ({100 * h['unsupported']:.1f} % without a fully supported one, "
            "before a fill); lost as: " + ", ".join(f"{k} {100 * h[k]:.0f} %" for k in HOLE_CAUSES)
        )
        print(
            "  no stereo: "
            + ", ".join(
                f"{k.removeprefix('no_stereo_')} {100 * h[k]:.0f} %" for k in NO_STEREO_SPLIT
            )
            + " (no depth on the point's pixels / the closest depth in front of / behind it)"
        )
    if out.get("fit"):
        for k, r in out["fit"]["traits"].items():
            print(f"  {k:<28}{r['estimated']:>10.3f} (true {r['true']:.3f})")
        print_rules(out["fit"])
        att = out["fit"]["loss"]
        n = sum(len(g) for g in SCORE_GROUPS)
        print(
            f"  loss on {n} fresh canopies, answer / true parameters (their basins' floors): "
            + ", ".join(
                f"against the {k.replace('_', ' ')} {att[k]['answer']:.4f} / "
                f"{att[k]['truth']:.4f} ({att[k]['answer_floor']:.4f} / "
                f"{att[k]['truth_floor']:.4f}, difference {att['floor_difference'][k]['mean']:+.4f}"
                f" ± {att['floor_difference'][k]['se']:.4f})"
                for k in ("observation", "true_mesh")
            )
            + "".join(
                f"; on the {side.replace('_', ' ')} the {k}'s polish left its basin"
                for side, flags in att.get("floor_left_basin", {}).items()
                for k, v in flags.items()
                if v and not all(flags.values())
            )
            + f"; whose miss: {att['whose']}"
        )
    if out.get("fit_true_mesh"):
        m, f = out["fit_true_mesh"], out["fit"]
        print(
            f"  LAI relative error {100 * f['lai_rel_err']:+.1f} % = the method's from this row "
            f"camera {100 * m['lai_rel_err']:+.1f} % (the true mesh fitted at the same budget: a "
            f"perfect reconstruction) + the reconstruction's "
            f"{100 * (f['lai_rel_err'] - m['lai_rel_err']):+.1f} points"
        )
        att, d = m["loss"], m["loss"]["floor_difference"]["true_mesh"]
        print(
            f"  the perfect reconstruction's answer / the true parameters on the true mesh: "
            f"{att['true_mesh']['answer']:.4f} / {att['true_mesh']['truth']:.4f} (their basins' "
            f"floors {att['true_mesh']['answer_floor']:.4f} / {att['true_mesh']['truth_floor']:.4f}"
            f", difference {d['mean']:+.4f} ± {d['se']:.4f}); its miss: "
            + {"optimiser": "the optimiser's", "loss": "the view's (this draw of the canopy)"}[
                att["whose"]
            ]
        )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="cropcraft bench pipeline", description=__doc__.splitlines()[0]
    )
    add_scene_arguments(ap)
    ap.add_argument(
        "--crop",
        choices=tuple(DEFAULT_TRAJECTORY),
        default=None,
        help="the scene's crop (default: a reused scene's own, else soybean)",
    )
    ap.add_argument(
        "--trajectory",
        choices=("walk", "drone"),
        default=None,
        help="a new scene's capture (default: walk for soybean, drone for maize)",
    )
    ap.add_argument("--poses", choices=("sfm", "truth"), default="sfm")
    ap.add_argument("--sfm", action="append", default=[], help="run_sfm option KEY=VALUE")
    ap.add_argument(
        "--sfm-dir", default=None, help="keep SfM's work here; reuse its model if there (timing!)"
    )
    ap.add_argument("--surfaces", action="append", default=[], help="SurfacesConfig KEY=VALUE")
    ap.add_argument("--image-scale", type=positive, default=1.0, help="row-camera resolution")
    ap.add_argument(
        "--prediction-blur",
        default=0.0,
        type=lambda v: v if v == "auto" else float(v),
        help="blur of the fit's predictions, as the scene flow's observe.prediction_blur: "
        "metres (0: none, the default) or 'auto' (the surfaces' own softening)",
    )
    ap.add_argument(
        "--bbox",
        type=lambda v: v if v == "auto" else json.loads(v),
        default="auto",
        help='scene box: "auto" (default) or JSON [[x, y, z], [x, y, z]]',
    )
    ap.add_argument(
        "--fit",
        type=seeds_by_evals,
        default=None,
        metavar="SEEDSxEVALS",
        help="also fit, e.g. 10x300",
    )
    ap.add_argument(
        "--fit-true-mesh",
        action="store_true",
        help="with --fit: also fit the true mesh seen from the same row camera (a perfect "
        "reconstruction), to split the LAI error into the reconstruction's and the method's",
    )
    ap.add_argument("--json", type=output_file, default=None)
    ap.add_argument(
        "--keep",
        default=None,
        help="save points, row fit, surfaces, depths and the observation here",
    )
    a = ap.parse_args(argv)
    if a.fit_true_mesh and not a.fit:
        ap.error("--fit-true-mesh needs --fit SEEDSxEVALS (the budget of both fits)")
    check_settings(ap, a)
    out = run(a)
    out.pop("_observation")
    _print(out)
    if a.json:
        write_json(a.json, out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
