"""Ray casting with Open3D's Embree-backed ``RaycastingScene`` (CPU).

This is the reference renderer and the tool for arbitrary rays (shadow rays, ground probes). For
the many depth maps of a scene fit use the faster ``cropcraft_core.render.raster.depth_map``.

Open3D computes in float32: origins, directions and vertices are rounded to ~7 significant
digits, so keep coordinates near the origin (``raycast_depth`` recentres on the camera itself).
"""

from __future__ import annotations

import numpy as np
import open3d as o3d

from cropcraft_core.errors import GeometryError
from cropcraft_core.geometry.camera import PinholeCamera
from cropcraft_core.render.result import (
    RenderResult,
    as_vertices_faces,
    check_near,
    check_vertices_faces,
)

_INVALID_ID = o3d.t.geometry.RaycastingScene.INVALID_ID


def build_scene(vertices: np.ndarray, faces: np.ndarray) -> o3d.t.geometry.RaycastingScene:
    """An Open3D ``RaycastingScene`` holding one triangle mesh.

    vertices: (n, 3) float, metres (converted to float32).  faces: (m, 3) int indices.
    Face ``i`` of the input is primitive ``i`` of the scene. An empty mesh gives an empty scene
    (every ray misses).
    """
    v, f = check_vertices_faces(vertices, faces)
    scene = o3d.t.geometry.RaycastingScene()
    if len(f):
        scene.add_triangles(
            o3d.core.Tensor(v.astype(np.float32)),
            o3d.core.Tensor(f.astype(np.uint32)),
        )
    return scene


def cast_rays(
    scene: o3d.t.geometry.RaycastingScene,
    origins: np.ndarray,
    directions: np.ndarray,
    nthreads: int = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """First hits of rays ``origins + t * directions`` (t ≥ 0).

    origins, directions: (n, 3) float (or (3,) for a shared origin/direction); directions need not
    be unit length: ``t`` is in units of each direction's length.
    Returns ``(t_hit (n,) float64, inf where the ray misses; face_id (n,) int64, -1 on a miss)``.
    ``nthreads=0`` lets Open3D use every core.
    """
    d = np.asarray(directions, dtype=np.float64)
    o = np.asarray(origins, dtype=np.float64)
    if d.ndim == 1:
        d = d[None, :]
    if o.ndim == 1:
        o = o[None, :]
    if d.ndim != 2 or d.shape[1] != 3 or o.ndim != 2 or o.shape[1] != 3:
        raise GeometryError(
            f"origins and directions must be (n, 3) arrays, got {o.shape} and {d.shape}"
        )
    n = max(len(o), len(d))
    if len(o) not in (1, n) or len(d) not in (1, n):
        raise GeometryError(f"origins ({len(o)}) and directions ({len(d)}) differ in length")
    if not (np.all(np.isfinite(o)) and np.all(np.isfinite(d))):
        raise GeometryError("ray origins and directions must be finite")
    rays = np.empty((n, 6), dtype=np.float32)
    rays[:, :3] = o
    rays[:, 3:] = d
    if n == 0:
        return np.zeros(0), np.zeros(0, np.int64)
    ans = scene.cast_rays(o3d.core.Tensor(rays), nthreads=nthreads)
    t_hit = ans["t_hit"].numpy().astype(np.float64)
    prim = ans["primitive_ids"].numpy().astype(np.int64)
    miss = (prim == _INVALID_ID) | ~np.isfinite(t_hit)
    t_hit[miss] = np.inf
    prim[miss] = -1
    return t_hit, prim


def raycast_depth(
    mesh_or_vf: object,
    camera: PinholeCamera,
    near: float | None = None,
    nthreads: int = 0,
) -> RenderResult:
    """Reference z-depth render: one ray per pixel centre of ``camera``.

    mesh_or_vf: a ``CanopyMesh`` or ``(vertices (n, 3), faces (m, 3))``.
    near: if given, faces with any vertex nearer than ``near`` (camera z-depth, metres) are
    dropped first, exactly as ``render_depth`` does; by default every face is kept.
    Returns a ``RenderResult`` with depth (H, W) float32 (NaN for background) and face_id (H, W)
    int32 (-1 for background). The scene is built per call (recentred on the camera for float32
    precision); for many views of one mesh use ``build_scene`` / ``cast_rays``.
    """
    if not isinstance(camera, PinholeCamera):
        raise GeometryError(f"camera must be a PinholeCamera, got {type(camera).__name__}")
    vertices, faces = as_vertices_faces(mesh_or_vf)
    face_index = np.arange(len(faces))
    if near is not None:
        check_near(near)
        z = camera.to_camera(vertices)[:, 2]
        keep = np.all(z[faces] >= near, axis=1) if len(faces) else np.zeros(0, bool)
        faces, face_index = faces[keep], face_index[keep]
    scene = build_scene(vertices - camera.center, faces)
    d = camera.ray_directions(normalized=False).reshape(-1, 3)  # unit camera-z: t = z-depth
    t_hit, prim = cast_rays(scene, np.zeros(3), d, nthreads=nthreads)
    h, w = camera.height, camera.width
    depth = np.where(np.isfinite(t_hit), t_hit, np.nan).astype(np.float32).reshape(h, w)
    fid = np.where(prim >= 0, face_index[np.maximum(prim, 0)] if len(faces) else -1, -1)
    return RenderResult(depth=depth, face_id=fid.astype(np.int32).reshape(h, w), camera=camera)
