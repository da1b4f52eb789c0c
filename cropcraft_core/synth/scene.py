"""Synthetic photo scenes of a generated canopy: test data for SfM and the demo scene.

``make_scene`` builds a canopy (the plot plus every plant any view can see, so no image shows the
edge of the planting), flies a camera along a realistic trajectory, and writes for every view a
shaded colour image and its true z-depth, plus the poses (COLMAP text model and nerfstudio
``transforms.json``) and the truth (parameters, metrics, plot mesh).

World frame: z up, ground plane z = 0, metres, plot centred on the origin (``CanopyLayout``).
Cameras: ``PinholeCamera`` (OpenCV axes, pixel centres at +0.5).

The images are made for feature matching: soil with multi-octave value noise, clods and pebbles;
leaves green with per-plant, per-leaf (plant, node) and per-face tints and a world-anchored texture
(fine noise and vein-like ridges); lighter petioles and stems; Lambert sun with cast shadows (one
shadow map per scene), light through back-lit leaves, sky ambient; sky where rays go up; 2 × 2
supersampling and a little sensor noise. All texture is a function of the 3D surface point, so it
is identical in every view (what SIFT needs). Trajectories:

* ``walk``: a person walking once around the plot, camera 1.0–1.8 m above the ground, looking down
  (45–70°) and inwards at points inside the plot that change from view to view.
* ``drone``: a lawnmower pattern over the plot at ~13 m, camera tilted 5–15° forward from nadir.
"""

from __future__ import annotations

import json
import math
import os
import time
from collections.abc import Mapping
from pathlib import Path

import numpy as np
from numba import njit, prange
from PIL import Image

from cropcraft_core.config.layout import CanopyLayout, default_layout
from cropcraft_core.config.params import check_crop, resolve_params
from cropcraft_core.errors import ConfigError, OutputError
from cropcraft_core.geometry.camera import PinholeCamera
from cropcraft_core.geometry.mesh import CanopyMesh, Organ
from cropcraft_core.procedural.canopy import generate_canopy, max_reach, plot_region
from cropcraft_core.procedural.structure import Canopy
from cropcraft_core.render.preview import hash01
from cropcraft_core.render.result import RenderResult
from cropcraft_core.sfm.poses import Poses, export_colmap_text, export_transforms_json

TRAJECTORIES = ("walk", "drone")
#: Where a synthetic scene's world origin lies on Earth when its photos carry GPS positions
#: (latitude, longitude in degrees, altitude in metres): a field in central Illinois.
GPS_ORIGIN = (40.0646, -88.1963, 222.0)
#: Vertical field of view of the synthetic camera (degrees); 640 × 480 gives ~64° horizontally,
#: a phone's main camera.
DEFAULT_VFOV_DEG = 50.0
WORLD_FRAME_NOTE = "z up, ground plane z = 0, metres, plot centred on the origin"

# Linear-light reflectances (before the sRGB transfer curve).
_SOIL = (0.19, 0.11, 0.06)
_PEBBLE = (0.34, 0.30, 0.25)
_LEAF = (0.050, 0.150, 0.028)
_LEAF_YELLOW = (0.095, 0.170, 0.030)
_LEAF_DARK = (0.030, 0.105, 0.030)
_PETIOLE = (0.11, 0.21, 0.05)
_STEM = (0.17, 0.22, 0.07)
_SKY_HORIZON = (0.62, 0.72, 0.85)
_SKY_ZENITH = (0.20, 0.36, 0.68)
_SUN_RGB = (1.0, 0.96, 0.90)
_AMBIENT_RGB = (0.30, 0.33, 0.38)


def _render_depth(vertices: np.ndarray, faces: np.ndarray, camera: PinholeCamera) -> RenderResult:
    """Depth + face ids through the numba rasterizer, or the Open3D ray caster without it."""
    try:
        from cropcraft_core.render.raster import render_depth
    except ImportError:  # pragma: no cover - raster is the default renderer
        from cropcraft_core.render.raycast import raycast_depth

        return raycast_depth((vertices, faces), camera)
    return render_depth(vertices, faces, camera)


# --------------------------------------------------------------------------- trajectories


def camera_from_angles(
    position: np.ndarray,
    yaw: float,
    pitch_down: float,
    roll: float,
    size: tuple[int, int],
    vfov_deg: float,
) -> PinholeCamera:
    """A camera at ``position`` (3,) metres heading ``yaw`` (radians from +x, counter-clockwise
    seen from above), tilted ``pitch_down`` radians below the horizon (π/2 = nadir), rolled by
    ``roll`` radians about its optical axis. Image x points right of the heading."""
    cp, sp = math.cos(pitch_down), math.sin(pitch_down)
    f = np.array([cp * math.cos(yaw), cp * math.sin(yaw), -sp])
    r = np.array([math.sin(yaw), -math.cos(yaw), 0.0])
    d = np.cross(f, r)
    cr, sr = math.cos(roll), math.sin(roll)
    r, d = cr * r + sr * d, -sr * r + cr * d
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = r, d, f, position
    return PinholeCamera.from_vfov(size[0], size[1], vfov_deg, m)


#: The largest plot side a walk round the plot covers: from its edge, looking down 45-70°,
#: the plot's centre is in 48-50 of 50 views of a 2 m plot, 32-35 of a 3 m one, 15-22 of a
#: 4 m one and none of a 6 m one (three trajectory seeds each).
WALK_MAX_PLOT_M = 3.0


