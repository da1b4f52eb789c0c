"""Stage ``poses``: camera poses of the ingested images, imported (nerfstudio
``transforms.json`` or a COLMAP model) or computed by structure from motion."""

from __future__ import annotations

import json
from pathlib import Path, PurePosixPath
from typing import Any

import numpy as np

from cropcraft_core.errors import InputError
from tasks.common import (
    Timer,
    artefact,
    core,
    key_of,
    make_record,
    named_ply,
    open_store,
    stage_log,
    stage_progress,
    stage_task,
    workdir,
)


def _rename_to_ingested(poses, manifest: dict, where: str):
    """Poses named by the source photos → named by the ingested images (same stems), their
    intrinsics scaled to the ingested size (``ingest.max_size``). A camera of a photo that
    ingest turned upright by its EXIF orientation, given at the size the photo is stored at
    (COLMAP and the tools that run it ignore the tag), is turned with it; a mirroring
    orientation is refused."""
    import dataclasses

    Poses = core("poses", "cropcraft_core.sfm", "Poses")
    turn_upright, mirroring = core(
        "poses", "cropcraft_core.geometry.lens", "turn_upright", "MIRRORING_ORIENTATIONS"
    )
    # names compared in one Unicode form: macOS writes "été" decomposed (NFD), JSON writers
    # and COLMAP's text files as typed (NFC), and the same-looking names did not match
    # (session 94's folders audit)
    by_source = {_nfc(im["source"]): im["name"] for im in manifest["images"]}
    by_stem = {PurePosixPath(src).stem: name for src, name in by_source.items()}

    def ingested_as(name: str) -> str | None:
        name = _nfc(name)
        return by_source.get(name) or by_stem.get(PurePosixPath(name).stem)

    posed = {ingested_as(n) for n in poses.names}
    for d in manifest.get("duplicates") or ():
        # a dropped copy's pose is the pose of the photo kept in its place, where that has
        # none of its own (Finder's "view_003 copy.jpg" sorts first and is kept)
        kept = by_source.get(_nfc(d["duplicate_of"]))
        if kept is not None and kept not in posed:
            by_source.setdefault(_nfc(d["source"]), kept)
            by_stem.setdefault(PurePosixPath(_nfc(d["source"])).stem, kept)
    ingested = {im["name"]: im for im in manifest["images"]}
    views, missing, dist, unlike = [], [], {}, []
    for name, cam in poses:
        new = ingested_as(name)
        if new is None:
            missing.append(name)
            continue
        im = ingested[new]
        size = (im["width"], im["height"])
        lens_of = poses.distortion.get(name)
        orientation = int(im.get("exif_orientation") or 1)
        if orientation in mirroring:
            raise InputError(
                f"the photo {im['source']} carries EXIF orientation {orientation}, a mirror "
                f"image: the poses in {where} cannot be turned to it; save the photo upright "
                "without the tag and pose it again"
            )
        upright = (im["source_width"], im["source_height"])
        stored = upright[::-1] if orientation in (6, 8) else upright  # a quarter turn
        if orientation != 1 and (cam.width, cam.height) == stored:
            cam, lens_of = turn_upright(cam, lens_of, orientation)
        if (cam.width, cam.height) != size and _same_view(cam, upright):
            # posed at the photo's size, or at a uniform downscale of it (nerfstudio's
            # images_2 / images_4 copies): the intrinsics follow the photo as ingested
            sx, sy = im["width"] / cam.width, im["height"] / cam.height
            cam = dataclasses.replace(
                cam,
                width=im["width"],
                height=im["height"],
                fx=cam.fx * sx,
                fy=cam.fy * sy,
                cx=cam.cx * sx,
                cy=cam.cy * sy,
            )
        elif (cam.width, cam.height) != size:
            unlike.append(
                f"{name} as {cam.width}x{cam.height} pixels, but the photo {im['source']} is "
                f"{im['source_width']}x{im['source_height']} upright"
            )
            continue
        views.append((new, cam))
        if lens_of:
            dist[new] = lens_of
    if unlike:  # every one named at once, not one a rerun (session 92's photos audit)
        more = "; ".join(unlike[1:8]) + (", ..." if len(unlike) > 8 else "")
        more = f" (and {len(unlike) - 1} more: {more})" if len(unlike) > 1 else ""
        raise InputError(
            f"{where} gives {unlike[0]}{more}: poses of other (rotated or cropped?) photos"
        )
    if len(views) < 3:
        raise InputError(
            f"the imported poses name {len(poses)} images but only {len(views)} of them were "
            f"ingested (e.g. missing: {', '.join(missing[:5])}); give the poses of these photos"
        )
    return Poses(tuple(views), dist), missing


def _nfc(name: str) -> str:
    """``name`` in Unicode's composed form (NFC)."""
    import unicodedata

    return unicodedata.normalize("NFC", name)


