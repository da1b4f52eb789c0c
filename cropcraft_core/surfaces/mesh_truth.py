"""The 'truth' surfaces backend: a known canopy mesh over a flat ground (tests, benchmarks).

It needs no photos: ``fit`` only records the cameras and the bounding box. Renders are exact
(Open3D ray casting of the canopy plus the ground plane z = ``ground_z``); colours are flat per
organ (``ORGAN_RGB``) and soil (``SOIL_RGB``), unshaded. The point cloud is what the fit cameras
see (each rendered at a quarter of its size and unprojected), as the paper samples its NeRF.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from cropcraft_core.errors import ConfigError
from cropcraft_core.geometry.camera import PinholeCamera
from cropcraft_core.geometry.mesh import CanopyMesh
from cropcraft_core.render.preview import ORGAN_RGB, SOIL_RGB
from cropcraft_core.render.raycast import build_scene, cast_rays
from cropcraft_core.surfaces.base import (
    Progress,
    SurfaceBackend,
    SurfacesConfig,
    check_inputs,
)

MESH_FILE = "truth_canopy.ply"
#: half size of the ground square (m) around the canopy's centre
GROUND_HALF_SIZE = 50.0


class TruthSurfaces(SurfaceBackend):
    """Exact visible surfaces of ``mesh`` (a ``CanopyMesh``) over the ground plane z =
    ``ground_z`` (omitted with ``ground=False``)."""

    name = "truth"

    def __init__(
        self,
        mesh: CanopyMesh | None = None,
        config: SurfacesConfig | None = None,
        ground_z: float = 0.0,
        ground: bool = True,
    ) -> None:
        super().__init__(config or SurfacesConfig(backend="truth"))
        if mesh is None and self.config.truth_mesh:
            from cropcraft_core.export import read_ply

            mesh = read_ply(self.config.truth_mesh)
        if not isinstance(mesh, CanopyMesh):
            raise ConfigError(
                "the truth surfaces backend needs the true CanopyMesh (make_backend(config, "
                "mesh=...) or SurfacesConfig.truth_mesh = a PLY path)"
            )
        self.mesh = mesh
        self.ground_z = float(ground_z)
        self.ground = bool(ground)
        self._build()

    def _build(self) -> None:
        v, f = self.mesh.vertices, self.mesh.faces
        n_canopy = len(f)
        colors = np.asarray([ORGAN_RGB.get(int(o), (200, 0, 200)) for o in range(3)], float)
        face_rgb = colors[np.clip(self.mesh.organ.astype(np.int64), 0, 2)]
        if self.ground:
            c = v[:, :2].mean(axis=0) if len(v) else np.zeros(2)
            g = GROUND_HALF_SIZE
            gv = np.array(
                [
                    [c[0] - g, c[1] - g],
                    [c[0] + g, c[1] - g],
                    [c[0] + g, c[1] + g],
                    [c[0] - g, c[1] + g],
                ]
            )
            gv = np.column_stack([gv, np.full(4, self.ground_z)])
            gf = np.array([[0, 1, 2], [0, 2, 3]]) + len(v)
            v = np.vstack([v, gv])
            f = np.vstack([f, gf]).astype(np.int32)
            face_rgb = np.vstack([face_rgb, np.tile(np.asarray(SOIL_RGB, float), (2, 1))])
        self._origin = v.mean(axis=0) if len(v) else np.zeros(3)
        self._scene = build_scene(v - self._origin, f)
        self._face_rgb = face_rgb.astype(np.uint8)
        self._n_canopy = n_canopy

    def fit(self, images, cameras, bbox=None, progress: Progress | None = None) -> None:
        """Record ``cameras`` and ``bbox``; the images are not used (they may be empty arrays
        of the right shape)."""
        _, cams, box = check_inputs(images, cameras, bbox)
        self.cameras, self.bbox = cams, box
        if progress:
            progress("truth", 1.0)

    def render_faces(self, camera: PinholeCamera) -> tuple[np.ndarray, np.ndarray]:
        """(depth (H, W) float32 z-depth, NaN where empty; face (H, W) int64: canopy face index,
        −2 for the ground, −1 for nothing)."""
        d = camera.ray_directions(normalized=False).reshape(-1, 3)
        t, prim = cast_rays(self._scene, camera.center - self._origin, d)
        depth = np.where(np.isfinite(t), t, np.nan).astype(np.float32)
        face = np.where(prim >= self._n_canopy, -2, prim)
        h, w = camera.height, camera.width
        return depth.reshape(h, w), face.reshape(h, w)

    def render(self, camera: PinholeCamera) -> tuple[np.ndarray, np.ndarray]:
        """Works before ``fit`` too (the truth needs no fitting)."""
        depth, face = self.render_faces(camera)
        rgb = np.zeros((*depth.shape, 3), np.uint8)
        hit = face != -1
        idx = np.where(face == -2, len(self._face_rgb) - 1, face)
        rgb[hit] = self._face_rgb[idx[hit]]
        return depth, rgb

    def point_cloud(self, n_max: int = 100_000) -> tuple[np.ndarray, np.ndarray]:
        return self.rendered_point_cloud(n_max)

    def _save_payload(self, folder: Path) -> dict:
        from cropcraft_core.export import write_ply

        write_ply(folder / MESH_FILE, self.mesh)
        return {"mesh": MESH_FILE, "ground_z": self.ground_z, "ground": self.ground}

    def _load_payload(self, folder: Path, meta: dict) -> None:
        from cropcraft_core.export import read_ply

        self.mesh = read_ply(folder / meta.get("mesh", MESH_FILE))
        self.ground_z = float(meta.get("ground_z", 0.0))
        self.ground = bool(meta.get("ground", True))
        self._build()
