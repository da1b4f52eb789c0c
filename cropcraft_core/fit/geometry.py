"""Fit any geometry that is already metric with z up: a LiDAR scan, another reconstruction, a
canopy from elsewhere (``cropcraft fit --geometry FILE.ply``).

geometry (mesh or point cloud) → coloured points → ground plane, rows and row camera
(``rowfit``) → the row observation rendered from the geometry itself (a mesh by the rasteriser,
a point cloud by a z-buffer splat) → the usual fit. Geometry without colours is coloured by
height (soil-brown within 3 cm of the ground level, leaf-green above) and, as a metric z-up
geometry stands on its lowest point, given a ground grid there for the plane fit (a bare canopy
mesh has no ground of its own; on a slope both follow the plane of its lowest points) — both
recorded in the observation's ``meta``. A geometry taller than its crop stands is refused
(not metres?).

Also the paper's Poisson baseline: Open3D Poisson reconstruction of the visible points,
background removed by height, every remaining face counted as leaf.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cropcraft_core.errors import ConfigError, InputError
from cropcraft_core.geometry import CanopyMesh, Organ, PinholeCamera
from cropcraft_core.observe import (
    NO_SURFACE_WARN,
    Observation,
    coverage_warning,
    observation_mask,
    observe_views,
    preset,
)
from cropcraft_core.render.raster import depth_map

SOIL_RGB = np.array([0.45, 0.33, 0.22])
LEAF_RGB = np.array([0.22, 0.50, 0.16])
GROUND_BAND_M = 0.03
#: Height percentile an uncoloured geometry's ground grid is laid at (its lowest points).
GROUND_PERCENTILE = 0.1
#: Colours whose channels differ by less than this everywhere (0-1) are grey: no colour.
GREY_CHROMA = 0.02
#: An uncoloured geometry with at least this share of its points within ``GROUND_BAND_M`` of
#: its highest points (the 99.9th height percentile), and ``FLIPPED_RATIO`` times the share
#: within it of its lowest, reads as z down: a flat soil on top (``orientation_warning``).
FLIPPED_SHARE = 0.2
FLIPPED_RATIO = 3.0


@dataclass
class Geometry:
    """A metric, z-up geometry in the world frame of its row fit."""

    mesh: CanopyMesh | None
    points: np.ndarray  # (n, 3)
    colors: np.ndarray  # (n, 3) in [0, 1]
    meta: dict


def sample_mesh(mesh: CanopyMesh, n: int, rng: np.random.Generator) -> np.ndarray:
    """(n, 3) points uniformly distributed over the mesh surface (area-weighted)."""
    areas = mesh.face_areas()
    if areas.sum() <= 0:
        raise InputError("mesh has no surface area to sample")
    face = rng.choice(len(areas), size=n, p=areas / areas.sum())
    r1, r2 = rng.random(n), rng.random(n)
    s = np.sqrt(r1)
    w = np.stack([1 - s, s * (1 - r2), s * r2], axis=1)
    return np.einsum("nk,nkd->nd", w, mesh.triangles()[face])


def load_geometry(path: str | Path, n_points: int = 200_000, seed: int = 0) -> Geometry:
    """Read ``path`` (PLY mesh or point cloud) into coloured points (see the module docstring)."""
    from cropcraft_core.export import read_geometry

    rng = np.random.default_rng(seed)
    g = read_geometry(path)
    meta: dict = {"source": str(path)}
    if isinstance(g, CanopyMesh):
        if g.n_faces == 0:
            raise InputError(f"{path}: mesh has no faces")
        if not np.all(np.isfinite(g.vertices)):  # before sampling: NaN areas are no weights
            raise InputError(f"{path}: geometry has non-finite coordinates")
        try:
            pts = sample_mesh(g, n_points, rng)
        except InputError as e:
            raise InputError(f"{path}: {e}") from None
        mesh, cols = g, None
        meta["kind"] = "mesh"
    else:
        mesh, pts = None, np.asarray(g.points, dtype=np.float64)
        cols = None if g.colors is None else np.asarray(g.colors, dtype=np.float64)
        meta["kind"] = "points"
        finite = np.isfinite(pts).all(1)
        if not finite.all():  # an organised scan's empty returns: not points of the canopy
            meta["dropped_non_finite"] = int((~finite).sum())
            pts = pts[finite]
            cols = None if cols is None else cols[finite]
        if len(pts) < 100:
            raise InputError(f"{path}: only {len(pts)} points; a point cloud needs at least 100")
        if cols is not None and float(np.ptp(cols, axis=1).max(initial=0.0)) < GREY_CHROMA:
            # grey or black everywhere: a scanner's intensity, or zeros for no colour
            meta["colours_ignored"] = "grey (no hue): read as no colours"
            cols = None
    if cols is None:
        # No colours (a bare mesh, an uncoloured scan): colour by height, and since a metric
        # z-up geometry stands on its lowest points, add a ground grid there for the plane fit
        # (harmless where a scanned ground exists: it lies in the same plane). Its level is
        # the 0.1th percentile, not the minimum: one stray return below the soil moved the
        # whole ground (0.4 m under: the canopy read 0.96 m tall for 0.58).
        # On a slope (or from a scanner not levelled) the lowest points lie on a tilted
        # plane: heights are taken above it, and the grid laid on it (a flat grid at the
        # lowest point coloured most of a 5° slope's soil as leaves: LAI +51-64 %, session
        # 92's geometry audit); the row fit's ground plane then levels the scene, as it
        # levels a coloured one.
        slope, tilt = _lowest_surface(pts)
        height = pts[:, 2] - pts[:, :2] @ slope
        ground_z = float(np.percentile(height, GROUND_PERCENTILE))
        warning = _flipped(height, ground_z)
        if warning:
            meta["orientation_warning"] = warning
        lo, hi = pts[:, :2].min(0), pts[:, :2].max(0)
        n_g = max(int(0.3 * len(pts)), 1000)
        gxy = np.column_stack([rng.uniform(lo[0], hi[0], n_g), rng.uniform(lo[1], hi[1], n_g)])
        grid = np.column_stack([gxy, ground_z + gxy @ slope])
        pts = np.concatenate([pts, grid])
        above = pts[:, 2] - pts[:, :2] @ slope
        cols = np.where((above < ground_z + GROUND_BAND_M)[:, None], SOIL_RGB, LEAF_RGB)
        meta["colours"] = "by height"
        meta["ground"] = (
            f"ground grid added at the lowest points, z = {ground_z:.3f} m"
            if tilt is None
            else f"ground grid added on the lowest points' plane, tilted {tilt:.1f} degrees "
            f"(z = {ground_z:.3f} m + {slope[0]:.4f} x + {slope[1]:.4f} y)"
        )
    return Geometry(mesh, pts, cols, meta)


#: The lowest surface of an uncoloured geometry is taken as tilted from this many degrees,
#: where its plane fits the lowest points within ``TILT_FIT_M`` (RMS): a level canopy mesh
#: reads 0.0-0.4 degrees (its stems' feet and lowest leaves), a 5 degree slope 5.0.
TILT_MIN_DEG = 1.0
TILT_FIT_M = 0.02


def _lowest_surface(pts: np.ndarray, cell_m: float = 0.1) -> tuple[np.ndarray, float | None]:
    """``(slope, degrees)``: the plane ``z = slope · (x, y) + c`` under ``pts``, fitted to the
    lowest point of each ``cell_m`` cell, keeping the lower half of them at each pass (while
    at least 30 and a tenth remain); ``(0, 0), None`` where it tilts less than
    :data:`TILT_MIN_DEG` or does not fit the lowest points within :data:`TILT_FIT_M`."""
    flat = (np.zeros(2), None)
    ij = np.floor((pts[:, :2] - pts[:, :2].min(0)) / cell_m).astype(np.int64)
    cell = ij[:, 0] * (int(ij[:, 1].max()) + 1) + ij[:, 1]
    order = np.lexsort((pts[:, 2], cell))
    first = np.r_[True, cell[order][1:] != cell[order][:-1]]
    low = pts[order][first]
    if len(low) < 30:
        return flat
    a = np.column_stack([low[:, :2], np.ones(len(low))])
    keep = np.ones(len(low), bool)
    for _ in range(8):
        coef = np.linalg.lstsq(a[keep], low[keep, 2], rcond=None)[0]
        r = low[:, 2] - a @ coef
        lower = r <= np.median(r[keep])
        if lower.sum() < max(30, 0.1 * len(low)):
            break
        keep = lower
    fit = float(np.sqrt(np.mean((low[keep, 2] - a[keep] @ coef) ** 2)))
    degrees = float(np.degrees(np.arctan(np.hypot(coef[0], coef[1]))))
    if degrees < TILT_MIN_DEG or fit > TILT_FIT_M:
        return flat
    return coef[:2], degrees


def _flipped(z: np.ndarray, ground_z: float) -> str | None:
    """A warning where heights ``z`` look upside down: their densest flat layer (a scanned
    soil) at the top rather than at the bottom, where ``ground_z`` lays the ground grid. The
    grid would then lie on the canopy's tops and the soil read as a leaf layer below them."""
    top_z = float(np.percentile(z, 100.0 - GROUND_PERCENTILE))
    top = float(np.mean(z > top_z - GROUND_BAND_M))
    bottom = float(np.mean(z < ground_z + GROUND_BAND_M))
    if top < FLIPPED_SHARE or top < FLIPPED_RATIO * bottom:
        return None
    return (
        f"{100 * top:.0f} % of the points lie within {100 * GROUND_BAND_M:.0f} cm of the "
        f"highest ones, {100 * bottom:.0f} % of the lowest: a flat layer on top, as of a soil "
        "seen from below. Is the geometry z down? It is read as z up, standing on its lowest "
        "points (if so, turn it 180 degrees about the x axis: y and z negated)"
    )