def walk_trajectory(
    layout: CanopyLayout,
    n_views: int,
    rng: np.random.Generator,
    canopy_top: float,
    size: tuple[int, int] = (640, 480),
    vfov_deg: float = DEFAULT_VFOV_DEG,
    arc_deg: float = 360.0,
) -> list[PinholeCamera]:
    """A person walking around the plot with a hand-held camera, in capture order.

    Camera 1.0–1.8 m above the ground (and ≥ 0.35 m above ``canopy_top``), on a wobbly ring just
    outside the plot's half-diagonal, covering ``arc_deg`` degrees of it (360: once around); each
    view looks at a point inside the plot (drifting smoothly over the central 25 % of its length
    and width, at half the canopy height, plus jitter), pitched down 45–70°, with a few degrees of
    roll.
    """
    side = max(layout.plot_length, layout.plot_width)
    if side > WALK_MAX_PLOT_M:  # looking down 45-70 degrees from its edge, views miss its centre
        raise ConfigError(
            f"a {layout.plot_width:g} x {layout.plot_length:g} m plot is too large for the walk "
            f"trajectory (at most {WALK_MAX_PLOT_M:g} m a side): looking down at 45-70 degrees "
            "from its edge, the views miss its centre; use the drone trajectory or a smaller plot"
        )
    half_diag = 0.5 * math.hypot(layout.plot_length, layout.plot_width)
    radius0 = half_diag + 0.5
    h_lo = max(1.0, canopy_top + 0.35)
    if h_lo > 1.8:
        raise ConfigError(
            f"the canopy is {canopy_top:.2f} m tall: a walking camera (≤ 1.8 m) cannot look down "
            "onto it; use the drone trajectory"
        )
    a = math.radians(layout.row_azimuth_deg)
    rot = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
    if not 0 < arc_deg <= 360:
        raise ConfigError(f"walk arc must be in (0, 360] degrees, got {arc_deg}")
    phase = rng.uniform(0, 2 * math.pi, size=6)
    arc = math.radians(arc_deg)
    step = arc / n_views if arc_deg == 360 else arc / max(n_views - 1, 1)
    cams = []
    for i in range(n_views):
        th = phase[0] + i * step + rng.normal(0, 0.05 * step)
        rad = radius0 + 0.15 * math.sin(2 * th + phase[1]) + rng.normal(0, 0.04)
        h = 1.4 + 0.3 * math.sin(th + phase[2]) + rng.normal(0, 0.06)
        h = float(np.clip(h, h_lo, 1.8))
        pos = np.array([rad * math.cos(th), rad * math.sin(th), h])
        drift = np.array([math.sin(3 * th + phase[3]), math.sin(2 * th + phase[4])])
        tgt_row = (0.12 * drift + rng.normal(0, 0.015, 2)) * [layout.plot_length, layout.plot_width]
        tgt = np.array([*(rot @ tgt_row), 0.5 * canopy_top])
        v = tgt - pos
        yaw = math.atan2(v[1], v[0])
        pitch = math.atan2(-v[2], math.hypot(v[0], v[1]))
        pitch = float(np.clip(pitch + rng.normal(0, math.radians(1)), *np.radians([45, 70])))
        roll = rng.normal(0, math.radians(2))
        cams.append(camera_from_angles(pos, yaw, pitch, roll, size, vfov_deg))
    return cams


def drone_trajectory(
    layout: CanopyLayout,
    n_views: int,
    rng: np.random.Generator,
    canopy_top: float,
    size: tuple[int, int] = (640, 480),
    vfov_deg: float = DEFAULT_VFOV_DEG,
    height: float = 13.0,
) -> list[PinholeCamera]:
    """A drone flying a lawnmower pattern over the plot at ``height`` ± 0.3 m, in capture order.

    Flight lines run along the rows over the plot plus 1.5 m each side, alternating direction;
    the camera faces the flight direction, tilted 5–15° forward from nadir, with small yaw and
    roll jitter.
    """
    if height <= canopy_top + 1.0:
        raise ConfigError(f"drone height {height} m is too close to the canopy top")
    n_lines = max(2, round(math.sqrt(n_views / 2.5)))
    per_line = math.ceil(n_views / n_lines)
    hx = layout.plot_length / 2 + 1.5
    hy = layout.plot_width / 2 + 1.5
    a = math.radians(layout.row_azimuth_deg)
    rot = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
    cams = []
    for i in range(n_views):
        line, k = divmod(i, per_line)
        forward = line % 2 == 0
        s = k / max(per_line - 1, 1)
        x = -hx + 2 * hx * (s if forward else 1 - s)
        y = -hy + 2 * hy * line / (n_lines - 1)
        xy = rot @ (np.array([x, y]) + rng.normal(0, 0.15, 2))
        pos = np.array([*xy, height + rng.normal(0, 0.1)])
        yaw = a + (0.0 if forward else math.pi) + rng.normal(0, math.radians(3))
        pitch = math.radians(90 - rng.uniform(5, 15))
        roll = rng.normal(0, math.radians(1.5))
        cams.append(camera_from_angles(pos, yaw, pitch, roll, size, vfov_deg))
    return cams


def views_region(cameras: list[PinholeCamera], layout: CanopyLayout, reach: float):
    """Row-frame (xmin, xmax, ymin, ymax) of plant bases that can appear in any of ``cameras``:
    the union of their ground footprints and the plot, grown by ``reach`` metres."""
    a = math.radians(layout.row_azimuth_deg)
    c, s = math.cos(a), math.sin(a)
    pts = [np.array([[r[0], r[2]], [r[1], r[3]]]) for r in [plot_region(layout, 0.0)]]
    for cam in cameras:
        fp = cam.ground_footprint(0.0)
        pts.append(np.column_stack([fp[:, 0] * c + fp[:, 1] * s, -fp[:, 0] * s + fp[:, 1] * c]))
    p = np.concatenate(pts)
    return (
        float(p[:, 0].min() - reach),
        float(p[:, 0].max() + reach),
        float(p[:, 1].min() - reach),
        float(p[:, 1].max() + reach),
    )


