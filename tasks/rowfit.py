"""Stage ``rowfit``: ground plane, crop rows and the row camera from the surfaces' point cloud."""

from __future__ import annotations

from typing import Any

from tasks.common import Timer, artefact, key_of, make_record, open_store, stage_task


@stage_task("rowfit")
def rowfit(
    store_root: str,
    scene: str,
    config: dict[str, Any],
    upstream: dict[str, Any],
    lease: str | None = None,
) -> dict[str, Any]:
    """:func:`cropcraft_core.rowfit.fit_ground_and_rows` on ``{scene}/surfaces/points.npz``;
    stores ``{scene}/rowfit/rowfit.json`` (``RowFit.to_dict()`` plus ``camera_in_scene``, the
    row camera in the poses' frame, which the observe stage renders the surfaces from).

    config: ``preset`` (RowFitPreset overrides), ``seed``, ``scale`` (metres per scene unit),
    ``layout`` (planting; its row spacing is the known one). The scale source is
    ``metric_poses`` when the poses stage imported metric poses, ``camera_height`` or
    ``camera_distance`` when it levelled SfM poses with the user's camera height or measured
    distance between two photos, ``gps`` with the photos' GPS positions (with a camera
    height, the scale is measured again as the hint over the cameras' median height above
    the fitted ground plane: the poses stage's ground, the sparse points' lowest, lies on the
    leaves when SfM saw no soil), ``user_hint`` when ``scale`` is given, else
    ``row_spacing`` (the fitted rows' spacing against the planting row spacing,
    ``assumed_metric`` when it cannot be measured). The known row spacing also snaps the best
    row onto the periodic row pattern (``RowFitPreset.row_spacing``).
    """
    from cropcraft_core.rowfit import fit_rows_with_scale
    from cropcraft_core.rowfit import preset as rowfit_preset
    from cropcraft_core.sfm.frame import looks_down
    from cropcraft_core.sfm.poses import Poses
    from tasks.fit_seed import layout_of

    store = open_store(store_root, scene=scene, lease=lease, what="rowfit")
    crop = scene.split("/")[1]
    with Timer() as t:
        cloud = store.get_npz(key_of(upstream["surfaces"], "points"))
        poses_summary = upstream["poses"].get("summary", {})
        metric = bool(poses_summary.get("metric"))
        frame_source = poses_summary.get("frame", {}).get("scale_source")
        hinted = ("camera_height", "camera_distance", "gps")
        metric_source = frame_source if frame_source in hinted else "metric_poses"
        scale = config.get("scale")
        camera_height = cameras = None
        nadir = False
        if not scale:
            poses = Poses.from_dict(store.get_json(key_of(upstream["poses"], "poses")))
            if frame_source == "camera_height":
                camera_height = (poses.centers(), float(poses_summary["frame"]["camera_height_m"]))
            else:
                # the heights the scale implies put to the rows: a distance in feet, or poses
                # read as an AR capture's metres that are not (an older Metashape export);
                # SfM's: the canopy against the cameras' height at the rows' scale (a drone
                # flight scaled by a hand-held prior)
                cameras, nadir = poses.centers(), looks_down(poses)
        spacing = layout_of(crop, config).row_spacing
        overrides = {"row_spacing": spacing, **dict(config.get("preset") or {})}
        fit = fit_rows_with_scale(
            cloud["points"],
            cloud["colors"],
            crop,
            rowfit_preset(crop, **overrides),
            rng=int(config.get("seed", 0)),
            metric_scale=1.0 if metric and not scale else None,
            metric_source=metric_source,
            camera_height=camera_height,
            scale_hint=float(scale) if scale else None,
            known_row_spacing=spacing,
            cameras=cameras,
            nadir=nadir,
            gps_reason=poses_summary.get("gps", {}).get("reason"),
        )
        record = {**fit.to_dict(), "camera_in_scene": fit.camera_in_scene().to_dict()}
        key = artefact(scene, "rowfit", "rowfit.json")
        digest = store.put_json(key, record)
    return make_record(
        "rowfit",
        scene,
        {"rowfit": key},
        {key: digest},
        {
            "n_rows": len(fit.rows),
            # the lines within 10° of the best row: the rows; the others are RANSAC's lines
            # through leaves (a maize drone scene: 5 of 6 lay 19-67° across the rows)
            "n_rows_parallel": fit.parallel_rows(),
            "row_azimuth_deg": fit.best_row.azimuth_deg,
            "render_height_m": fit.render_height,
            "scale": fit.scale,
            "scale_source": fit.scale_source,
            "dense": fit.dense,
            # the rows against a camera-height hint far from the crop's usual (else absent)
            **({"scale_warning": w} if (w := fit.diagnostics.get("scale_warning")) else {}),
        },
        t.seconds,
    )