#: A splatted point's radius, in multiples of the distance to its nearest neighbour in pixels
#: at its depth (:func:`splat_radius`). One soybean canopy's clouds of 52k, 520k and 5.2M
#: points (6.6, 1.9 and 0.6 px apart) then cover 62 %, 61 % and 69 % of the row view, its mesh
#: 65 %; a fixed 2 px radius covered 6 %, 37 % and 69 %, and the sparse cloud fitted a canopy
#: of two nodes.
SPLAT_SPACINGS = 1.8
#: Points further apart than this in the row view (pixels) are a sparse cloud: it is splatted
#: wide to close the gaps, which blurs the leaves, and the observation's meta says so.
SPARSE_SPACING_PX = 3.0


def splat_radius(points: np.ndarray, camera: PinholeCamera, seed: int = 0) -> tuple[int, float]:
    """``(radius in pixels, median nearest-neighbour spacing in pixels)`` for splatting
    ``points`` (world frame) into ``camera``: :data:`SPLAT_SPACINGS` times the points'
    spacing where the camera sees them (a sample of 20,000 asked of every point in view),
    among distinct points (exact duplicates, as from two passes or overlapping tiles
    concatenated, read a spacing of 0 and splatted the cloud 1 px wide)."""
    from scipy.spatial import cKDTree

    ok, _, z = _seen(points, camera)
    seen, depth = points[ok], z[ok]
    _, first = np.unique(seen, axis=0, return_index=True)
    if len(first) < len(seen):  # a cloud merged with itself: its spacing is not zero
        keep = np.sort(first)  # in the cloud's order, as without duplicates
        seen, depth = seen[keep], depth[keep]
    if len(seen) < 2:
        return 2, float("nan")
    pick = np.random.default_rng(seed).choice(len(seen), min(len(seen), 20_000), replace=False)
    dist, _ = cKDTree(seen).query(seen[pick], k=2)
    spacing = float(np.median(dist[:, 1] * camera.fx / depth[pick]))
    return max(1, int(np.ceil(SPLAT_SPACINGS * spacing))), spacing


