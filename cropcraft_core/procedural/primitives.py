"""Vectorised geometry builders shared by the species models.

Each builder takes arrays describing many instances at once and returns (vertices, faces) for all
of them, so a whole canopy is built with a handful of numpy calls and no Python loop per organ.
"""

from __future__ import annotations

import numpy as np

# Soybean leaflet outline: stations along the normalised length s and half-width fractions
# (width / 2 = W/2 · f). Widest at s = 0.37 (domain-facts.md); the polygon's area is
# LEAFLET_AREA_FACTOR · L · W, close to the measured 0.59.
_LEAFLET_S = np.array([0.0, 0.12, 0.25, 0.37, 0.55, 0.75, 0.9, 1.0])
_LEAFLET_F = np.array([0.0, 0.46, 0.78, 1.0, 0.85, 0.53, 0.25, 0.0])


def _leaflet_template() -> tuple[np.ndarray, np.ndarray]:
    """(k, 2) unit outline vertices (x along length in [0, 1], y across width in [-0.5, 0.5]) and
    (t, 3) faces, counter-clockwise seen from +z."""
    inner = np.arange(1, len(_LEAFLET_S) - 1)
    verts = [[0.0, 0.0]]
    for i in inner:  # left then right vertex per interior station
        verts += [[_LEAFLET_S[i], 0.5 * _LEAFLET_F[i]], [_LEAFLET_S[i], -0.5 * _LEAFLET_F[i]]]
    verts.append([1.0, 0.0])
    v = np.array(verts)
    faces = [[0, 2, 1]]
    for k in range(len(inner) - 1):
        left, right = 1 + 2 * k, 2 + 2 * k
        faces += [[left, right, right + 2], [left, right + 2, left + 2]]
    tip = len(v) - 1
    faces.append([tip - 2, tip - 1, tip])
    return v, np.array(faces, dtype=np.int32)


LEAFLET_VERTS, LEAFLET_FACES = _leaflet_template()


def _polygon_area(v: np.ndarray) -> float:
    t = v[LEAFLET_FACES]
    a = t[:, 1] - t[:, 0]
    b = t[:, 2] - t[:, 0]
    return float(np.sum(0.5 * np.abs(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0])))


LEAFLET_AREA_FACTOR = _polygon_area(LEAFLET_VERTS)


def flat_leaves(
    base: np.ndarray, direction: np.ndarray, side: np.ndarray, length: np.ndarray, width: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Place the leaflet template many times.

    base (L, 3) attachment points; direction (L, 3) and side (L, 3) orthonormal in-plane axes
    (length and width directions); length, width (L,) in metres.
    Returns vertices (L·k, 3) and faces (L·t, 3) (indices local to the returned vertices).
    """
    n = len(base)
    k = len(LEAFLET_VERTS)
    ax = LEAFLET_VERTS[:, 0][None, :, None] * (length[:, None, None] * direction[:, None, :])
    ay = LEAFLET_VERTS[:, 1][None, :, None] * (width[:, None, None] * side[:, None, :])
    verts = (base[:, None, :] + ax + ay).reshape(-1, 3)
    faces = (LEAFLET_FACES[None] + (np.arange(n) * k)[:, None, None]).reshape(-1, 3)
    return verts, faces.astype(np.int32)


# A thin stem or petiole segment is a triangular prism without caps: 3 sides, 6 triangles.
_PRISM_SIDES = 3
_PRISM_FACES = np.array(
    [[i, (i + 1) % 3, 3 + i] for i in range(3)]
    + [[(i + 1) % 3, 3 + (i + 1) % 3, 3 + i] for i in range(3)],
    dtype=np.int32,
)
PRISM_N_FACES = len(_PRISM_FACES)


def prisms(
    start: np.ndarray, end: np.ndarray, r_start: np.ndarray, r_end: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Triangular prisms around segments start (S, 3) → end (S, 3) with radii (S,) at each end.
    Returns vertices (S·6, 3) and faces (S·6, 3)."""
    n = len(start)
    axis = end - start
    length = np.linalg.norm(axis, axis=1, keepdims=True)
    axis = axis / np.maximum(length, 1e-12)
    # any vector not parallel to the axis → first perpendicular
    helper = np.where(np.abs(axis[:, 2:3]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
    p1 = np.cross(axis, helper)
    p1 /= np.linalg.norm(p1, axis=1, keepdims=True)
    p2 = np.cross(axis, p1)
    ang = 2 * np.pi * np.arange(_PRISM_SIDES) / _PRISM_SIDES
    ring = np.cos(ang)[None, :, None] * p1[:, None, :] + np.sin(ang)[None, :, None] * p2[:, None, :]
    v0 = start[:, None, :] + r_start[:, None, None] * ring
    v1 = end[:, None, :] + r_end[:, None, None] * ring
    verts = np.concatenate([v0, v1], axis=1).reshape(-1, 3)
    faces = (_PRISM_FACES[None] + (np.arange(n) * 2 * _PRISM_SIDES)[:, None, None]).reshape(-1, 3)
    return verts, faces.astype(np.int32)


def strip_blades(
    midrib: np.ndarray, side: np.ndarray, half_width: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Leaf blades as strips of trapezoids along a midrib.

    midrib (B, s, 3) station points from base to tip; side (B, 3) unit lateral direction;
    half_width (B, s) half blade width at each station (the last station, the tip, must be 0 and
    gets a single vertex). Returns vertices (B·(2s-1), 3) and faces (B·(2s-3), 3): (s-2) quads of
    two triangles and one tip triangle per blade.
    """
    b, s, _ = midrib.shape
    left = midrib[:, :-1] + half_width[:, :-1, None] * side[:, None, :]
    right = midrib[:, :-1] - half_width[:, :-1, None] * side[:, None, :]
    pairs = np.stack([left, right], axis=2).reshape(b, 2 * (s - 1), 3)
    verts = np.concatenate([pairs, midrib[:, -1:]], axis=1)
    nv = 2 * s - 1
    q = np.arange(s - 2)
    l0, r0, l1, r1 = 2 * q, 2 * q + 1, 2 * q + 2, 2 * q + 3
    quads = np.concatenate([np.stack([l0, r0, r1], 1), np.stack([l0, r1, l1], 1)])
    tip = np.array([[2 * (s - 2), 2 * (s - 2) + 1, nv - 1]])
    template = np.concatenate([quads, tip]).astype(np.int32)
    faces = (template[None] + (np.arange(b) * nv)[:, None, None]).reshape(-1, 3)
    return verts.reshape(-1, 3), faces.astype(np.int32)


def unit(azimuth: np.ndarray, zenith: np.ndarray) -> np.ndarray:
    """(…, 3) unit vectors from azimuth (from +x, counter-clockwise) and angle from vertical."""
    sz = np.sin(zenith)
    return np.stack([sz * np.cos(azimuth), sz * np.sin(azimuth), np.cos(zenith)], axis=-1)


def horizontal_side(azimuth: np.ndarray) -> np.ndarray:
    """(…, 3) horizontal unit vectors 90° counter-clockwise of ``azimuth``."""
    return np.stack([-np.sin(azimuth), np.cos(azimuth), np.zeros_like(azimuth)], axis=-1)
