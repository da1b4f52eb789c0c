"""Stage ``report``: one self-contained HTML page per scene."""

from __future__ import annotations

import io
from typing import Any

import numpy as np

from tasks.common import (
    STAGES,
    Timer,
    artefact,
    key_of,
    load_observation,
    make_record,
    open_store,
    photos_left_out,
    stage_task,
)
from tasks.fit_seed import layout_of, row_spacing_used


def _timings(upstream: dict[str, Any]) -> dict[str, float]:
    """Seconds per stage of the records the report reads; the seeds and answers of every row
    fitted (``seed-3@row_p1``, ``aggregate@row_p1`` beside the best row's) summed and
    counted, and the scene's answer under ``rows.answer=mean`` (``answer``) as the rows
    stage it is."""
    out: dict[str, float] = {}
    n_rows = sum(1 for n in upstream if n == "aggregate" or n.startswith("aggregate@"))
    over = f" over {n_rows} rows" if n_rows > 1 else ""
    for stage in STAGES:
        if stage in ("fit_seed", "aggregate"):
            prefix = "seed-" if stage == "fit_seed" else "aggregate"
            recs = [r for n, r in upstream.items() if n.split("@")[0].startswith(prefix)]
            if recs and (stage == "fit_seed" or n_rows > 1):
                out[f"{stage} (x{len(recs)}{over})"] = sum(float(r["seconds"]) for r in recs)
            elif recs:
                out[stage] = float(recs[0].get("seconds", 0.0))
        elif stage in upstream:
            out[stage] = float(upstream[stage].get("seconds", 0.0))
    return out


def _libraries(env: dict[str, str] | None) -> str | None:
    """``"numpy 2.4.6, scipy 1.17.1, ..."`` of a stage record's environment (None where the
    record predates it): the fit's answer moves with these, so the report names them."""
    return ", ".join(f"{k} {v}" for k, v in env.items()) if env else None


def _percent(x: float | None) -> str | None:
    return None if x is None else f"{100 * float(x):.1f} %"