def _seen(points: np.ndarray, camera: PinholeCamera) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(mask, uv, z)``: which ``points`` project into ``camera``'s image in front of it, and
    every point's pixel coordinates and z-depth."""
    uv, z = camera.project(points)
    with np.errstate(invalid="ignore"):
        ok = (
            np.isfinite(uv).all(1)
            & (z > 0)
            & (uv[:, 0] >= 0)
            & (uv[:, 0] < camera.width)
            & (uv[:, 1] >= 0)
            & (uv[:, 1] < camera.height)
        )
    return ok, uv, z


def splat_depth(points: np.ndarray, camera: PinholeCamera, radius_px: int = 2) -> np.ndarray:
    """(H, W) float32 z-depth of a point cloud: nearest point per pixel, holes closed by a
    ``radius_px`` minimum filter (points are surfels about that many pixels wide)."""
    import cv2

    ok, uv, z = _seen(points, camera)
    u = np.floor(uv[ok, 0]).astype(np.int64)
    v = np.floor(uv[ok, 1]).astype(np.int64)
    flat = np.full(camera.width * camera.height, np.inf, np.float32)
    np.minimum.at(flat, v * camera.width + u, z[ok].astype(np.float32))
    img = flat.reshape(camera.height, camera.width)
    if radius_px > 0:
        k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius_px + 1, 2 * radius_px + 1))
        img = cv2.erode(img, k)
    img[~np.isfinite(img)] = np.nan
    return img


def observe_geometry(
    source: str | Path | Geometry,
    crop: str,
    n_points: int = 200_000,
    seed: int = 0,
    row_spacing: float | None = None,
    preset_overrides: dict | None = None,
) -> tuple[Observation, object]:
    """Row-fit ``source`` (a path, or a :class:`Geometry` already loaded) and render its
    observation (the crop's preset with ``preset_overrides``, e.g. pooled row cameras:
    :func:`_observe`). Returns (observation, row fit)."""
    from cropcraft_core.rowfit import fit_ground_and_rows
    from cropcraft_core.rowfit import preset as rowfit_preset

    geo = source if isinstance(source, Geometry) else load_geometry(source, n_points, seed)
    _check_height(geo, crop)
    # the paper's scene boxes are in NeRF units; a metric geometry is used whole
    rp = rowfit_preset(crop, box_center=None, box_size=None, row_spacing=row_spacing)
    rowfit = fit_ground_and_rows(geo.points, geo.colors, crop, preset=rp, rng=seed)
    from cropcraft_core.config import default_layout

    spacing = _spacing_check(rowfit, row_spacing or default_layout(crop).row_spacing)
    obs = _observe(geo, rowfit, crop, rowfit.camera, preset_overrides, row_spacing, **spacing)
    return obs, rowfit


