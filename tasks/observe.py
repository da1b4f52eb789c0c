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
    :class:`~cropcraft_core.observe.Observation` (``Observation.from_depth``: the paper's mask
    and histograms); store it as ``{scene}/observe/observation.npz``.

    config: ``image_scale`` (row-camera resolution relative to the preset's, e.g. 0.5) and
    ``preset`` (ObservePreset overrides). Depth is converted to metres with the row fit's scale.
    """
    from cropcraft_core.geometry.camera import PinholeCamera
    from cropcraft_core.observe import Observation
    from cropcraft_core.observe import preset as observe_preset

    _surfaces_api()
    from cropcraft_core.surfaces import load_surfaces

    store = open_store(store_root)
    crop = scene.split("/")[1]
    with Timer() as t:
        rf = store.get_json(key_of(upstream["rowfit"], "rowfit"))
        factor = float(config.get("image_scale", 1.0))
        cam_world = PinholeCamera.from_dict(rf["camera"])
        cam_scene = PinholeCamera.from_dict(rf["camera_in_scene"])
        if factor != 1.0:
            cam_world, cam_scene = cam_world.scaled(factor), cam_scene.scaled(factor)
        with store.open_local(key_of(upstream["surfaces"], "model")) as model_dir:
            backend = load_surfaces(model_dir)
            depth, rgb = backend.render(cam_scene)
        depth_m = np.asarray(depth, np.float64) * float(rf["scale"])
        p = observe_preset(
            crop,
            **{
                "render_height": float(rf["render_height"]),
                "image_width": cam_world.width,
                "image_height": cam_world.height,
                **dict(config.get("preset") or {}),
            },
        )
        obs = Observation.from_depth(
            crop, depth_m, cam_world, rgb=rgb, preset=p, meta={"scene": scene}
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
            "size_px": [cam_world.width, cam_world.height],
            "foreground_fraction": float(np.mean(obs.mask)),
            "render_height_m": float(rf["render_height"]),
        },
        t.seconds,
    )
