"""Stage ``consistency``: the reconstructed surfaces against the photos, at the photos' cameras."""

from __future__ import annotations

from typing import Any

import numpy as np

from tasks.common import Timer, artefact, key_of, make_record, open_store, stage_task
from tasks.surfaces import _surfaces_api


@stage_task("consistency")
def consistency(
    store_root: str,
    scene: str,
    config: dict[str, Any],
    upstream: dict[str, Any],
    lease: str | None = None,
) -> dict[str, Any]:
    """:func:`cropcraft_core.surfaces.consistency.photo_consistency` of the fitted surfaces
    against up to ``max_views`` of the ingested photos, over the plot (the fitted ground plane
    inside the surfaces' scene box); stores ``{scene}/consistency/consistency.json`` (every
    view's shares too). The record's summary carries ``unreconstructed`` (photo plant with no
    reconstructed surface), ``extra`` (raised surface over photo soil), both as shares of the
    photos' plant pixels, ``net`` (their difference) and ``warning`` (``consistency_warning``
    at ``warn``, or None). A diagnostic: nothing downstream reads it but the report and the
    run's summary, so the fit's cache keys do not depend on it.

    config: ``max_views``, ``min_height`` (m above the ground from which a surface is raised),
    ``plant_a_below`` (None: the crop's row-fit colour rule), ``warn`` (the |net| limit; None:
    no warning).
    """
    from cropcraft_core.rowfit import preset as rowfit_preset
    from cropcraft_core.sfm.poses import Poses, pinhole_photos
    from cropcraft_core.surfaces.consistency import (
        MAX_VIEWS,
        MIN_HEIGHT_M,
        photo_consistency,
        pick_views,
    )

    _surfaces_api()
    from cropcraft_core.surfaces import load_surfaces

    store = open_store(store_root, scene=scene, lease=lease, what="consistency")
    crop = scene.split("/")[1]
    a_below = config.get("plant_a_below")
    if a_below is None:
        a_below = rowfit_preset(crop).plant_a_below
    with Timer() as t:
        rf = store.get_json(key_of(upstream["rowfit"], "rowfit"))
        poses = Poses.from_dict(store.get_json(key_of(upstream["poses"], "poses")))
        views = pick_views(len(poses.names), int(config.get("max_views", MAX_VIEWS)))
        images: list[np.ndarray] = [np.zeros((0, 0, 3), np.uint8)] * len(poses.names)
        with store.open_local(key_of(upstream["ingest"], "images")) as image_dir:
            for i, photo in zip(views, pinhole_photos(image_dir, poses, views), strict=True):
                images[i] = photo
        with store.open_local(key_of(upstream["surfaces"], "model")) as model_dir:
            backend = load_surfaces(model_dir)
            result = photo_consistency(
                backend.render,
                images,
                poses.cameras,
                rf["ground_normal"],
                rf["ground_offset"],
                scale=float(rf["scale"]),
                bbox=backend.bbox,
                plant_a_below=float(a_below),
                min_height_m=float(config.get("min_height", MIN_HEIGHT_M)),
                views=views,
            )
        key = artefact(scene, "consistency", "consistency.json")
        digest = store.put_json(key, result.to_dict())
    return make_record(
        "consistency",
        scene,
        {"consistency": key},
        {key: digest},
        {
            "views": len(result.views),
            "photo_plant": result.photo_plant,
            "holes": result.holes,
            "unreconstructed": result.unreconstructed,
            "extra": result.extra,
            "net": result.net,
            "warning": result.warning(config.get("warn")),
        },
        t.seconds,
    )