#: The tallest a geometry of each crop stands (metres, from its lowest points, the 0.1th height
#: percentile, to its 99.5th): the model's tallest canopies stand 1.85 m (soybean) and 3.2 m
#: (maize), with room for a plot's slope. A geometry in centimetres fitted for 93 s and then
#: failed blaming --plot and --density, one in millimetres as "no rows found" (session 92's
#: geometry audit).
MAX_STANDING_M = {"soybean": 3.0, "maize": 6.0}


#: The tallest canopy the procedural model builds (metres; see :data:`MAX_STANDING_M`). An
#: uncoloured geometry standing over ``TALLEST_MARGIN`` times this is named as maybe not z up:
#: an uncoloured soybean cloud exported y up (its plot's width read as its height, 2.25 m)
#: fitted LAI 6.8 for 1.26, with only a warning that LAI was "likely underestimated" (session
#: 92's geometry audit). A coloured one is levelled by its soil's colour.
MODEL_TALLEST_M = {"soybean": 1.85, "maize": 3.2}
TALLEST_MARGIN = 1.1


def _check_height(geo: Geometry, crop: str) -> None:
    """InputError where ``geo`` stands taller than :data:`MAX_STANDING_M` allows its crop:
    not metres, not z up, or something tall in the scan. An uncoloured geometry taller than
    the model's tallest canopy of the crop (:data:`MODEL_TALLEST_M`) but within that is
    warned of (``orientation_warning``): its heights are all it is read by."""
    z = geo.points[:, 2]
    low, high = np.percentile(z, [GROUND_PERCENTILE, 99.5])
    tall, most = float(high - low), MAX_STANDING_M.get(crop)
    if most is None or tall <= most:
        model = MODEL_TALLEST_M.get(crop)
        if geo.meta.get("colours") == "by height" and model and tall > TALLEST_MARGIN * model:
            said = geo.meta.get("orientation_warning")
            geo.meta["orientation_warning"] = (f"{said}. " if said else "") + (
                f"It stands {tall:.3g} m tall, taller than the {model:g} m of the model's "
                f"tallest {crop} canopy: is the geometry z up? It is read as z up, standing on "
                "its lowest points, so a y-up export (many tools write one) is read on its side "
                "(if so, turn it: (x, y, z) -> (x, -z, y))"
            )
        return
    other = " (or is it maize?)" if crop == "soybean" and tall <= MAX_STANDING_M["maize"] else ""
    raise InputError(
        f"{geo.meta.get('source', 'the geometry')}: it stands {tall:,.4g} units tall (from its "
        f"lowest points to its 99.5th height percentile), more than the {most:g} m a {crop} "
        f"canopy can{other}: is it in metres, and z up? In centimetres it would stand "
        f"{tall / 100:.3g} m, in millimetres {tall / 1000:.3g} m: scale it to metres (or "
        "turn it z up, or crop a tall object out of it) first"
    )


#: A geometry's measured row spacing this far (relative) from the layout's is named: its units
#: or the layout are off (a cloud in feet fitted silently to LAI 0.44 for 1.26).
SPACING_TOLERANCE = 0.15


def _spacing_check(rowfit, expected: float) -> dict:
    """``{"row_spacing_measured_m": ..., "spacing_warning": ...}``: the rows' period near
    ``expected`` (the row fit's own window, 0.6-1.6 times it); where none lies within
    :data:`SPACING_TOLERANCE` of it, the period over a wide window (0.3-4 times), named when
    that is off too. (The wide window alone picks a multiple of the true period on a small
    plot: 2.29 m for rows 0.76 m apart.) Where the rows show no period (one row), a warning
    that the layout's spacing is assumed."""
    from cropcraft_core.rowfit.fit import estimate_scale_from_rows

    def measured(search=(0.6, 1.6)) -> float | None:
        est = estimate_scale_from_rows(rowfit, expected, search=search)
        ok = est.spacing is not None and est.method != "fallback_unchanged"
        return float(est.spacing) if ok else None

    def off(spacing: float | None) -> bool:
        return spacing is not None and abs(spacing / expected - 1) > SPACING_TOLERANCE

    near = measured()
    if near is not None and not off(near):
        return {"row_spacing_measured_m": round(near, 4)}
    wide = measured((0.3, 4.0))
    if wide is None:  # one row (session 92's audit: LAI +58 % with no word) or no regular rows
        what = "one row" if rowfit.parallel_rows() <= 1 else "no regular rows"
        return {
            "spacing_warning": (
                f"the geometry shows {what}, so the row spacing could not be measured: the "
                f"fit's canopy has rows the layout's {expected:.3g} m apart, beside this one "
                "too; if its rows are otherwise, give --row-spacing (a row standing alone is "
                "not the canopy the model builds)"
            )
        }
    out = {"row_spacing_measured_m": round(wide, 4)}
    if off(wide):
        out["spacing_warning"] = (
            f"the rows are {wide:.3g} m apart, the layout's row spacing is {expected:.3g} "
            f"m: is the geometry in metres (a scale of {expected / wide:.3g} would make "
            "it so)? If the rows really are that far apart, give --row-spacing"
        )
    return out


