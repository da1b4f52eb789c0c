"""Stage ``observe``: the row observation (depth, RGB, mask, histograms) rendered from the
surfaces through the row camera."""

from __future__ import annotations

import io
from typing import Any

import numpy as np

from tasks.common import Timer, artefact, key_of, make_record, open_store, stage_task
from tasks.surfaces import _surfaces_api


def _observe(
    backend: Any,
    crop: str,
    scene: str,
    rf: dict[str, Any],
    config: dict[str, Any],
    camera: Any,
    camera_in_scene: Any,
    limit: float | None = None,
    **meta: Any,
) -> tuple[Any, float]:
    """``(observation, no_surface_fraction)`` of the surfaces ``backend`` from the world
    ``camera`` (``camera_in_scene``: the same in the surfaces' frame): the share of its view
    without a fully supported surface (before a fill), then ``Observation.from_surfaces`` at
    the stage's ``image_scale`` and ``preset``; the observation is None when that share is over
    ``limit``. A view the preset pools beside the row camera
    (``views_along``/``views_across``) that shows more than ``NO_SURFACE_WARN`` without a
    supported surface, and more than the row camera's own view, lies (partly) outside the
    reconstruction and is left out of the pool (``meta["views_left_out"]``)."""
    from cropcraft_core.observe import Observation, no_surface_fraction
    from cropcraft_core.surfaces import prediction_blur_m

    scale = float(config.get("image_scale", 1.0))
    unseen = no_surface_fraction(backend.render_supported(camera_in_scene.scaled(scale)))
    if limit is not None and unseen > limit:
        return None, unseen
    from tasks.fit_seed import layout_of

    obs = Observation.from_surfaces(
        crop,
        backend.render,
        camera,
        camera_in_scene,
        float(rf["scale"]),
        float(rf["render_height"]),
        image_scale=scale,
        preset_overrides={
            **dict(config.get("preset") or {}),
            # the fused surfaces bend the leaves near their edges where procedural leaves stay
            # flat: the fit can blur its predictions alike (ObservePreset.prediction_blur_m)
            "prediction_blur_m": prediction_blur_m(
                backend, float(rf["scale"]), config.get("prediction_blur", 0.0)
            ),
        },
        meta={"scene": scene, "no_surface_fraction": unseen, **meta},
        # the planting row spacing places the neighbouring rows a pooled observation adds
        # (ObservePreset.views_across; the flow passes the layout only then)
        row_spacing=layout_of(crop, config).row_spacing,
        # each pooled view's share without a supported surface, against the row camera's
        no_surface=lambda cam: no_surface_fraction(backend.render_supported(cam)),
    )
    return obs, unseen


def _views_summary(obs: Any) -> dict[str, Any]:
    """The pooled row cameras of ``obs`` for a stage record's summary: how many were pooled
    and which were left out (outside the reconstruction); empty for the single camera."""
    if "views" not in obs.meta:
        return {}
    return {"views_pooled": len(obs.meta["views"]), "views_left_out": obs.meta["views_left_out"]}


def _npz(obs: Any) -> bytes:
    buf = io.BytesIO()
    obs.save(buf)
    return buf.getvalue()


@stage_task("observe")
def observe(
    store_root: str,
    scene: str,
    config: dict[str, Any],
    upstream: dict[str, Any],
    lease: str | None = None,
) -> dict[str, Any]:
    """Render the fitted surfaces from the row camera and build the
    :class:`~cropcraft_core.observe.Observation` (``Observation.from_surfaces``: the paper's mask
    and histograms); store it as ``{scene}/observe/observation.npz``. The record's summary
    carries ``no_surface_fraction`` (also in the observation's meta), the share of the view
    without a fully supported surface (``SurfaceBackend.render_supported``: for tsdf, the
    two-view mesh before its one-view fill; ``cropcraft_core.observe.coverage_warning``).

    config: ``image_scale`` (row-camera resolution relative to the preset's, e.g. 0.5),
    ``prediction_blur`` (metres, 0 = none, the default; or ``"auto"``: the surfaces
    backend's own softening near leaf edges, ``cropcraft_core.surfaces.prediction_blur_m``;
    the summary's ``prediction_blur_m`` and ``prediction_blur_px``) and
    ``preset`` (ObservePreset overrides; ``views_along``/``views_across`` pool the statistics
    over several row cameras, :func:`cropcraft_core.observe.observe_views`), and ``layout``
    (its row spacing places the neighbouring rows; the flow passes it only when they are
    pooled). Depth is converted to metres with the row fit's scale. The no-surface share is
    the row camera's own; a pooled view less covered than both it and ``NO_SURFACE_WARN`` is
    left out of the pool (the summary's ``views_pooled`` and ``views_left_out``).
    """
    from cropcraft_core.geometry.camera import PinholeCamera
    from cropcraft_core.observe import check_coverage

    _surfaces_api()
    from cropcraft_core.surfaces import load_surfaces

    store = open_store(store_root, scene=scene, lease=lease, what="observe")
    crop = scene.split("/")[1]
    with Timer() as t:
        rf = store.get_json(key_of(upstream["rowfit"], "rowfit"))
        with store.open_local(key_of(upstream["surfaces"], "model")) as model_dir:
            obs, unseen = _observe(
                load_surfaces(model_dir),
                crop,
                scene,
                rf,
                config,
                PinholeCamera.from_dict(rf["camera"]),
                PinholeCamera.from_dict(rf["camera_in_scene"]),
            )
        check_coverage(unseen)  # a view the surfaces hardly cover: no fit from its gaps
        key = artefact(scene, "observe", "observation.npz")
        digest = store.put_bytes(key, _npz(obs))
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
            "prediction_blur_m": float(obs.preset.prediction_blur_m),
            "prediction_blur_px": float(obs.prediction_blur_px),
            **_views_summary(obs),
        },
        t.seconds,
    )


