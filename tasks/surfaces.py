"""Stage ``surfaces``: the visible surfaces of the posed photos (the paper's NeRF stage)."""

from __future__ import annotations

from typing import Any

from cropcraft_core.errors import CropCraftError, InputError
from tasks.common import (
    Timer,
    artefact,
    core,
    key_of,
    make_record,
    open_store,
    stage_log,
    stage_progress,
    stage_task,
    workdir,
)

#: The backends whose stereo reads each photo's depths of the scene box (nerfacto trains on
#: every photo, the box only bounding its samples).
STEREO_BACKENDS = ("tsdf", "points")


def _surfaces_api():
    try:
        from cropcraft_core.surfaces import SurfacesConfig, make_backend
    except ImportError as exc:  # the surfaces package is optional in a partial checkout
        raise CropCraftError(
            f"stage surfaces not available: cropcraft_core.surfaces cannot be imported ({exc})"
        ) from exc
    return SurfacesConfig, make_backend


def ground_hint(crop: str, frame: dict[str, Any] | None) -> str | None:
    """Why a scene's surfaces found nothing, where its poses are the likely cause: metric
    poses without points stand a prior capture height above a ground of its own choosing,
    and photos taken from elsewhere (a drone's maize filed as soybean) put the scene box off
    the plot. None where the ground was found otherwise."""
    from cropcraft_core.sfm.frame import PRIOR_CAMERA_HEIGHT_M

    if not frame or frame.get("ground_source") != "prior":
        return None
    others = ", ".join(
        f"{other}'s ~{h:g} m" for other, h in PRIOR_CAMERA_HEIGHT_M.items() if other != crop
    )
    return (
        "The poses are metric but carry no points to find the ground by, so it was placed "
        f"{frame['camera_height_m']:.3g} m below the cameras (poses.prior_camera_height, "
        f"{crop}'s usual capture height): photos taken from another height put the scene box "
        f"off the plot. Set poses.prior_camera_height to the cameras' height above the ground, "
        f"or check the crop ({others})"
    )


@stage_task("surfaces")
def surfaces(
    store_root: str,
    scene: str,
    config: dict[str, Any],
    upstream: dict[str, Any],
    lease: str | None = None,
) -> dict[str, Any]:
    """Fit a surfaces backend (``config["backend"]``: tsdf or points on CPU, nerfacto on
    CUDA) to the ingested images (undistorted into their pinhole cameras) and their poses;
    store the fitted model under ``{scene}/surfaces/model/`` and a coloured point cloud
    (``points`` (n, 3) m, ``colors`` (n, 3) in [0, 1]) as ``{scene}/surfaces/points.npz``.

    config: ``SurfacesConfig`` fields, plus ``bbox`` ([[xmin, ymin, zmin], [xmax, ymax, zmax]]
    in the poses' frame, ``"auto"`` for the crop's scene box in the levelled frame, or None)
    and ``n_points`` (point-cloud size).
    """
    Poses, pinhole_photos = core("surfaces", "cropcraft_core.sfm", "Poses", "pinhole_photos")
    SurfacesConfig, make_backend = _surfaces_api()
    from cropcraft_core.surfaces import SurfacesError, resolve_bbox, views_in_box

    store = open_store(store_root, scene=scene, lease=lease, what="surfaces")
    cfg = dict(config)
    bbox = resolve_bbox(cfg.pop("bbox", None), scene.split("/")[1])
    n_points = int(cfg.pop("n_points", 100_000))
    poses = Poses.from_dict(store.get_json(key_of(upstream["poses"], "poses")))
    hashes: dict[str, str] = {}
    with Timer() as t, workdir("surfaces") as tmp:
        with store.open_local(key_of(upstream["ingest"], "images")) as image_dir:
            images = pinhole_photos(image_dir, poses)  # undistorted where poses have a lens
        if cfg.get("backend") == "nerfacto" and not cfg.get("workdir"):
            cfg["workdir"] = str(tmp / "nerfacto")  # its photos and checkpoints go with tmp
        backend = make_backend(SurfacesConfig.from_dict(cfg))
        cams, names = poses.cameras, poses.names
        away: list[str] = []
        try:
            if backend.name in STEREO_BACKENDS and cfg.get("depth_range") is None:
                keep = views_in_box(names, cams, bbox)  # the others have no depths of the plot
                kept = set(keep)
                away = [n for i, n in enumerate(names) if i not in kept]
                if away:
                    stage_log().warning(
                        "surfaces: %d of %d photos do not see the scene box and are left out: %s",
                        len(away), len(cams), ", ".join(away),
                    )  # fmt: skip
                    images, cams = [images[i] for i in keep], [cams[i] for i in keep]
            backend.fit(images, cams, bbox, progress=stage_progress(scene, "surfaces"))
        except (InputError, SurfacesError) as exc:
            hint = ground_hint(scene.split("/")[1], upstream["poses"]["summary"].get("frame"))
            if hint is None:
                raise
            raise type(exc)(f"{exc}. {hint}") from exc
        points, colors = backend.point_cloud(n_points)
        backend.save(tmp / "model")
        hashes.update(store.put_tree(tmp / "model", artefact(scene, "surfaces", "model")))
        key = artefact(scene, "surfaces", "points.npz")
        hashes[key] = store.put_npz(key, {"points": points, "colors": colors})
    timings = {k: float(v) for k, v in backend.timings.items() if isinstance(v, int | float)}
    return make_record(
        "surfaces",
        scene,
        {"model": artefact(scene, "surfaces", "model"), "points": key},
        hashes,
        {
            "backend": backend.name,
            "n_points": int(len(points)),
            "timings": timings,
            **({"photos_left_out": away} if away else {}),
        },
        t.seconds,
    )