def _depth(geo: Geometry, rowfit, cam: PinholeCamera, radius_px: int = 2) -> np.ndarray:
    """(H, W) depth of ``geo`` (in ``rowfit``'s scene frame) from the world camera ``cam``, NaN
    where it sees nothing (a point cloud splatted ``radius_px`` wide)."""
    m = rowfit.world_from_scene
    if geo.mesh is not None:
        v = geo.mesh.vertices @ m[:3, :3].T + m[:3, 3]
        return depth_map(v, geo.mesh.faces, cam)
    return splat_depth(geo.points @ m[:3, :3].T + m[:3, 3], cam, radius_px)


def _observe(
    geo: Geometry,
    rowfit,
    crop: str,
    cam: PinholeCamera,
    preset_overrides: dict | None = None,
    row_spacing: float | None = None,
    **meta,
) -> Observation:
    """The observation of ``geo`` (in ``rowfit``'s scene frame) from the world camera ``cam``,
    under the crop's preset with ``preset_overrides``. Where that pools several row cameras
    (``views_along``, ``views_across``; neighbouring rows ``row_spacing`` apart, by default the
    crop's), a view whose ground lies beyond the geometry over more than 18 % and more than the
    row camera's own (:func:`outside_fraction`) is left out of the pool
    (:func:`~cropcraft_core.observe.observe_views`)."""
    p = preset(crop, **{"render_height": float(rowfit.render_height), **(preset_overrides or {})})
    radius = 2
    if geo.mesh is None:  # a point cloud: splatted as wide as its points lie apart
        m = rowfit.world_from_scene
        radius, spacing = splat_radius(geo.points @ m[:3, :3].T + m[:3, 3], cam)
        meta["splat"] = {"radius_px": radius, "point_spacing_px": round(spacing, 2)}
        if spacing > SPARSE_SPACING_PX:
            meta["splat"]["warning"] = (
                f"sparse point cloud: its points lie {spacing:.1f} px apart in the row view, "
                f"splatted {radius} px wide, which blurs the leaves; a denser cloud or a mesh "
                "fits better"
            )

    # the geometry's ground may end inside the row view (an edge row, a small plot): the fit
    # reads the empty ground beyond it as gaps, as the scene flow's coverage check warns
    outside = outside_fraction(geo, rowfit, cam)
    meta["outside_fraction"] = round(outside, 4)
    if coverage_warning(outside):
        meta["coverage_warning"] = (
            f"{100 * outside:.0f} % of the row camera's view lies beyond the geometry "
            f"(over {100 * NO_SURFACE_WARN:.0f} %): the fit reads it as gaps, so LAI is "
            "likely underestimated; a geometry reaching further around the fitted row helps"
        )

    def view(dx: float, dy: float):
        c = cam.shifted(dx, dy)
        depth = _depth(geo, rowfit, c, radius)
        return c, depth, observation_mask(depth, None, c, p), None

    if p.n_views > 1:
        from cropcraft_core.config import default_layout

        row_spacing = row_spacing or default_layout(crop).row_spacing
    meta = {
        **geo.meta,
        "rowfit": {
            "rows": len(rowfit.rows),
            "dense": bool(rowfit.dense),
            "render_height_m": float(rowfit.render_height),
            "scale_source": rowfit.scale_source,
        },
        **meta,
    }
    return observe_views(
        crop,
        p,
        view,
        row_spacing,
        meta=meta,
        coverage=lambda dx, dy: outside_fraction(geo, rowfit, cam.shifted(dx, dy)),
    )


def geometry_warnings(meta: dict) -> list[str]:
    """The warnings an observation of a geometry carries in its ``meta`` (an uncoloured
    geometry that looks z down, rows not the layout's spacing apart, a sparse point cloud, a row
    view reaching beyond the geometry), for
    ``cropcraft fit`` to print."""
    said = (
        meta.get("orientation_warning"),
        meta.get("spacing_warning"),
        (meta.get("splat") or {}).get("warning"),
        meta.get("coverage_warning"),
    )
    return [w for w in said if w]