# --------------------------------------------------------------------------- noise (numba)


@njit(cache=True, inline="always")
def _hash(ix, iy, iz, seed):  # pragma: no cover - numba
    """Uniform [0, 1) from four int64 keys (wrapping integer mixing)."""
    h = ix * 0x27D4EB2F165667C5 + iy * 0x165667B19E3779F9 + iz * 0x61C8864680B583EB
    h = h + seed * 0x2545F4914F6CDD1D
    h = (h ^ (h >> 31)) * 0x7FB5D329728EA185
    h = (h ^ (h >> 27)) * 0x81DADEF4BC2DD44D
    h = h ^ (h >> 33)
    return (h & 0xFFFFFF) / 16777216.0


@njit(cache=True, inline="always")
def _smooth(t):  # pragma: no cover - numba
    return t * t * (3.0 - 2.0 * t)


@njit(cache=True)
def _vnoise3(x, y, z, seed):  # pragma: no cover - numba
    """Trilinear value noise in [0, 1] on the unit lattice."""
    fx, fy, fz = math.floor(x), math.floor(y), math.floor(z)
    ix, iy, iz = np.int64(fx), np.int64(fy), np.int64(fz)
    u, v, w = _smooth(x - fx), _smooth(y - fy), _smooth(z - fz)
    c000 = _hash(ix, iy, iz, seed)
    c100 = _hash(ix + 1, iy, iz, seed)
    c010 = _hash(ix, iy + 1, iz, seed)
    c110 = _hash(ix + 1, iy + 1, iz, seed)
    c001 = _hash(ix, iy, iz + 1, seed)
    c101 = _hash(ix + 1, iy, iz + 1, seed)
    c011 = _hash(ix, iy + 1, iz + 1, seed)
    c111 = _hash(ix + 1, iy + 1, iz + 1, seed)
    a = c000 + u * (c100 - c000)
    b = c010 + u * (c110 - c010)
    c = c001 + u * (c101 - c001)
    d = c011 + u * (c111 - c011)
    e = a + v * (b - a)
    f = c + v * (d - c)
    return e + w * (f - e)


@njit(cache=True)
def _vnoise2(x, y, seed):  # pragma: no cover - numba
    fx, fy = math.floor(x), math.floor(y)
    ix, iy = np.int64(fx), np.int64(fy)
    u, v = _smooth(x - fx), _smooth(y - fy)
    c00 = _hash(ix, iy, 0, seed)
    c10 = _hash(ix + 1, iy, 0, seed)
    c01 = _hash(ix, iy + 1, 0, seed)
    c11 = _hash(ix + 1, iy + 1, 0, seed)
    a = c00 + u * (c10 - c00)
    b = c01 + u * (c11 - c01)
    return a + v * (b - a)


@njit(cache=True)
def _fbm2(x, y, scales, seed):  # pragma: no cover - numba
    """Sum of value noise at ``scales`` (metres, coarse first), amplitude ∝ scale^0.5, in [0, 1]."""
    acc = 0.0
    norm = 0.0
    for k in range(scales.shape[0]):
        amp = math.sqrt(scales[k] / scales[0])
        acc += amp * _vnoise2(x / scales[k], y / scales[k], seed + 7919 * k)
        norm += amp
    return acc / norm


@njit(cache=True)
def _fbm3(x, y, z, scales, seed):  # pragma: no cover - numba
    acc = 0.0
    norm = 0.0
    for k in range(scales.shape[0]):
        amp = math.sqrt(scales[k] / scales[0])
        acc += amp * _vnoise3(x / scales[k], y / scales[k], z / scales[k], seed + 7919 * k)
        norm += amp
    return acc / norm


@njit(cache=True)
def _bumps(x, y, cell, prob, r_lo, r_hi, seed):  # pragma: no cover - numba
    """Random discs on a jittered grid of ``cell`` metres: returns (inside, nx, ny, tone) for the
    disc covering (x, y) (tone ∈ [0, 1) its random shade; (nx, ny) the slope of a dome)."""
    cx0 = np.int64(math.floor(x / cell))
    cy0 = np.int64(math.floor(y / cell))
    for dx in range(-1, 2):
        for dy in range(-1, 2):
            i, j = cx0 + dx, cy0 + dy
            if _hash(i, j, 1, seed) >= prob:
                continue
            px = (i + _hash(i, j, 2, seed)) * cell
            py = (j + _hash(i, j, 3, seed)) * cell
            r = cell * (r_lo + (r_hi - r_lo) * _hash(i, j, 4, seed))
            ex, ey = (x - px) / r, (y - py) / r
            # irregular outline: radius modulated by angle
            q = ex * ex + ey * ey
            wob = 1.0 + 0.25 * (_vnoise2(4.0 * ex + i, 4.0 * ey + j, seed + 5) - 0.5)
            if q < wob * wob:
                return True, 0.8 * ex, 0.8 * ey, _hash(i, j, 5, seed)
    return False, 0.0, 0.0, 0.0


# --------------------------------------------------------------------------- shading (numba)


