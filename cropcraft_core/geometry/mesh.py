"""Organ-labelled triangle meshes.

A ``CanopyMesh`` is plain arrays: vertices (n, 3) float64 in metres (world frame, z up, ground at
z = 0), faces (m, 3) int32, and per face the organ (``Organ``), the plant id and the node id.
Node ids are unique within a plant: main-stem nodes are 0 .. n_main-1 from the bottom, branch nodes
follow (see ``cropcraft_core.procedural``); faces of a stem segment carry the node at its top.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum

import numpy as np

from cropcraft_core.errors import GeometryError


class Organ(IntEnum):
    LEAF = 0
    PETIOLE = 1
    STEM = 2


ORGAN_NAMES = {Organ.LEAF: "leaf", Organ.PETIOLE: "petiole", Organ.STEM: "stem"}


@dataclass(frozen=True, eq=False)
class CanopyMesh:
    """Triangle soup with per-face labels.

    vertices: (n, 3) float64, metres.  faces: (m, 3) int32 indices into vertices.
    organ: (m,) uint8 ``Organ``.  plant: (m,) int32.  node: (m,) int32.
    """

    vertices: np.ndarray
    faces: np.ndarray
    organ: np.ndarray
    plant: np.ndarray
    node: np.ndarray

    def __post_init__(self) -> None:
        m = len(self.faces)
        if self.vertices.ndim != 2 or self.vertices.shape[1] != 3:
            raise GeometryError(f"vertices must be (n, 3), got {self.vertices.shape}")
        if self.faces.ndim != 2 or self.faces.shape[1] != 3:
            raise GeometryError(f"faces must be (m, 3), got {self.faces.shape}")
        if len(self.faces) and not np.issubdtype(self.faces.dtype, np.integer):
            # float indices were cut (1.9 -> 1) by the writers and failed as raw IndexErrors
            raise GeometryError(f"faces must be integer vertex indices, got {self.faces.dtype}")
        for name in ("organ", "plant", "node"):
            if getattr(self, name).shape != (m,):
                raise GeometryError(f"{name} must have one entry per face ({m})")

    @property
    def n_faces(self) -> int:
        return len(self.faces)

    def triangles(self) -> np.ndarray:
        """(m, 3, 3) float64 corner coordinates of every face."""
        return self.vertices[self.faces]

    def face_areas(self) -> np.ndarray:
        """(m,) float64 triangle areas in m²."""
        t = self.triangles()
        return 0.5 * np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1)

    def face_normals(self) -> np.ndarray:
        """(m, 3) float64 unit normals (zero for degenerate faces)."""
        t = self.triangles()
        n = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
        norm = np.linalg.norm(n, axis=1, keepdims=True)
        return np.divide(n, norm, out=np.zeros_like(n), where=norm > 0)

    def select(self, mask: np.ndarray) -> CanopyMesh:
        """The sub-mesh of the faces where ``mask`` (m,) bool is true, vertices compacted."""
        faces = self.faces[mask]
        used, inverse = np.unique(faces, return_inverse=True)
        return CanopyMesh(
            vertices=self.vertices[used],
            faces=inverse.reshape(-1, 3).astype(np.int32),
            organ=self.organ[mask],
            plant=self.plant[mask],
            node=self.node[mask],
        )

    @staticmethod
    def concatenate(parts: list[CanopyMesh]) -> CanopyMesh:
        parts = [p for p in parts if p.n_faces]
        if not parts:
            return CanopyMesh.empty()
        offsets = np.cumsum([0] + [len(p.vertices) for p in parts[:-1]])
        return CanopyMesh(
            vertices=np.concatenate([p.vertices for p in parts]),
            faces=np.concatenate([p.faces + o for p, o in zip(parts, offsets, strict=True)]).astype(
                np.int32
            ),
            organ=np.concatenate([p.organ for p in parts]),
            plant=np.concatenate([p.plant for p in parts]),
            node=np.concatenate([p.node for p in parts]),
        )

    @staticmethod
    def empty() -> CanopyMesh:
        return CanopyMesh(
            vertices=np.zeros((0, 3)),
            faces=np.zeros((0, 3), np.int32),
            organ=np.zeros(0, np.uint8),
            plant=np.zeros(0, np.int32),
            node=np.zeros(0, np.int32),
        )

    def validate(self) -> None:
        """Raise ``GeometryError`` unless finite, indexed in range and non-degenerate."""
        if not np.all(np.isfinite(self.vertices)):
            raise GeometryError("mesh has non-finite vertices")
        if self.n_faces and (self.faces.min() < 0 or self.faces.max() >= len(self.vertices)):
            raise GeometryError("mesh faces index outside the vertex array")
        if self.n_faces and not np.all(self.face_areas() > 0):
            raise GeometryError(f"mesh has {int(np.sum(self.face_areas() <= 0))} degenerate faces")
        if not np.isin(self.organ, [int(o) for o in Organ]).all():
            raise GeometryError("mesh has faces with an unknown organ label")