def outside_fraction(geo: Geometry, rowfit, cam: PinholeCamera, cell_m: float = 0.1) -> float:
    """The share of ``cam``'s view whose ground (z = 0 of ``rowfit``'s world frame) lies beyond
    the geometry: where no point of ``geo`` falls within a cell of the ``cell_m`` grid (or its
    8 neighbours). Gaps between leaves down to a bare ground count as inside, unlike a depth
    map's empty pixels (a leaves-only mesh has nothing under them)."""
    import cv2

    m = rowfit.world_from_scene
    xy = (geo.points @ m[:3, :3].T + m[:3, 3])[:, :2]
    lo = xy.min(0)
    ij = np.floor((xy - lo) / cell_m).astype(np.int64)
    shape = tuple(ij.max(0) + 1)
    grid = np.zeros(shape, np.uint8)
    grid[ij[:, 0], ij[:, 1]] = 1
    grid = cv2.dilate(grid, np.ones((3, 3), np.uint8)).astype(bool)
    d = cam.scaled(1 / 16).ray_directions(normalized=False).reshape(-1, 3)
    c = cam.center
    down = d[:, 2] < 0
    t = -c[2] / np.where(down, d[:, 2], -1.0)
    q = np.floor((c[:2] + d[:, :2] * t[:, None] - lo) / cell_m).astype(np.int64)
    inside = down & np.all((q >= 0) & (q < np.array(shape)), axis=1)
    seen = np.zeros(len(q), bool)
    seen[inside] = grid[q[inside, 0], q[inside, 1]]
    return float(1.0 - seen.mean())


def neighbour_observations(
    geo: Geometry,
    crop: str,
    rowfit,
    row_spacing: float,
    neighbours: int,
    max_no_surface: float = NO_SURFACE_WARN,
    preset_overrides: dict | None = None,
) -> tuple[dict[int, Observation], list[dict]]:
    """Observations of ``geo`` over the best row's neighbours (``rowfit`` from
    :func:`observe_geometry`; ``cropcraft_core.rowfit.neighbours``): ``({index: observation},
    tried)``, a neighbour left out where more than ``max_no_surface`` of its view's ground
    lies beyond the geometry (:func:`outside_fraction`); ``tried`` lists every one
    considered. The cameras sit k row spacings from the best row's (no snapping onto fitted
    rows: :func:`~cropcraft_core.rowfit.neighbour_row_views`); each is observed as the best
    row is (``preset_overrides``)."""
    from cropcraft_core.rowfit import neighbour_row_views

    kept: dict[int, Observation] = {}
    tried = []
    for view in neighbour_row_views(rowfit.camera, rowfit.rows, row_spacing, neighbours):
        unseen = outside_fraction(geo, rowfit, view.camera)
        ok = bool(unseen <= max_no_surface)
        tried.append({**view.to_dict(), "outside_fraction": unseen, "kept": ok})
        if ok:
            kept[view.index] = _observe(
                geo, rowfit, crop, view.camera, preset_overrides, row_spacing, row=view.to_dict()
            )
    return kept, tried


#: The paper's Poisson baseline (supplementary, *Baseline Implementation Details*): nerfstudio's
#: ``ns-export poisson`` on 100K points (Open3D's Poisson at depth 9, the vertices of the lowest
#: 10 % density removed), its mesh at 50K faces; soybean in the method's box (here the points'
#: own footprint), maize in a 4 m × 4 m column; faces lower than the points' 1st height
#: percentile + 0.2 m (maize 0.1 m) removed, every other face a leaf.
POISSON_POINTS = 100_000
POISSON_FACES = 50_000
POISSON_DEPTH = 9
POISSON_MAIZE_COLUMN_M = 4.0


def poisson_region(points: np.ndarray, crop: str) -> tuple[np.ndarray, np.ndarray]:
    """``(lo, hi)`` xy corners of the baseline's box: the points' footprint, for maize within a
    4 m × 4 m column about its centre."""
    lo, hi = points[:, :2].min(0), points[:, :2].max(0)
    if crop == "maize":
        mid, half = 0.5 * (lo + hi), 0.5 * POISSON_MAIZE_COLUMN_M
        lo, hi = np.maximum(lo, mid - half), np.minimum(hi, mid + half)
    return lo, hi


def poisson_baseline(
    points: np.ndarray,
    crop: str,
    depth: int = POISSON_DEPTH,
    *,
    n_points: int = POISSON_POINTS,
    n_faces: int = POISSON_FACES,
    seed: int = 0,
) -> CanopyMesh:
    """The paper's Poisson baseline on metric z-up points (:data:`POISSON_POINTS` and the
    constants beside it): ``n_points`` of them drawn (``seed``), Open3D's Poisson surface at
    ``depth`` without its lowest-density tenth, at most ``n_faces`` faces (quadric
    decimation), the faces in :func:`poisson_region` above the height cut kept, all leaves."""
    import open3d as o3d

    cut = np.percentile(points[:, 2], 1.0) + (0.2 if crop == "soybean" else 0.1)
    lo, hi = poisson_region(points, crop)
    if len(points) > n_points:
        points = points[np.random.default_rng(seed).choice(len(points), n_points, replace=False)]
    # about the points' centre: Open3D's octree and normals in float32-like precision lost
    # the leaves of georeferenced points (409k faces at the origin, 55k at UTM coordinates)
    centre = points.mean(0)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points - centre))
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=0.05, max_nn=30))
    pcd.orient_normals_to_align_with_direction(np.array([0.0, 0.0, 1.0]))
    mesh, density = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(pcd, depth=depth)
    density = np.asarray(density)
    mesh.remove_vertices_by_mask(density < np.quantile(density, 0.1))
    if len(mesh.triangles) > n_faces:
        mesh = mesh.simplify_quadric_decimation(target_number_of_triangles=n_faces)
    v = np.asarray(mesh.vertices) + centre
    f = np.asarray(mesh.triangles, dtype=np.int32)
    c = v[f].mean(1) if len(f) else np.zeros((0, 3))
    keep = (c[:, 2] > cut) & np.all((c[:, :2] >= lo) & (c[:, :2] <= hi), axis=1)
    f = f[keep]
    n = len(f)
    out = CanopyMesh(
        v, f, np.full(n, int(Organ.LEAF), np.uint8), np.zeros(n, np.int32), np.zeros(n, np.int32)
    )
    return out.select(out.face_areas() > 0)