@njit(cache=True, parallel=True)
def _shadow_lookup(
    points, kind, fid, sm_depth, sm_fid, w2c, fx, fy, cx, cy, bias, lit
):  # pragma: no cover - numba
    """lit (H, W): fraction of a 3 × 3 shadow-map neighbourhood that does not occlude the point."""
    h, w = kind.shape
    sh, sw = sm_depth.shape
    for y in prange(h):
        for x in range(w):
            if kind[y, x] == 0:
                lit[y, x] = 1.0
                continue
            px, py, pz = points[y, x, 0], points[y, x, 1], points[y, x, 2]
            zc = w2c[2, 0] * px + w2c[2, 1] * py + w2c[2, 2] * pz + w2c[2, 3]
            xc = w2c[0, 0] * px + w2c[0, 1] * py + w2c[0, 2] * pz + w2c[0, 3]
            yc = w2c[1, 0] * px + w2c[1, 1] * py + w2c[1, 2] * pz + w2c[1, 3]
            u = fx * xc / zc + cx
            v = fy * yc / zc + cy
            iu = np.int64(math.floor(u))
            iv = np.int64(math.floor(v))
            own = fid[y, x]
            n_lit = 0
            for dv in range(-1, 2):
                for du in range(-1, 2):
                    a, b = iv + dv, iu + du
                    if a < 0 or b < 0 or a >= sh or b >= sw:
                        n_lit += 1
                        continue
                    d = sm_depth[a, b]
                    if not (d == d) or (own >= 0 and sm_fid[a, b] == own) or zc <= d + bias:
                        n_lit += 1
            lit[y, x] = n_lit / 9.0


@njit(cache=True, parallel=True)
def _shade(
    points,
    dirs,
    kind,
    fid,
    face_rgb,
    face_normal,
    face_organ,
    lit,
    sun,
    seed,
    out,
):  # pragma: no cover - numba
    """Linear RGB (H, W, 3) of every pixel. kind: 0 sky, 1 ground, 2 plant."""
    h, w = kind.shape
    soil_coarse = np.array([0.9, 0.35])
    soil_fine = np.array([0.12, 0.05, 0.025, 0.012, 0.006])
    leaf_tex = np.array([0.04, 0.018, 0.008, 0.004])
    for y in prange(h):
        for x in range(w):
            dx, dy, dz = dirs[y, x, 0], dirs[y, x, 1], dirs[y, x, 2]
            k = kind[y, x]
            if k == 0:
                n = math.sqrt(dx * dx + dy * dy + dz * dz)
                e = max(0.0, dz / n) ** 0.6
                for c in range(3):
                    out[y, x, c] = _SKY_HORIZON[c] + e * (_SKY_ZENITH[c] - _SKY_HORIZON[c])
                continue
            px, py, pz = points[y, x, 0], points[y, x, 1], points[y, x, 2]
            s = lit[y, x]
            if k == 1:
                m = _fbm2(px, py, soil_coarse, seed + 11)
                d = _fbm2(px, py, soil_fine, seed + 12)
                tone = (0.72 + 0.5 * m) * (0.45 + 1.1 * d)
                r, g, b = _SOIL[0] * tone, _SOIL[1] * tone, _SOIL[2] * tone
                # darker, redder where moist (coarse noise)
                g *= 0.92 + 0.16 * m
                b *= 0.85 + 0.3 * m
                nx, ny = 0.0, 0.0
                inside, bx, by, t = _bumps(px, py, 0.022, 0.09, 0.2, 0.38, seed + 21)
                if inside:
                    f = 0.75 + 0.5 * t
                    r, g, b = _PEBBLE[0] * f, _PEBBLE[1] * f, _PEBBLE[2] * f
                    nx, ny = bx, by
                else:
                    inside, bx, by, t = _bumps(px, py, 0.04, 0.5, 0.25, 0.5, seed + 31)
                    if inside:
                        f = 0.8 + 0.45 * t
                        r, g, b = r * f, g * f, b * f
                        nx, ny = bx, by
                nz = math.sqrt(max(0.05, 1.0 - nx * nx - ny * ny))
                ndl = max(0.0, (nx * sun[0] + ny * sun[1] + nz * sun[2]))
                amb = 0.55 + 0.45 * nz
                out[y, x, 0] = r * (amb * _AMBIENT_RGB[0] + s * ndl * _SUN_RGB[0])
                out[y, x, 1] = g * (amb * _AMBIENT_RGB[1] + s * ndl * _SUN_RGB[1])
                out[y, x, 2] = b * (amb * _AMBIENT_RGB[2] + s * ndl * _SUN_RGB[2])
                continue
            f = fid[y, x]
            nx, ny, nz = face_normal[f, 0], face_normal[f, 1], face_normal[f, 2]
            if nx * dx + ny * dy + nz * dz > 0:
                nx, ny, nz = -nx, -ny, -nz
            ndl = nx * sun[0] + ny * sun[1] + nz * sun[2]
            organ = face_organ[f]
            r, g, b = face_rgb[f, 0], face_rgb[f, 1], face_rgb[f, 2]
            if organ == 0:
                t = _fbm3(px, py, pz, leaf_tex, seed + 41)
                tone = 0.45 + 1.1 * t
                vn = _vnoise3(px / 0.015, py / 0.015, pz / 0.015, seed + 43)
                vein = 1.0 - 2.0 * abs(vn - 0.5)
                if vein > 0.86:
                    tone *= 1.0 + 2.0 * (vein - 0.86)
                spot = _vnoise3(px / 0.008, py / 0.008, pz / 0.008, seed + 47)
                if spot > 0.9:
                    r *= 1.3
                    g *= 1.1
            else:
                tone = 0.8 + 0.4 * _fbm3(px, py, pz, leaf_tex[1:], seed + 51)
            r, g, b = r * tone, g * tone, b * tone
            if ndl >= 0:
                direct = ndl * s
                tr = 1.0
                tb = 1.0
            else:  # light through the leaf: yellower, dimmer
                direct = (0.35 if organ == 0 else 0.0) * -ndl * s
                tr = 1.25
                tb = 0.5
            amb = 0.6 + 0.4 * max(nz, 0.0)
            out[y, x, 0] = r * (amb * _AMBIENT_RGB[0] + direct * tr * _SUN_RGB[0])
            out[y, x, 1] = g * (amb * _AMBIENT_RGB[1] + direct * _SUN_RGB[1])
            out[y, x, 2] = b * (amb * _AMBIENT_RGB[2] + direct * tb * _SUN_RGB[2])