@stage_task("observe_rows")
def observe_rows(
    store_root: str,
    scene: str,
    config: dict[str, Any],
    upstream: dict[str, Any],
    lease: str | None = None,
) -> dict[str, Any]:
    """Observations over the best row's neighbours
    (:func:`cropcraft_core.rowfit.neighbours.neighbour_row_views`: the row camera moved by ±k
    planting row spacings, or with ``snap_fraction`` onto a fitted row there), each rendered
    and built as the ``observe`` stage's; a neighbour whose view has more than
    ``max_no_surface`` without a fully supported surface, and more than the best row's own
    view (the ``observe`` record's ``no_surface_fraction``), lies (partly) outside the
    reconstruction and is left out. Stores ``{scene}/observe/row_p1/observation.npz`` etc.;
    the record's artefacts are ``observation@{index}`` and its summary lists every candidate
    row (index, offset, kept, no_surface_fraction, foreground_fraction).

    config: ``max_side`` (neighbours tried on each side), ``max_no_surface``,
    ``snap_fraction`` (None: k row spacings from the best row; else onto a fitted row within
    that fraction of a spacing), ``image_scale``, ``prediction_blur``
    and ``preset`` (the observe stage's, so every row is observed alike) and ``layout`` (its
    row spacing).
    """
    from cropcraft_core.geometry.camera import PinholeCamera
    from cropcraft_core.observe import NO_SURFACE_WARN
    from cropcraft_core.rowfit import Row, camera_to_scene, neighbour_row_views
    from tasks.fit_seed import layout_of

    _surfaces_api()
    from cropcraft_core.surfaces import load_surfaces

    store = open_store(store_root, scene=scene, lease=lease, what="observe_rows")
    crop = scene.split("/")[1]
    with Timer() as t:
        rf = store.get_json(key_of(upstream["rowfit"], "rowfit"))
        # a neighbour no worse covered than the best row itself (whose answer is kept anyway)
        # is kept too
        best = upstream["observe"]["summary"].get("no_surface_fraction") or 0.0
        limit = max(float(config.get("max_no_surface", NO_SURFACE_WARN)), float(best))
        rows = [
            Row(np.asarray(r["direction"], float), np.asarray(r["point"], float), r["n_inliers"])
            for r in rf["rows"]
        ]
        views = neighbour_row_views(
            PinholeCamera.from_dict(rf["camera"]),
            rows,
            layout_of(crop, config).row_spacing,
            int(config.get("max_side", 2)),
            snap_fraction=config.get("snap_fraction"),
        )
        artefacts, hashes, listed = {}, {}, []
        with store.open_local(key_of(upstream["surfaces"], "model")) as model_dir:
            backend = load_surfaces(model_dir)
            for view in views:
                cam_scene = camera_to_scene(view.camera, rf["world_from_scene"], rf["scale"])
                obs, unseen = _observe(
                    backend,
                    crop,
                    scene,
                    rf,
                    config,
                    view.camera,
                    cam_scene,
                    limit,
                    row=view.to_dict(),
                )
                entry = {
                    "index": view.index,
                    "offset_m": view.offset_m,
                    "snapped": view.snapped,
                    "no_surface_fraction": unseen,
                    "kept": obs is not None,
                }
                listed.append(entry)
                if obs is None:
                    continue
                entry["foreground_fraction"] = float(np.mean(obs.mask))
                entry.update(_views_summary(obs))
                key = artefact(scene, "observe_rows", "observation.npz", row=view.index)
                hashes[key] = store.put_bytes(key, _npz(obs))
                artefacts[f"observation@{view.index}"] = key
    return make_record(
        "observe_rows",
        scene,
        artefacts,
        hashes,
        {"rows": listed, "kept": [e["index"] for e in listed if e["kept"]]},
        t.seconds,
    )


def row_observation_record(rec: dict[str, Any], index: int) -> dict[str, Any]:
    """The part of an ``observe_rows`` record that row ``index``'s fit reads, shaped as an
    ``observe`` record (``artefacts["observation"]`` and its one hash), so that a row's seeds
    key on their own observation only."""
    key = key_of(rec, f"observation@{int(index)}")
    return {
        "stage": "observe_rows",
        "scene": rec["scene"],
        "artefacts": {"observation": key},
        "hashes": {key: rec["hashes"][key]},
        "summary": {"row": int(index)},
        "seconds": 0.0,
    }