def _same_view(cam, upright: tuple[int, int]) -> bool:
    """Whether a camera of ``cam.width`` x ``cam.height`` pixels poses the whole photo of size
    ``upright``: that size, or that size scaled uniformly (nerfstudio's ``images_2``: the
    height within a pixel of the width's scale)."""
    w, h = upright
    if (cam.width, cam.height) == (w, h):
        return True
    return cam.width != w and abs(h * cam.width / w - cam.height) <= 1.0


def _fetch(uri: str, dest: Path) -> Path:
    """Copy a file or folder at a local path / fsspec URL to ``dest``; return the local path.
    A ``transforms.json`` comes with the sparse-point PLY it names, where that is there."""
    from fsspec.core import url_to_fs

    fs, path = url_to_fs(uri)
    target = dest / PurePosixPath(path.rstrip("/")).name
    if fs.isdir(path):
        root = path.rstrip("/")
        for src in fs.find(root):  # every file below, by name (no glob: see _copy)
            _copy(fs, src, target / PurePosixPath(src).relative_to(root))
        return target
    _copy(fs, path, target)
    ply = named_ply(fs, path, target.read_bytes())  # not JSON: the import names the problem
    if ply is not None:
        _copy(fs, ply[1], target.parent / ply[0])
    return target


def _copy(fs, src: str, dst: Path) -> None:
    """One file to a local path, opened by its name: ``fs.get`` reads a path as a glob
    pattern, and a folder named ``Plot [rep 2]`` matched nothing (a bare ``FileNotFoundError:
    []``: session 94's folders audit)."""
    import shutil

    dst.parent.mkdir(parents=True, exist_ok=True)
    with fs.open(src, "rb") as fin, open(dst, "wb") as fout:
        shutil.copyfileobj(fin, fout, 1 << 20)


def gps_positions(manifest: dict) -> dict[str, list[float]]:
    """``{written name: [latitude, longitude, altitude]}`` of the ingested photos whose EXIF
    gave a GPS position (ingest's ``gps``; a manifest written before ingest read them has none)."""
    return {im["name"]: list(im["gps"]) for im in manifest["images"] if im.get("gps")}


def focal_priors(manifest: dict) -> dict[str, float]:
    """``{written name: focal length (px)}`` of the ingested photos whose EXIF gave one
    (ingest's ``focal_px``; a manifest written before ingest read them has none)."""
    return {im["name"]: float(im["focal_px"]) for im in manifest["images"] if im.get("focal_px")}


