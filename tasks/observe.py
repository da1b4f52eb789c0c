"""Stage ``observe``: the row observation (depth, RGB, mask, histograms) rendered from the
surfaces through the row camera."""

from __future__ import annotations

import io
from typing import Any

import numpy as np

from tasks.common import Timer, artefact, key_of, make_record, open_store, stage_task
from tasks.surfaces import _surfaces_api


@stage_task("observe")
def observe(
    store_root: str, scene: str, config: dict[str, Any], upstream: dict[str, Any]
) -> dict[str, Any]:
    """Render the fitted surfaces from the row camera and build the
    :class:`~cropcraft_core.observe.Observation` (``Observation.from_surfaces``: the paper's mask
    and histograms); store it as ``{scene}/observe/observation.npz``. The record's summary
    carries ``no_surface_fraction`` (also in the observation's meta), the share of the view
    without a fully supported surface (``SurfaceBackend.render_supported``: for tsdf, the
    two-view mesh before its one-view fill; ``cropcraft_core.observe.coverage_warning``).

    config: ``image_scale`` (row-camera resolution relative to the preset's, e.g. 0.5) and
    ``preset`` (ObservePreset overrides). Depth is converted to metres with the row fit's scale.
    """
    from cropcraft_core.geometry.camera import PinholeCamera
    from cropcraft_core.observe import Observation, no_surface_fraction

    _surfaces_api()
    from cropcraft_core.surfaces import load_surfaces

    store = open_store(store_root)
    crop = scene.split("/")[1]
    with Timer() as t:
        rf = store.get_json(key_of(upstream["rowfit"], "rowfit"))
        scale = float(config.get("image_scale", 1.0))
        cam_scene = PinholeCamera.from_dict(rf["camera_in_scene"])
        with store.open_local(key_of(upstream["surfaces"], "model")) as model_dir:
            backend = load_surfaces(model_dir)
            # coverage: the share of the view without a fully supported surface (before a fill)
            unseen = no_surface_fraction(backend.render_supported(cam_scene.scaled(scale)))
            obs = Observation.from_surfaces(
                crop,
                backend.render,
                PinholeCamera.from_dict(rf["camera"]),
                cam_scene,
                float(rf["scale"]),
                float(rf["render_height"]),
                image_scale=scale,
                preset_overrides=config.get("preset"),
                meta={"scene": scene, "no_surface_fraction": unseen},
            )
        buf = io.BytesIO()
        obs.save(buf)
        key = artefact(scene, "observe", "observation.npz")
        digest = store.put_bytes(key, buf.getvalue())
    return make_record(
        "observe",
        scene,
        {"observation": key},
        {key: digest},
        {
            "size_px": [obs.camera.width, obs.camera.height],
            "foreground_fraction": float(np.mean(obs.mask)),
            "no_surface_fraction": unseen,
            "render_height_m": float(rf["render_height"]),
        },
        t.seconds,
    )
