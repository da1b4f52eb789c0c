"""Images for people: shaded canopy views, colour-mapped depth maps, a 3/4 view camera, PNG files.

Nothing here feeds the fit; it favours looks over speed (a shaded 994 × 738 view with shadows takes
a few tenths of a second).
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np

from cropcraft_core.errors import ConfigError, GeometryError, InputError, OutputError
from cropcraft_core.export.atomic import atomic_path
from cropcraft_core.geometry.camera import ROW_CAMERA_SIZE, ROW_CAMERA_VFOV_DEG, PinholeCamera
from cropcraft_core.geometry.mesh import CanopyMesh, Organ
from cropcraft_core.render.raster import render_depth

#: Base colours per organ, sRGB 0–255.
ORGAN_RGB = {
    Organ.LEAF: (62, 128, 44),
    Organ.PETIOLE: (120, 170, 76),
    Organ.STEM: (160, 165, 70),
}
UNKNOWN_RGB = (200, 0, 200)  # a face whose label is no organ's: shown, not passed off as one
SOIL_RGB = (118, 84, 58)
SKY_HORIZON_RGB = (206, 222, 238)
SKY_ZENITH_RGB = (118, 162, 218)
BACKGROUND_RGB = (128, 128, 128)


def hash01(keys: np.ndarray, seed: int) -> np.ndarray:
    """Deterministic pseudo-random numbers in [0, 1), one per integer key (splitmix64): a
    texture or tint that depends only on what it colours, not on draw order."""
    with np.errstate(over="ignore"):
        x = keys.astype(np.uint64) * np.uint64(0x9E3779B97F4A7C15) + np.uint64(seed % 2**63)
        x ^= x >> np.uint64(30)
        x *= np.uint64(0xBF58476D1CE4E5B9)
        x ^= x >> np.uint64(27)
        x *= np.uint64(0x94D049BB133111EB)
        x ^= x >> np.uint64(31)
    return (x >> np.uint64(11)).astype(np.float64) / float(2**53)


def _unit(v: object, name: str) -> np.ndarray:
    a = np.asarray(v, dtype=np.float64)
    if a.shape != (3,) or not np.all(np.isfinite(a)) or np.linalg.norm(a) == 0:
        raise ConfigError(f"{name} must be a finite non-zero 3-vector, got {v!r}")
    return a / np.linalg.norm(a)


def _soil_texture(x: np.ndarray, y: np.ndarray, seed: int) -> np.ndarray:
    """(k,) brightness factors around 1 for ground points (x, y): a faint 0.25 m checker (to read
    scale and perspective) plus 2 cm clods of random brightness."""
    checker = ((np.floor(x / 0.25) + np.floor(y / 0.25)) % 2) * 0.06 - 0.03
    cx = np.floor(x / 0.02).astype(np.int64)
    cy = np.floor(y / 0.02).astype(np.int64)
    clod = hash01(cx * 1_000_003 + cy, seed + 17) * 0.24 - 0.12
    return 1.0 + checker + clod


def shade_rgb(
    mesh: CanopyMesh,
    camera: PinholeCamera,
    sun_dir: tuple[float, float, float] = (0.35, -0.25, 1.0),
    ambient: float = 0.35,
    ground: bool = True,
    ground_z: float = 0.0,
    shadows: bool = True,
    plant_variation: float = 0.12,
    seed: int = 0,
    near: float = 0.01,
) -> np.ndarray:
    """(H, W, 3) uint8 shaded view of a canopy.

    Lambert + ambient shading of two-sided faces (``ambient`` in [0, 1] is the light that reaches
    faces turned away from or hidden from the sun); colours per organ (``ORGAN_RGB``: leaf green
    with a per-plant brightness/hue variation of relative size ``plant_variation``, lighter green
    petioles, yellow-green stems). ``sun_dir`` is the direction towards the sun (world frame, any
    length). Background rays that go down meet a brown, lightly textured soil plane at
    ``ground_z`` (if ``ground``); the rest show a sky gradient. ``shadows`` casts a shadow ray per
    lit pixel with Open3D. ``seed`` fixes the per-plant colours and the soil texture.
    """
    if not isinstance(mesh, CanopyMesh):
        raise GeometryError(f"shade_rgb needs a CanopyMesh, got {type(mesh).__name__}")
    if not 0.0 <= ambient <= 1.0:
        raise ConfigError(f"ambient must be in [0, 1], got {ambient}")
    sun = _unit(sun_dir, "sun_dir")
    h, w = camera.height, camera.width
    res = render_depth(mesh.vertices, mesh.faces, camera, near=near)
    hit = res.mask
    fid = res.face_id[hit]

    rays = camera.ray_directions(normalized=False)  # (H, W, 3), unit camera z
    origin = camera.center
    rgb = np.empty((h, w, 3))
    light = np.ones((h, w))

    # --- canopy: base colour per face, Lambert on the side facing the camera
    # the organs' colours, then magenta for a label no organ has (it was drawn as a stem)
    base = np.array([*(ORGAN_RGB[Organ(o)] for o in range(3)), UNKNOWN_RGB], dtype=np.float64)
    organ = mesh.organ[fid].astype(np.int64)
    organ = np.where((organ >= 0) & (organ <= 2), organ, 3)
    col = base[organ]
    plant = mesh.plant[fid].astype(np.int64)
    jitter = (hash01(plant, seed) - 0.5) * 2 * plant_variation
    hue = (hash01(plant, seed + 1) - 0.5) * 2 * plant_variation
    col *= (1.0 + jitter)[:, None]
    col[:, 0] *= 1.0 + 0.8 * hue  # shift between bluish and yellowish green
    col[:, 2] *= 1.0 - 0.8 * hue
    rgb[hit] = col
    normals = res.normals(mesh, toward_camera=True)[hit]
    lambert = np.clip(normals @ sun, 0.0, None)
    pts = origin + rays[hit] * res.depth[hit, None].astype(np.float64)

    # --- background: ground plane or sky
    bg = ~hit
    d_bg = rays[bg]
    down = d_bg[:, 2] < 0 if ground else np.zeros(len(d_bg), bool)
    t = np.where(down, (ground_z - origin[2]) / np.where(down, d_bg[:, 2], -1.0), 0.0)
    down &= t > 0
    gp = origin + d_bg[down] * t[down, None]
    bg_rgb = np.empty((len(d_bg), 3))
    soil = np.asarray(SOIL_RGB, float) * _soil_texture(gp[:, 0], gp[:, 1], seed)[:, None]
    bg_rgb[down] = soil
    up = d_bg[~down]
    elev = np.clip(up[:, 2] / np.linalg.norm(up, axis=1), 0.0, 1.0) ** 0.6
    bg_rgb[~down] = (1 - elev)[:, None] * np.asarray(SKY_HORIZON_RGB, float) + elev[
        :, None
    ] * np.asarray(SKY_ZENITH_RGB, float)
    rgb[bg] = bg_rgb

    # --- light: canopy Lambert, ground Lambert (normal +z); the sky is not lit
    light_hit = lambert.copy()
    g_light = np.full(len(gp), max(sun[2], 0.0))
    if shadows and mesh.n_faces:
        # Shadow rays towards the sun from lit canopy points (nudged off their face to the sunny
        # side) and from lit ground points; the scene is recentred on the camera (float32).
        lit = np.flatnonzero(lambert > 0)
        g_lit = np.flatnonzero(g_light > 0)
        n_sun = np.where((normals[lit] @ sun)[:, None] >= 0, normals[lit], -normals[lit])
        o_all = np.concatenate(
            [pts[lit] + 1e-4 * n_sun - origin, gp[g_lit] + [0.0, 0.0, 1e-4] - origin]
        )
        if len(o_all):
            # Open3D only here: the rest of the package (the z-buffer) imports without it
            from cropcraft_core.render.raycast import build_scene, cast_rays

            scene = build_scene(mesh.vertices - origin, mesh.faces)
            blocked = np.isfinite(cast_rays(scene, o_all, sun)[0])
            light_hit[lit[blocked[: len(lit)]]] = 0.0
            g_light[g_lit[blocked[len(lit) :]]] = 0.0
    light[hit] = ambient + (1 - ambient) * light_hit
    bg_light = np.ones(len(d_bg))
    bg_light[down] = ambient + (1 - ambient) * g_light
    light[bg] = bg_light
    return np.clip(rgb * light[..., None], 0, 255).round().astype(np.uint8)


def depth_to_rgb(
    depth: np.ndarray,
    vmin: float | None = None,
    vmax: float | None = None,
    cmap: str = "turbo",
    background: tuple[int, int, int] = BACKGROUND_RGB,
) -> np.ndarray:
    """(H, W) depth (metres, NaN/inf = background) → (H, W, 3) uint8 colour image.

    Values are mapped linearly from [vmin, vmax] (default: the finite min and max) onto the
    matplotlib colour map ``cmap`` (e.g. "turbo", "viridis"), clipped at the ends; background
    pixels get ``background``. Equal bounds (a flat map's own) map from [vmin, vmin + 1];
    given bounds must be finite with vmin <= vmax (a NaN bound painted every pixel black,
    crossed ones a flat image).
    """
    import matplotlib  # lazy: matplotlib is slow to import and only previews need it

    d = np.asarray(depth, dtype=np.float64)
    if d.ndim != 2:
        raise InputError(f"depth must be an (H, W) array, got shape {d.shape}")
    for name, bound in (("vmin", vmin), ("vmax", vmax)):
        if bound is not None and not np.isfinite(bound):
            raise ConfigError(f"depth colour scale: {name} must be a finite number, got {bound}")
    if vmin is not None and vmax is not None and vmin > vmax:
        raise ConfigError(f"depth colour scale: vmin {vmin} is above vmax {vmax}")
    try:
        cm = matplotlib.colormaps[cmap]
    except KeyError:
        raise ConfigError(f"unknown matplotlib colour map {cmap!r}") from None
    fin = np.isfinite(d)
    out = np.empty((*d.shape, 3), np.uint8)
    out[:] = np.asarray(background, np.uint8)
    if not fin.any():
        return out
    lo = float(np.min(d[fin])) if vmin is None else float(vmin)
    hi = float(np.max(d[fin])) if vmax is None else float(vmax)
    span = hi - lo if hi > lo else 1.0
    x = np.clip((d[fin] - lo) / span, 0.0, 1.0)
    out[fin] = cm(x, bytes=True)[:, :3]
    return out


def oblique_camera(
    extent_xy: tuple[float, float, float, float],
    height: float = 1.0,
    elevation_deg: float = 35.0,
    azimuth_deg: float = -60.0,
    size: tuple[int, int] = ROW_CAMERA_SIZE,
    vfov_deg: float = ROW_CAMERA_VFOV_DEG,
    margin: float = 1.05,
) -> PinholeCamera:
    """A 3/4 view camera looking at the centre of a plot.

    extent_xy: (xmin, xmax, ymin, ymax) of the plot in metres; height: top of the canopy box
    [0, height] in metres. The camera sits at ``elevation_deg`` above the horizon, in the
    horizontal direction ``azimuth_deg`` (counter-clockwise from +x) seen from the box centre,
    looking at the box centre with the world z axis up in the image, just far enough for the
    whole box to fit with ``margin`` (≥ 1) to spare. ``size`` = (width, height) in pixels.
    """
    xmin, xmax, ymin, ymax = (float(a) for a in extent_xy)
    if not (xmax > xmin and ymax > ymin) or not all(
        math.isfinite(a) for a in (xmin, xmax, ymin, ymax)
    ):
        raise ConfigError(f"extent_xy must be (xmin, xmax, ymin, ymax), got {extent_xy}")
    if not (height >= 0 and math.isfinite(height)):
        raise ConfigError(f"height must be a finite non-negative number, got {height}")
    if not 0 < elevation_deg < 90:
        raise ConfigError(f"elevation_deg must be in (0, 90), got {elevation_deg}")
    if margin < 1:
        raise ConfigError(f"margin must be ≥ 1, got {margin}")
    target = np.array([(xmin + xmax) / 2, (ymin + ymax) / 2, height / 2])
    el, az = math.radians(elevation_deg), math.radians(azimuth_deg)
    back = np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
    z = -back
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    rot = np.column_stack([x, y, z])
    probe = PinholeCamera.from_vfov(size[0], size[1], vfov_deg, np.eye(4))
    tx = 0.5 * probe.width / probe.fx / margin
    ty = 0.5 * probe.height / probe.fy / margin
    corners = np.array(
        [[a, b, c] for a in (xmin, xmax) for b in (ymin, ymax) for c in (0.0, height)]
    )
    rc = (corners - target) @ rot  # corner offsets in camera axes
    dist = float(np.max(np.maximum(np.abs(rc[:, 0]) / tx, np.abs(rc[:, 1]) / ty) - rc[:, 2]))
    m = np.eye(4)
    m[:3, :3] = rot
    m[:3, 3] = target + back * max(dist, 1e-3)
    return PinholeCamera.from_vfov(size[0], size[1], vfov_deg, m)


def save_png(path: str | os.PathLike, rgb: np.ndarray) -> Path:
    """Write an (H, W, 3) or (H, W, 4) uint8 image (or (H, W) grey) to ``path`` as PNG, atomically
    (:func:`cropcraft_core.export.atomic_path`). Returns the path."""
    from PIL import Image

    a = np.asarray(rgb)
    if a.dtype != np.uint8 or not (a.ndim == 2 or (a.ndim == 3 and a.shape[2] in (3, 4))):
        raise InputError(
            f"image must be uint8 (H, W), (H, W, 3) or (H, W, 4), got {a.dtype} {a.shape}"
        )
    p = Path(path)
    if not p.parent.is_dir():
        raise OutputError(f"cannot write {p}: folder {p.parent} does not exist")
    with atomic_path(p) as tmp:  # the usual file mode, not mkstemp's 0600
        Image.fromarray(np.ascontiguousarray(a)).save(tmp, format="PNG")
    return p