def compare_image(observed: np.ndarray, predicted: np.ndarray, vmax: float) -> np.ndarray:
    """(H, 2W + 8, 3) uint8: observed and predicted depth side by side on one colour scale, the
    observed depths' range (as the report's; 0 to ``vmax`` where it has none): over 0 to the
    render height a maize canopy 3.8-4.9 m under its 5 m camera took one colour. The range
    is written under the panels' labels."""
    from cropcraft_core.render.preview import depth_to_rgb

    seen = np.asarray(observed, np.float64)
    seen = seen[np.isfinite(seen)]
    lo, hi = (float(seen.min()), float(seen.max())) if seen.size else (0.0, float(vmax))
    if not hi > lo:
        lo, hi = 0.0, float(vmax)
    a = depth_to_rgb(observed, lo, hi)
    b = depth_to_rgb(predicted, lo, hi)
    gap = np.full((a.shape[0], 8, 3), 255, np.uint8)
    img = np.concatenate([a, gap, b], axis=1)
    from PIL import Image, ImageDraw

    pil = Image.fromarray(img)
    draw = ImageDraw.Draw(pil)
    scale = f"depth {lo:.2f} m (blue, near) to {hi:.2f} m (red, far)"
    for x, label in ((10, "observed depth"), (a.shape[1] + 18, "predicted depth (fitted model)")):
        for y, text in ((10, label), (30, scale)):
            draw.rectangle([x - 4, y - 4, x + 7 * len(text), y + 16], fill=(255, 255, 255))
            draw.text((x, y), text, fill=(0, 0, 0))
    return np.asarray(pil)