@stage_task("poses")
def poses(
    store_root: str,
    scene: str,
    config: dict[str, Any],
    upstream: dict[str, Any],
    poses_uri: str | None = None,
    lease: str | None = None,
) -> dict[str, Any]:
    """Poses of the ingested images, stored as ``{scene}/poses/poses.json`` (and, after SfM, the
    sparse points as ``points.npz``).

    With ``poses_uri``: :func:`~cropcraft_core.sfm.import_poses` (a ``transforms.json`` or a
    COLMAP model folder); ``config["imported_metric"]`` says whether they are in metres and
    gravity-aligned (``"auto"``: a ``transforms.json`` of an AR capture is, a COLMAP model or
    a ``transforms.json`` of an SfM project is not). Without:
    :func:`~cropcraft_core.sfm.run_sfm` (config ``matcher``, ``seed``, ``num_threads``,
    ``sift_peak_threshold``: None for ``SIFT_PEAK_THRESHOLD``, ``guided_matching``; each
    camera starts from the focal length ingest read from the photos' EXIF unless
    ``exif_focal`` is false: the summary's ``focal_prior_px`` and ``n_focal_prior`` say which).
    All are then levelled by :func:`~cropcraft_core.sfm.level_poses` (z up, plot-centred):
    metric imported ones without scaling, up along their frame's gravity axis, a frame
    levelled already kept as it is; the others in metres from ``config["camera_height"]``
    or ``config["camera_distance"]`` ([photo A, photo B, metres] between their cameras;
    source names or stems) if given, else from the photos' GPS positions where they set it
    (:func:`~cropcraft_core.sfm.gps.gps_scale`; ``config["gps"]`` false: never; the summary's
    ``gps`` says what they gave, and why not where they were not used), else provisional from
    ``prior_camera_height`` or the crop's typical capture height. The summary's ``frame``
    records how, and ``metric`` is true when the scale is known (metric poses, a hint, GPS).
    """
    import_poses, run_sfm, level_poses = core(
        "poses", "cropcraft_core.sfm", "import_poses", "run_sfm", "level_poses"
    )
    from cropcraft_core.sfm.frame import GRAVITY_AXIS_DEG, PRIOR_CAMERA_HEIGHT_M
    from cropcraft_core.sfm.poses import MIN_REGISTERED_FRACTION, SIFT_PEAK_THRESHOLD

    crop = scene.split("/")[1]
    prior = config.get("prior_camera_height") or PRIOR_CAMERA_HEIGHT_M.get(crop, 1.4)
    hint = config.get("camera_height")
    distance = config.get("camera_distance")
    peak = config.get("sift_peak_threshold")

    def level(found, points, summary: dict, metric: bool = False):
        """Level the poses; record how in ``summary`` (``frame``, and ``metric`` when the scale
        is known rather than provisional; ``gps`` where the photos carry positions)."""
        scale = None
        positions = gps_positions(manifest) if config.get("gps", True) else {}
        if positions and not metric and hint is None and distance is None:
            from cropcraft_core.sfm.gps import gps_scale

            named = [n for n in found.names if n in positions]
            g = gps_scale(
                np.array([found.camera(n).center for n in named]).reshape(-1, 3),
                np.array([positions[n] for n in named]).reshape(-1, 3),
            )
            summary["gps"] = g.summary()
            scale = g.scale
            if g.reason:
                stage_log().warning("poses: the photos' GPS does not set the scale: %s", g.reason)
        out_poses, out_points, frame = level_poses(
            found,
            points,
            metric=metric,
            camera_height_m=None if metric else hint,
            camera_distance=tuple(distance) if distance and not metric else None,
            gps_scale=scale,
            prior_camera_height_m=float(prior),
            gravity_axis_deg=GRAVITY_AXIS_DEG if metric else None,
            keep_levelled=metric,
        )
        summary["frame"] = frame.summary()
        summary["metric"] = frame.metric
        return out_poses, out_points

    store = open_store(store_root, scene=scene, lease=lease, what="poses")
    ing = upstream["ingest"]
    manifest = store.get_json(key_of(ing, "manifest"))
    hashes: dict[str, str] = {}
    arts: dict[str, str] = {}
    with Timer() as t, workdir("poses") as tmp:
        if poses_uri:
            imported = import_poses(_fetch(poses_uri, tmp))
            result, photoless = _rename_to_ingested(imported.poses, manifest, poses_uri)
            metric = config.get("imported_metric", "auto")
            if metric == "auto":
                metric = not imported.from_sfm
            if metric and (hint is not None or distance is not None):
                raise InputError(
                    f"the imported poses at {poses_uri} are read as metric, so a camera height "
                    "or distance cannot scale them: set poses.imported_metric=false to have "
                    "them scaled by it"
                )
            summary = {
                "source": "imported",
                "metric": metric,
                "n_registered": len(result),
                "n_images": len(manifest["images"]),
            }
            if photoless:  # a capture's frames whose photos are not here: said, not dropped
                stage_log().warning(
                    "poses: %d of the %d poses in %s have no photo among the %d ingested: %s",
                    len(photoless), len(imported.poses), poses_uri, len(manifest["images"]),
                    ", ".join(photoless[:8]) + (", ..." if len(photoless) > 8 else ""),
                )  # fmt: skip
                summary["photoless_poses"] = len(photoless)
            unposed = sorted({im["name"] for im in manifest["images"]} - set(result.names))
            if unposed:  # a photo added since the capture was posed: said, not dropped quietly
                if len(result) < MIN_REGISTERED_FRACTION * len(manifest["images"]):
                    raise InputError(
                        f"the poses in {poses_uri} cover {len(result)} of the "
                        f"{len(manifest['images'])} photos (e.g. without a pose: "
                        f"{', '.join(unposed[:5])}): pose them all, or run SfM without --poses"
                    )
                stage_log().warning(
                    "poses: %d of %d photos have no pose in %s and are left out: %s",
                    len(unposed), len(manifest["images"]), poses_uri, ", ".join(unposed),
                )  # fmt: skip
                summary["unposed"] = unposed
            result, _ = level(result, imported.points, summary, metric=metric)
        else:
            with store.open_local(key_of(ing, "images")) as image_dir:
                sfm = run_sfm(
                    image_dir,
                    tmp / "sfm",
                    matcher=config.get("matcher", "auto"),
                    num_threads=int(config.get("num_threads", 2)),
                    seed=int(config.get("seed", 0)),
                    sift_peak_threshold=float(peak if peak is not None else SIFT_PEAK_THRESHOLD),
                    guided_matching=bool(config.get("guided_matching", False)),
                    focal_priors=focal_priors(manifest) if config.get("exif_focal", True) else None,
                    progress=stage_progress(scene, "poses"),
                )
            summary = {"source": "sfm", **sfm.summary()}
            summary.pop("model_dir", None)
            # photos SfM did not register (in its largest model): named, not dropped quietly
            missed = sorted({im["name"] for im in manifest["images"]} - set(sfm.poses.names))
            if missed:
                summary["unregistered"] = missed
            result, points = level(sfm.poses, sfm.points, summary)
            key = artefact(scene, "poses", "points.npz")
            hashes[key] = store.put_npz(key, {"points": points, "colors": sfm.colors})
            arts["points"] = key
        key = artefact(scene, "poses", "poses.json")
        hashes[key] = store.put_json(key, result.to_dict())
        arts["poses"] = key
    json.dumps(summary)  # small and JSON-able by construction
    return make_record("poses", scene, arts, hashes, summary, t.seconds)
