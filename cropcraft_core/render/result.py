"""The result type shared by every depth renderer (numba rasterizer and Open3D ray caster).

A ``RenderResult`` holds, per pixel of an (H, W) image, the z-depth of the nearest surface (metres
along the camera's optical axis, NaN for background) and the index of the face seen there (-1 for
background). Everything else (normals, 3D points, masks) derives from these two arrays plus the
mesh and camera.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from cropcraft_core.errors import GeometryError
from cropcraft_core.geometry.camera import PinholeCamera
from cropcraft_core.geometry.mesh import CanopyMesh


def as_vertices_faces(mesh_or_vf: object) -> tuple[np.ndarray, np.ndarray]:
    """Accept a ``CanopyMesh`` or a ``(vertices, faces)`` pair; return validated contiguous
    ``(vertices (n, 3) float64, faces (m, 3) int32)``.

    Raises ``GeometryError`` for wrong shapes, non-finite vertices or out-of-range indices.
    """
    if isinstance(mesh_or_vf, CanopyMesh):
        vertices, faces = mesh_or_vf.vertices, mesh_or_vf.faces
    elif isinstance(mesh_or_vf, tuple | list) and len(mesh_or_vf) == 2:
        vertices, faces = mesh_or_vf
    else:
        raise GeometryError(
            f"expected a CanopyMesh or a (vertices, faces) pair, got {type(mesh_or_vf).__name__}"
        )
    return check_vertices_faces(vertices, faces)


def check_vertices_faces(vertices: object, faces: object) -> tuple[np.ndarray, np.ndarray]:
    """Validate and convert to ``(vertices (n, 3) float64, faces (m, 3) int32)``, C-contiguous."""
    v = np.ascontiguousarray(vertices, dtype=np.float64)
    f_in = np.asarray(faces)
    if v.ndim != 2 or v.shape[1] != 3:
        raise GeometryError(f"vertices must be an (n, 3) array, got shape {v.shape}")
    if f_in.ndim != 2 or f_in.shape[1] != 3:
        raise GeometryError(f"faces must be an (m, 3) array, got shape {f_in.shape}")
    if f_in.size and not np.issubdtype(f_in.dtype, np.integer):
        raise GeometryError(f"faces must hold integer vertex indices, got dtype {f_in.dtype}")
    if not np.all(np.isfinite(v)):
        raise GeometryError(f"vertices contain {int(np.sum(~np.isfinite(v)))} non-finite values")
    if f_in.size and (f_in.min() < 0 or f_in.max() >= len(v)):
        raise GeometryError(
            f"faces index vertices in [{f_in.min()}, {f_in.max()}] but there are only {len(v)}"
        )
    f = np.ascontiguousarray(f_in, dtype=np.int32)
    return v, f


def _face_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(m, 3) float64 unit normals (right-hand rule on the face's vertex order, zero if
    degenerate)."""
    t = vertices[faces]
    n = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    return np.divide(n, norm, out=np.zeros_like(n), where=norm > 0)


@dataclass(frozen=True, eq=False)
class RenderResult:
    """Per-pixel z-depth and face index of one rendered view.

    depth: (H, W) float32 z-depth in metres, NaN where no face is seen (background).
    face_id: (H, W) int32 index into the mesh's faces, -1 for background.
    camera: the ``PinholeCamera`` the view was rendered with (optional; needed by ``points`` and
    by ``normals(..., toward_camera=True)``).
    """

    depth: np.ndarray
    face_id: np.ndarray
    camera: PinholeCamera | None = None

    def __post_init__(self) -> None:
        if self.depth.ndim != 2 or self.depth.shape != self.face_id.shape:
            raise GeometryError(
                f"depth {self.depth.shape} and face_id {self.face_id.shape} must be the same "
                "(H, W) shape"
            )

    @property
    def shape(self) -> tuple[int, int]:
        """(H, W) of the image."""
        return self.depth.shape  # type: ignore[return-value]

    @property
    def mask(self) -> np.ndarray:
        """(H, W) bool, true where a face is seen (finite depth)."""
        return np.isfinite(self.depth)

    @property
    def coverage(self) -> float:
        """Fraction of pixels where a face is seen."""
        return float(np.mean(self.mask))

    def normals(self, mesh_or_vf: object, toward_camera: bool = False) -> np.ndarray:
        """(H, W, 3) float64 unit world-frame face normals of the face seen at each pixel, NaN for
        background.

        ``mesh_or_vf`` is the ``CanopyMesh`` (or ``(vertices, faces)``) that was rendered. Normals
        follow the right-hand rule on each face's vertex order; with ``toward_camera=True`` they
        are flipped where needed to face the camera (two-sided surfaces such as leaves).
        """
        vertices, faces = as_vertices_faces(mesh_or_vf)
        fid = self.face_id
        if fid.size and fid.max() >= len(faces):
            raise GeometryError(
                f"render refers to face {int(fid.max())} but the mesh has only {len(faces)} faces;"
                " pass the mesh that was rendered"
            )
        fn = _face_normals(vertices, faces)
        out = np.full((*fid.shape, 3), np.nan)
        hit = fid >= 0
        out[hit] = fn[fid[hit]]
        if toward_camera:
            if self.camera is None:
                raise GeometryError("toward_camera=True needs the RenderResult's camera")
            rays = self.camera.ray_directions(normalized=False)
            flip = np.sum(out * rays, axis=-1) > 0
            out[flip] *= -1.0
        return out

    def points(self) -> np.ndarray:
        """(H, W, 3) float64 world points of the seen surfaces, NaN for background."""
        if self.camera is None:
            raise GeometryError("points() needs the RenderResult's camera")
        return self.camera.unproject(self.depth.astype(np.float64))


def check_near(near: object) -> None:
    """A GeometryError unless ``near`` is a positive finite distance (metres), as both
    renderers take it (NaN or inf dropped every face and rendered an empty view)."""
    ok = isinstance(near, (int, float, np.integer, np.floating)) and not isinstance(near, bool)
    if not (ok and near > 0 and math.isfinite(near)):
        raise GeometryError(f"near must be a positive finite distance in metres, got {near!r}")