def _srgb(linear: np.ndarray) -> np.ndarray:
    c = np.clip(linear, 0.0, 1.0)
    return np.where(c <= 0.0031308, 12.92 * c, 1.055 * np.power(c, 1 / 2.4) - 0.055)


def face_colors(canopy: Canopy, seed: int) -> np.ndarray:
    """(m, 3) float64 linear-light reflectance of every face of ``canopy.mesh``: leaves between a
    yellowish and a dark green by plant tint, varied per leaf (plant, node) and per face;
    petioles and stems lighter."""
    mesh = canopy.mesh
    m = mesh.n_faces
    tint = np.asarray(canopy.info.get("plant_tint", []), dtype=np.float64)
    if len(tint) != len(canopy.plant_xy):
        tint = hash01(np.arange(len(canopy.plant_xy)), seed + 1)
    pt = tint[mesh.plant]
    leaf_key = mesh.plant.astype(np.int64) * 4096 + mesh.node.astype(np.int64)
    lt = hash01(leaf_key, seed + 2)
    ft = hash01(np.arange(m, dtype=np.int64), seed + 3)
    yellow, dark, base = (np.array(c) for c in (_LEAF_YELLOW, _LEAF_DARK, _LEAF))
    w_y = np.clip(pt - 0.5, 0, None)[:, None] * 1.4
    w_d = np.clip(0.5 - pt, 0, None)[:, None] * 1.4
    rgb = base * (1 - w_y - w_d) + yellow * w_y + dark * w_d
    rgb = rgb * (0.8 + 0.4 * lt)[:, None] * (0.9 + 0.2 * ft)[:, None]
    rgb[:, 0] *= 0.85 + 0.3 * hash01(leaf_key, seed + 4)
    pet = mesh.organ == Organ.PETIOLE
    stem = mesh.organ == Organ.STEM
    rgb[pet] = np.array(_PETIOLE) * (0.85 + 0.3 * lt[pet])[:, None]
    rgb[stem] = np.array(_STEM) * (0.85 + 0.3 * lt[stem])[:, None]
    return rgb


class _ShadowMap:
    """Depth map of the canopy seen from the sun (a far pinhole camera ≈ parallel light)."""

    def __init__(self, mesh: CanopyMesh, sun: np.ndarray, region_world: np.ndarray, res: int):
        lo, hi = region_world.min(0), region_world.max(0)
        centre = np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, 0.0])
        half = 0.5 * float(np.hypot(hi[0] - lo[0], hi[1] - lo[1])) + 0.5
        dist = 300.0
        f = -sun
        up = np.array([0.0, 0.0, 1.0]) if abs(f[2]) < 0.99 else np.array([1.0, 0.0, 0.0])
        r = np.cross(f, up)
        r /= np.linalg.norm(r)
        d = np.cross(f, r)
        m = np.eye(4)
        m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = r, d, f, centre + sun * dist
        foc = 0.5 * res * (dist - half) / half
        self.camera = PinholeCamera(res, res, foc, foc, res / 2, res / 2, m)
        rr = _render_depth(mesh.vertices, mesh.faces, self.camera)
        self.depth = rr.depth.astype(np.float64)
        self.face_id = rr.face_id
        # depth tolerance: a few texels of slope plus 5 mm
        self.bias = 0.005 + 3.0 * dist / foc

    def lit(self, points: np.ndarray, kind: np.ndarray, fid: np.ndarray) -> np.ndarray:
        out = np.empty(kind.shape)
        c = self.camera
        _shadow_lookup(
            points, kind, fid, self.depth, self.face_id, c.world_to_cam,
            c.fx, c.fy, c.cx, c.cy, self.bias, out,
        )  # fmt: skip
        return out