@stage_task("report")
def report(
    store_root: str,
    scene: str,
    config: dict[str, Any],
    upstream: dict[str, Any],
    lease: str | None = None,
) -> dict[str, Any]:
    """Build ``{scene}/report/report.html`` with :func:`cropcraft_core.report.scene_report_html`:
    input thumbnails, observed vs predicted row-camera depth (the predicted canopy rendered by
    the fit's forward model with the generate stage's seed), the mesh preview, the metrics with
    units, the parameters with their spread over seeds, and every stage's time.

    config: ``n_thumbnails``, ``thumbnail_px``.
    """
    from PIL import Image

    from cropcraft_core.fit import ForwardModel
    from cropcraft_core.report import scene_report_html, thumbnail

    store = open_store(store_root, scene=scene, lease=lease, what="report")
    crop = scene.split("/")[1]
    with Timer() as t:
        thumbs = []
        n = int(config.get("n_thumbnails", 6))
        keys = [
            k
            for k in store.list(key_of(upstream["ingest"], "images"))
            if k.lower().endswith((".png", ".jpg", ".jpeg"))
        ]
        step = max(1, len(keys) // max(1, n))
        for k in keys[::step][:n]:
            with Image.open(io.BytesIO(store.get_bytes(k))) as im:
                thumbs.append(
                    thumbnail(np.asarray(im.convert("RGB")), int(config.get("thumbnail_px", 192)))
                )
        obs = load_observation(store, upstream)
        # the scene's answer: the best row's fit, or the rows' mean (rows.answer=mean)
        fit = store.get_json(key_of(upstream.get("answer", upstream["aggregate"]), "fit"))
        recipe = store.get_json(key_of(upstream["generate"], "recipe"))
        metrics = store.get_json(key_of(upstream["metrics"], "metrics"))
        fwd = ForwardModel(obs, layout_of(crop, {"layout": config.get("layout")}))
        predicted = fwd.depth(fit["params"], int(recipe["seed"]))
        preview = store.get_bytes(key_of(upstream["export"], "preview.png"))
        ps = upstream["poses"]["summary"]
        frame = ps.get("frame") or {}
        rf = upstream["rowfit"]["summary"]
        info = {
            "crop": crop,
            "photos ingested": upstream["ingest"]["summary"].get("n_images"),
            "poses": ps.get("source"),
            "registered": (
                f"{ps['n_registered']} of {ps['n_images']}"
                if ps.get("n_registered") is not None and ps.get("n_images")
                else None
            ),
            "reprojection error (px)": ps.get("mean_reprojection_error_px"),
            "matching": ps.get("matcher"),
            "up direction from": frame.get("up_source"),
            "surfaces backend": upstream["surfaces"]["summary"].get("backend"),
            "rows found": (
                f"{rf['n_rows_parallel']} (of {rf['n_rows']} lines, the others across the rows)"
                if rf.get("n_rows_parallel") is not None and rf["n_rows_parallel"] < rf["n_rows"]
                else rf.get("n_rows")
            ),
            "row view without surface": _percent(
                upstream["observe"]["summary"].get("no_surface_fraction")
            ),
            "row spacing (m)": _row_spacing(crop, config),
            "row camera height (m)": rf.get("render_height_m"),
            "scale (m per unit)": rf.get("scale"),
            "scale source": (
                f"{rf.get('scale_source')}. WARNING: {rf['scale_warning']}"
                if rf.get("scale_warning")
                else rf.get("scale_source")
            ),
            "libraries (fit)": _libraries(upstream["aggregate"].get("environment")),
        }
        cons = (upstream.get("consistency") or {}).get("summary") or {}
        if cons.get("net") is not None:
            from cropcraft_core.surfaces.consistency import describe

            line = describe(cons["unreconstructed"], cons["extra"])
            warning = cons.get("warning")
            info[f"surfaces against {cons['views']} photos"] = (
                f"{line}. WARNING: {warning}" if warning else line
            )
        views = upstream["observe"]["summary"]
        if "views_pooled" in views:  # the observation pools several row cameras
            left = views["views_left_out"]
            pooled = f"{views['views_pooled']} of {views['views_pooled'] + len(left)}"
            if left:
                where = ", ".join(f"{dx:+.2f} m along, {dy:+.2f} m across" for dx, dy, _ in left)
                pooled += f" (left out, outside the reconstruction: {where})"
            info["row cameras pooled"] = pooled
        if "observe_rows" in upstream:
            listed = upstream["observe_rows"]["summary"]["rows"]
            info["neighbour rows fitted"] = (
                f"{sum(e['kept'] for e in listed)} of {len(listed)} tried (the others lie "
                "outside the reconstruction)"
            )
        table = store.get_json(key_of(upstream["rows"], "rows")) if "rows" in upstream else None
        info = {k: v for k, v in info.items() if v is not None}
        page = scene_report_html(
            scene,
            thumbnails=thumbs,
            observed_depth=np.where(obs.mask, obs.depth, np.nan),
            predicted_depth=predicted,
            preview_png=preview,
            metrics=metrics,
            fit=fit,
            timings=_timings(upstream),
            info=info,
            rows=table,
            warnings=(warnings := run_warnings(crop, upstream, fit)),
        )
        key = artefact(scene, "report", "report.html")
        digest = store.put_bytes(key, page.encode("utf-8"))
        # the same warnings as data, for the season's summary and closing lines
        listed = artefact(scene, "report", "warnings.json")
        listed_digest = store.put_json(listed, warnings)
    return make_record(
        "report",
        scene,
        {"report": key, "warnings": listed},
        {key: digest, listed: listed_digest},
        {"bytes": len(page)},
        t.seconds,
    )


def _row_spacing(crop: str, config: dict[str, Any]) -> str:
    """The planting row spacing the run fitted with, marked where it is the crop's default."""
    used = row_spacing_used(crop, config)
    return f"{used['m']:g}" + ("" if used["given"] else f" (the {crop} default)")


def run_warnings(crop: str, upstream: dict[str, Any], fit: dict[str, Any]) -> list[str]:
    """The warnings a run prints, for its report: too few photos, the rows against a
    camera-height hint, an answer on the parameter box's edge, the row view's coverage, the
    reconstruction against the photos (its net cover: printed, but left out of the page's
    list and so of the season's note; session 93's report audit) and the photos left out."""
    from cropcraft_core.fit.fitting import edge_warning
    from cropcraft_core.observe import coverage_warning
    from cropcraft_core.report import few_photos_warning, left_out_lines

    out = [few_photos_warning(upstream["ingest"]["summary"].get("n_images"))]
    out.append(upstream["rowfit"]["summary"].get("scale_warning"))
    out.append(edge_warning(crop, fit["params"], (fit.get("config") or {}).get("box")))
    seen = upstream["observe"]["summary"].get("no_surface_fraction")
    out.append(None if seen is None else coverage_warning(seen, crop))
    out.append(((upstream.get("consistency") or {}).get("summary") or {}).get("warning"))
    return [w for w in out if w] + left_out_lines(photos_left_out(upstream))