def fit_geometry(
    path: str | Path,
    crop: str,
    out_dir: str | Path,
    config=None,
    layout=None,
    seed: int = 0,
    neighbours: int = 0,
    row_answer: str = "best",
    executor=None,
    preset_overrides: dict | None = None,
) -> dict:
    """``cropcraft fit``: row-fit and observe ``path``, fit (or Poisson-reconstruct) it and
    write the bundle plus ``compare.png`` and ``fit.json`` into ``out_dir``; where the answer is
    one fit's seeds, ``metrics.json`` also holds their traits (``seeds``,
    :func:`cropcraft_core.metrics.seeds.seed_traits`). ``neighbours``:
    also fit up to that many rows on each side of the best row that the geometry covers
    (:func:`neighbour_observations`), each alone, and write their answers side by side with
    their spread as ``rows.json`` (``cropcraft_core.metrics.rows.compare_rows``); the bundle
    is then ``row_answer``'s (``rows_answer``: the best row's, or the rows' mean), and
    ``fit.json`` keeps the best row's own fit as ``best_row_fit``. ``executor``: where the
    seeds run (:func:`~cropcraft_core.fit.fitting.fit_observation`), every row's at once
    (:func:`~cropcraft_core.fit.fitting.fit_observations`). ``preset_overrides``: the
    observation preset's (e.g. ``views_along``/``views_across`` pool row cameras)."""
    import json

    from cropcraft_core.bundle import check_output_dir, write_bundle
    from cropcraft_core.config import default_layout
    from cropcraft_core.export import atomic_write_text
    from cropcraft_core.fit.fitting import (
        FitConfig,
        edge_warning,
        fit_observation,
        fit_observations,
    )
    from cropcraft_core.fit.forward import ForwardModel
    from cropcraft_core.procedural import generate_canopy
    from cropcraft_core.render.preview import save_png

    out = check_output_dir(out_dir)
    layout = layout or default_layout(crop)
    cfg = config or FitConfig()
    if cfg.method == "poisson":
        if neighbours:
            raise ConfigError("neighbour rows are fitted by the model fits, not by poisson")
        return _poisson_to_files(path, crop, out, seed)
    geo = load_geometry(path, seed=seed)
    obs, rowfit = observe_geometry(
        geo, crop, seed=seed, row_spacing=layout.row_spacing, preset_overrides=preset_overrides
    )
    if not neighbours:
        res = fit_observation(obs, cfg, layout=layout, executor=executor)
        answer = res.to_dict()
    else:
        from cropcraft_core.metrics.rows import compare_rows, rows_answer

        others, tried = neighbour_observations(
            geo, crop, rowfit, layout.row_spacing, neighbours, preset_overrides=preset_overrides
        )
        # the rows' seeds share the executor: the best row's answer is the one it gets alone
        res, *rest = fit_observations([obs, *others.values()], cfg, layout, executor)
        fits = {0: res.to_dict()}  # every row's fit.json, by row index
        fits.update({k: r.to_dict() for k, r in zip(others, rest, strict=True)})
        offsets = {0: 0.0, **{t["index"]: t["offset_m"] for t in tried}}
        answers = [
            {
                "index": k,
                "offset_m": offsets[k],
                "params": f["params"],
                "params_std": f["params_std"],
            }
            for k, f in fits.items()
        ]
        answer = rows_answer(fits, row_answer)
        table = {**compare_rows(crop, answers, layout, seed), "tried": tried}
        table.update(answer=row_answer, answer_params=answer["params"])
    canopy = generate_canopy(crop, answer["params"], layout, seed=seed)
    from cropcraft_core.metrics.seeds import answer_seeds, seed_metrics, seed_traits

    seeds = answer_seeds(answer)
    more = None if seeds is None else seed_metrics(seed_traits(crop, seeds, layout, seed))
    metrics = write_bundle(
        canopy, out, extra={"fit": answer, "observation": obs.meta}, more_metrics=more
    )
    predicted = ForwardModel(obs, layout).depth(answer["params"], seed)
    # the observation's canopy only, as the report's: its soil coloured as far canopy beside a
    # prediction without soil, and stretched the scale (session 93's report audit)
    observed = np.where(obs.mask, obs.depth, np.nan)
    save_png(
        out / "compare.png", compare_image(observed, predicted, float(obs.preset.render_height))
    )
    record = {"fit": answer, "rowfit": rowfit.to_dict(), "observation": obs.meta}
    edge = edge_warning(crop, answer["params"], (answer.get("config") or {}).get("box"))
    if edge:
        record["edge_warning"] = edge
    if neighbours:
        record["best_row_fit"] = res.to_dict()
    atomic_write_text(out / "fit.json", json.dumps(record, indent=2, default=float) + "\n")
    if neighbours:
        atomic_write_text(out / "rows.json", json.dumps(table, indent=2, default=float) + "\n")
    from cropcraft_core.bundle import BUNDLE_FILES

    written = (*BUNDLE_FILES, "compare.png", "fit.json", *(["rows.json"] if neighbours else []))
    _drop_stale(out, written)
    return metrics


def _poisson_to_files(path, crop: str, out: Path, seed: int) -> dict:
    import json

    from cropcraft_core.export import atomic_write_text, write_ply
    from cropcraft_core.metrics import leaf_angle_histogram, leaf_inclinations, weighted_angle_stats

    geo = load_geometry(path, seed=seed)
    mesh = poisson_baseline(geo.points, crop, seed=seed)
    lo, hi = poisson_region(geo.points, crop)
    ground = float(np.prod(hi - lo))
    theta, w = leaf_inclinations(mesh)
    mean, sd = weighted_angle_stats(theta, w)
    hist, edges = leaf_angle_histogram(theta, w)
    area = float(w.sum())
    metrics = {
        "method": "poisson",
        "lai": area / ground,
        "leaf_area_m2": area,
        "ground_area_m2": ground,
        "leaf_angle_mean_deg": float(np.degrees(mean)),
        "leaf_angle_std_deg": float(np.degrees(sd)),
        "leaf_angle_hist": [float(h) for h in hist],
        "leaf_angle_hist_edges_deg": [float(e) for e in edges],
        "n_faces": int(mesh.n_faces),
        "definitions": {
            "lai": {
                "unit": "m2/m2",
                "method": "Poisson surface area above the height cut / "
                "area of its xy box: the points' footprint (maize: within a 4 m x 4 m "
                "column) (paper's Poisson baseline)",
            },
        },
    }
    write_ply(out / "canopy.ply", mesh)
    atomic_write_text(out / "metrics.json", json.dumps(metrics, indent=2) + "\n")
    _drop_stale(out, ("canopy.ply", "metrics.json"))
    return metrics


#: The files ``cropcraft fit`` writes beside the bundle's (``bundle.BUNDLE_FILES``).
FIT_FILES = ("compare.png", "fit.json", "rows.json")


def _drop_stale(out: Path, written: tuple[str, ...]) -> None:
    """Remove the fit files an earlier run left in ``out`` that this one did not write (a
    Poisson run after a model fit kept its params.json and compare.png; a run without
    neighbour rows an earlier rows.json), so the folder holds one fit's files."""
    from cropcraft_core.bundle import BUNDLE_FILES

    for name in {*BUNDLE_FILES, *FIT_FILES} - set(written):
        (out / name).unlink(missing_ok=True)