def render_view(
    mesh: CanopyMesh,
    camera: PinholeCamera,
    face_rgb: np.ndarray,
    face_normal: np.ndarray,
    sun: np.ndarray,
    shadow: _ShadowMap | None,
    seed: int,
    rng: np.random.Generator,
    supersample: int = 2,
    noise_dn: float = 1.0,
) -> tuple[np.ndarray, np.ndarray]:
    """One view: ((H, W, 3) uint8 sRGB image, (H, W) float32 true z-depth, NaN for sky).

    The colour image is rendered at ``supersample`` × the resolution and box-filtered; the depth is
    exact at the pixel centres (nearest of the mesh and the ground plane z = 0).
    """
    cam_hi = camera.scaled(supersample) if supersample > 1 else camera
    res = _render_depth(mesh.vertices, mesh.faces, cam_hi)
    dirs = cam_hi.ray_directions(normalized=False)
    depth = res.depth.astype(np.float64)
    fid = res.face_id
    c = cam_hi.center
    kind = np.where(fid >= 0, 2, 0).astype(np.int8)
    down = (fid < 0) & (dirs[..., 2] < 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        tg = -c[2] / dirs[..., 2]
    depth[down] = tg[down]
    kind[down] = 1
    points = c + dirs * np.where(kind > 0, depth, 0.0)[..., None]
    points = np.ascontiguousarray(points)
    lit = shadow.lit(points, kind, fid) if shadow is not None else np.ones(kind.shape)
    lin = np.zeros((*kind.shape, 3))
    _shade(
        points, np.ascontiguousarray(dirs), kind, fid, face_rgb, face_normal,
        mesh.organ.astype(np.int64), lit, sun, int(seed), lin,
    )  # fmt: skip
    if supersample > 1:
        h, w = camera.height, camera.width
        lin = lin.reshape(h, supersample, w, supersample, 3).mean(axis=(1, 3))
    img = _srgb(lin * 1.1) * 255.0
    if noise_dn > 0:
        img = img + rng.normal(0.0, noise_dn, img.shape)
    img = np.clip(np.rint(img), 0, 255).astype(np.uint8)
    if supersample > 1:
        truth = _render_depth(mesh.vertices, mesh.faces, camera)
        depth = truth.depth.astype(np.float64)
        d0 = camera.ray_directions(normalized=False)
        down0 = (truth.face_id < 0) & (d0[..., 2] < 0)
        with np.errstate(divide="ignore", invalid="ignore"):
            tg0 = -camera.center[2] / d0[..., 2]
        depth[down0] = tg0[down0]
    return img, depth.astype(np.float32)


# --------------------------------------------------------------------------- the scene


def _truth_metrics(canopy: Canopy, seed: int) -> dict:
    """The truth's metrics as ``cropcraft generate`` measures a canopy (gap-fraction rays
    through a border wide enough for them), the sensors seeded by the scene's seed."""
    from cropcraft_core.bundle import measure_canopy

    return measure_canopy(canopy, rng=seed)


def _write_ply(path: Path, mesh: CanopyMesh) -> None:
    try:
        from cropcraft_core.export import write_ply
    except ImportError:  # pragma: no cover - export ships with the package
        header = (
            "ply\nformat binary_little_endian 1.0\ncomment units metres, z up\n"
            f"element vertex {len(mesh.vertices)}\n"
            "property double x\nproperty double y\nproperty double z\n"
            f"element face {mesh.n_faces}\nproperty list uchar int vertex_indices\n"
            "property uchar organ\nproperty int plant\nproperty int node\nend_header\n"
        ).encode()
        dt = np.dtype([("n", "u1"), ("v", "<i4", (3,)), ("o", "u1"), ("p", "<i4"), ("d", "<i4")])
        rec = np.empty(mesh.n_faces, dt)
        rec["n"], rec["v"], rec["o"] = 3, mesh.faces, mesh.organ
        rec["p"], rec["d"] = mesh.plant, mesh.node
        path.write_bytes(header + mesh.vertices.astype("<f8").tobytes() + rec.tobytes())
        return
    write_ply(path, mesh)


def _gps_fixes(cams: list[PinholeCamera], noise_m: float, seed: int) -> np.ndarray:
    """(n, 3) latitude, longitude, altitude of each camera as a GPS receiver reports it
    (``make_scene``'s ``gps_noise_m``)."""
    import pycolmap

    rng = np.random.default_rng([int(seed) & 0xFFFFFFFF, 0x6F5])
    true = np.array([c.center for c in cams], dtype=np.float64)
    sd = noise_m * np.array([1.0, 1.0, 1.5])
    offset = rng.normal(0.0, 3.0, 3) * np.array([1.0, 1.0, 1.5])
    drift = np.cumsum(rng.normal(0.0, 0.1, true.shape) * sd, axis=0)
    enu = true + offset + drift + rng.normal(0.0, 1.0, true.shape) * sd
    t = pycolmap.GPSTransform(pycolmap.GPSTransformEllipsoid.WGS84)
    return np.asarray(t.enu_to_ellipsoid(enu, *GPS_ORIGIN), dtype=np.float64)


def _gps_exif(lat_lon_alt: np.ndarray) -> bytes:
    """EXIF bytes holding a GPS position (as a camera writes it: degrees, minutes, seconds)."""
    from PIL.TiffImagePlugin import IFDRational

    def dms(v: float) -> tuple:
        v = abs(v)
        d = int(v)
        m = int((v - d) * 60)
        sec = IFDRational(round((v - d - m / 60) * 3600e6), 10**6)
        return (IFDRational(d, 1), IFDRational(m, 1), sec)

    lat, lon, alt = (float(v) for v in lat_lon_alt)
    exif = Image.Exif()
    g = exif.get_ifd(0x8825)
    g.update({
        1: "N" if lat >= 0 else "S", 2: dms(lat), 3: "E" if lon >= 0 else "W", 4: dms(lon),
        5: b"\x00" if alt >= 0 else b"\x01", 6: IFDRational(round(abs(alt) * 1000), 1000),
    })  # fmt: skip
    return exif.tobytes()


def _write_json(path: Path, obj: object) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(obj, indent=2), encoding="utf-8")
    os.replace(tmp, path)


def _whole(v: object) -> bool:
    return isinstance(v, int | np.integer) and not isinstance(v, bool)


#: What a scene of ``make_scene`` consists of in its folder (each removed before a new one).
SCENE_FILES = (
    "images/view_*.jpg",
    "images/view_*.png",
    "depth/view_*.npy",
    "colmap/sparse/0/*.txt",
    "truth/params.json",
    "truth/metrics.json",
    "truth/canopy.ply",
    "transforms.json",
    "scene.json",
)


def _clear_scene(out: Path) -> None:
    """Remove an earlier scene's files (``SCENE_FILES``) from ``out``: a scene of fewer views
    kept the earlier one's last photos beside its own, and one without metrics its truth;
    files of other names are left alone."""
    for pattern in SCENE_FILES:
        for p in out.glob(pattern):
            p.unlink()


def make_scene(
    crop: str,
    out_dir: str | os.PathLike,
    params: Mapping[str, float] | None = None,
    seed: int = 0,
    views: int = 50,
    resolution: tuple[int, int] = (640, 480),
    trajectory: str = "walk",
    layout: CanopyLayout | None = None,
    *,
    vfov_deg: float = DEFAULT_VFOV_DEG,
    image_format: str = "jpg",
    supersample: int = 2,
    shadows: bool = True,
    metrics: bool = True,
    walk_arc_deg: float = 360.0,
    drone_height_m: float | None = None,
    gps_noise_m: float | None = None,
) -> dict:
    """Render a synthetic photo scene of a ``crop`` canopy into ``out_dir``; return its summary.

    crop: 'soybean' or 'maize'.  params: procedural parameters (missing ones: middle of range).
    seed: canopy, trajectory, lighting and noise all follow from it.  views: number of images.
    resolution: (width, height) pixels.  trajectory: 'walk' (hand-held, 1–1.8 m, around the plot)
    or 'drone' (lawnmower at ~13 m; use it for maize, which is too tall to walk over).
    layout: plot layout (default ``default_layout(crop)``).  vfov_deg: vertical field of view.
    image_format: 'jpg' (quality 95) or 'png'.  supersample: colour samples per pixel side.
    shadows: cast sun shadows.  metrics: compute ``truth/metrics.json`` (gap-fraction LAI
    included, a few seconds).  walk_arc_deg: how far around the plot the walk goes (360: once
    around; less gives small test scenes dense enough for SfM with few views).
    drone_height_m: the drone's flying height above the ground (None: 13 m, the issue's); a
    drone trajectory's only.
    gps_noise_m: where given, every photo's EXIF carries the camera's GPS position
    (:data:`GPS_ORIGIN` at the world's origin, east along x, north along y), each fix off by
    this standard deviation (m) horizontally and 1.5 times it vertically, plus a slow drift (a
    random walk of a tenth of it a photo) and an offset of the whole capture (a few metres, as
    any receiver's absolute error): 0.02 for a drone with RTK, 0.5-2 for consumer GPS, 3-5
    for a phone. None (the default): no GPS tags.

    Writes, under ``out_dir``:
      images/view_NNN.<ext>        the photos, in capture order
      depth/view_NNN.npy           (H, W) float32 true z-depth (m) of each view, NaN for sky
      colmap/sparse/0/*.txt        COLMAP text model (PINHOLE, world-to-camera poses, no points)
      transforms.json              nerfstudio poses (OpenGL camera axes, camera-to-world)
      truth/params.json            crop, resolved params, seed, layout
      truth/metrics.json           traits of the plot's plants (``canopy_metrics``)
      truth/canopy.ply             mesh of the plot's plants (labelled faces)
      scene.json                   crop, seed, layout, trajectory, resolution, sun, world frame
    The canopy rendered covers every plant any view sees (the plot plus a border); the truth files
    describe the plot (the same plants, by the canopy's per-plant random streams). A scene
    already in ``out_dir`` is replaced: its files (``SCENE_FILES``) are removed first.
    """
    t_start = time.perf_counter()
    crop = check_crop(crop)
    if trajectory not in TRAJECTORIES:
        raise ConfigError(f"unknown trajectory {trajectory!r}: choose {' or '.join(TRAJECTORIES)}")
    if not _whole(views) or views < 2:
        raise ConfigError(f"a scene needs a whole number of views, at least 2, got {views!r}")
    if len(resolution) != 2 or not all(_whole(v) for v in resolution):
        raise ConfigError(f"resolution must be two whole numbers (width, height), got {resolution}")
    w, h = (int(v) for v in resolution)
    if w < 16 or h < 16:
        raise ConfigError(f"resolution {w}×{h} is too small")
    if image_format not in ("jpg", "png"):
        raise ConfigError(f"image format must be jpg or png, got {image_format!r}")
    if not _whole(supersample) or supersample < 1:
        raise ConfigError(f"supersample must be a whole number ≥ 1, got {supersample!r}")
    if not (isinstance(vfov_deg, int | float) and 1.0 <= vfov_deg <= 120.0):
        raise ConfigError(f"vfov_deg must be a number of degrees in [1, 120], got {vfov_deg!r}")
    if not (_whole(seed) and 0 <= int(seed) < 2**32):  # checked here, before the old scene goes
        raise ConfigError(f"seed must be a whole number in [0, 2**32), got {seed!r}")
    if trajectory == "walk" and not (
        isinstance(walk_arc_deg, int | float) and 0 < walk_arc_deg <= 360
    ):
        raise ConfigError(f"walk arc must be in (0, 360] degrees, got {walk_arc_deg!r}")
    if drone_height_m is not None and trajectory != "drone":
        raise ConfigError(f"a drone height is for the drone trajectory, not the {trajectory}")
    if drone_height_m is None:
        drone_height_m = 13.0
    if not (isinstance(drone_height_m, int | float) and 1.0 <= drone_height_m <= 120.0):
        raise ConfigError(f"drone height must be 1-120 m, got {drone_height_m!r}")
    if gps_noise_m is not None and not (
        isinstance(gps_noise_m, int | float) and 0 <= gps_noise_m <= 50
    ):
        raise ConfigError(f"GPS noise must be 0-50 m, got {gps_noise_m!r}")
    if layout is not None and not isinstance(layout, CanopyLayout):
        raise ConfigError(f"layout must be a CanopyLayout, got {type(layout).__name__}")
    params = resolve_params(crop, params)
    layout = layout or default_layout(crop)
    out = Path(out_dir)

    ss = np.random.SeedSequence([int(seed) & 0xFFFFFFFF, 0x5C3E])
    rng_traj, rng_sun, rng_noise = (np.random.default_rng(s) for s in ss.spawn(3))

    # the plot's canopy (truth) tells the canopy height the trajectory must clear; its border is
    # as wide as the gap-fraction LAI's outer ring (68° from zenith) needs
    truth = generate_canopy(crop, params, layout, seed=seed)
    top = float(truth.mesh.vertices[:, 2].max()) if truth.mesh.n_faces else 0.0
    border = top * math.tan(math.radians(68)) + 0.2
    if metrics and border > layout.margin:
        truth = generate_canopy(crop, params, layout, seed=seed, region=plot_region(layout, border))
    if trajectory == "walk":
        cams = walk_trajectory(layout, int(views), rng_traj, top, (w, h), vfov_deg, walk_arc_deg)
    else:
        cams = drone_trajectory(
            layout, int(views), rng_traj, top, (w, h), vfov_deg, float(drone_height_m)
        )
    try:
        region = views_region(cams, layout, max_reach(crop, params))
    except ConfigError as e:  # a view with sky in a corner: the scene renders the ground only
        raise ConfigError(
            f"{e}: a {trajectory} view with vfov_deg {vfov_deg} at {w}x{h} sees above the horizon "
            "(narrow the field of view)"
        ) from None
    canopy = generate_canopy(crop, params, layout, seed=seed, region=region)
    mesh = canopy.mesh
    try:  # only now: every check above leaves a scene already in the folder as it was
        _clear_scene(out)
        for sub in ("images", "depth", "colmap/sparse/0", "truth"):
            (out / sub).mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise OutputError(f"cannot create the scene folder {out}: {e}") from None
    t_gen = time.perf_counter() - t_start

    sun_el = math.radians(rng_sun.uniform(45, 62))
    sun_az = rng_sun.uniform(0, 2 * math.pi)
    sun = np.array(
        [math.cos(sun_el) * math.cos(sun_az), math.cos(sun_el) * math.sin(sun_az), math.sin(sun_el)]
    )
    face_rgb = face_colors(canopy, seed)
    face_normal = mesh.face_normals()
    shadow = None
    if shadows:
        a = math.radians(layout.row_azimuth_deg)
        rot = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
        xr = np.array([[region[0], region[2]], [region[1], region[2]]])
        xr = np.vstack([xr, [[region[0], region[3]], [region[1], region[3]]]])
        shadow = _ShadowMap(mesh, sun, xr @ rot.T, res=3072)

    # drawn from their own stream, after every other draw: a scene without GPS is the same bytes
    gps = None if gps_noise_m is None else _gps_fixes(cams, float(gps_noise_m), seed)
    t0 = time.perf_counter()
    names = []
    for i, cam in enumerate(cams):
        name = f"view_{i:03d}.{image_format}"
        img, depth = render_view(
            mesh, cam, face_rgb, face_normal, sun, shadow, seed, rng_noise, supersample
        )
        path = out / "images" / name
        try:
            tags = {} if gps is None else {"exif": _gps_exif(gps[i])}
            if image_format == "jpg":
                Image.fromarray(img).save(path, quality=95, subsampling=0, **tags)
            else:
                Image.fromarray(img).save(path, **tags)
            np.save(out / "depth" / f"view_{i:03d}.npy", depth)
        except OSError as e:
            raise OutputError(f"cannot write {path}: {e}") from None
        names.append(name)
    t_render = time.perf_counter() - t0

    poses = Poses(tuple(zip(names, cams, strict=True)))
    export_colmap_text(poses, out / "colmap" / "sparse" / "0")
    export_transforms_json(
        poses,
        out / "transforms.json",
        extra={"cropcraft": {"world_frame": WORLD_FRAME_NOTE, "depth_dir": "depth"}},
    )
    _write_json(
        out / "truth" / "params.json",
        {"crop": crop, "params": params, "seed": int(seed), "layout": layout.to_dict()},
    )
    t0 = time.perf_counter()
    if metrics:
        _write_json(out / "truth" / "metrics.json", _truth_metrics(truth, seed))
    _write_ply(out / "truth" / "canopy.ply", truth.plot_mesh())
    t_truth = time.perf_counter() - t0

    summary = {
        "crop": crop,
        "seed": int(seed),
        "params": params,
        "layout": layout.to_dict(),
        "trajectory": trajectory,
        "walk_arc_deg": float(walk_arc_deg) if trajectory == "walk" else None,
        **({"drone_height_m": float(drone_height_m)} if trajectory == "drone" else {}),
        **({} if gps is None else {"gps_noise_m": float(gps_noise_m), "gps_origin": GPS_ORIGIN}),
        "views": len(names),
        "resolution": [w, h],
        "vfov_deg": float(vfov_deg),
        "image_format": image_format,
        "images": [f"images/{n}" for n in names],
        "depth": [f"depth/{Path(n).stem}.npy" for n in names],
        "depth_note": "z-depth along the optical axis (m), float32, NaN where the ray meets sky",
        "world_frame": WORLD_FRAME_NOTE,
        "camera_convention": "OpenCV (x right, y down, z forward), pixel centres at +0.5",
        "sun_direction": sun.tolist(),
        "rendered_region_row_frame": list(region),
        "rendered_faces": int(mesh.n_faces),
        "rendered_plants": int(len(canopy.plant_xy)),
        "plot_plants": int(truth.n_plants),
        "camera_height_range_m": [
            float(min(c.center[2] for c in cams)),
            float(max(c.center[2] for c in cams)),
        ],
        "seconds": {
            "generate": t_gen,
            "render": t_render,
            "truth": t_truth,
            "total": time.perf_counter() - t_start,
        },
    }
    _write_json(out / "scene.json", summary)
    summary["out_dir"] = str(out)
    return summary
