"""Accumulates labelled geometry parts into one ``CanopyMesh`` and node records."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from cropcraft_core.geometry.mesh import CanopyMesh, Organ


@dataclass
class NodeRecords:
    """Per-node arrays (see ``Canopy``)."""

    plant: np.ndarray
    node_id: np.ndarray
    stem: np.ndarray
    xyz: np.ndarray
    internode: np.ndarray


@dataclass
class MeshBuilder:
    _v: list = field(default_factory=list)
    _f: list = field(default_factory=list)
    _organ: list = field(default_factory=list)
    _plant: list = field(default_factory=list)
    _node: list = field(default_factory=list)
    _nv: int = 0

    def add(
        self,
        verts: np.ndarray,
        faces: np.ndarray,
        organ: Organ,
        instance_plant: np.ndarray,
        instance_node: np.ndarray,
        faces_per_instance: int,
    ) -> None:
        """Add ``verts`` (n, 3) / ``faces`` (m, 3) made of instances of ``faces_per_instance``
        faces each, labelled by per-instance plant and node ids."""
        if len(faces) == 0:
            return
        self._v.append(verts)
        self._f.append(faces + self._nv)
        self._nv += len(verts)
        self._organ.append(np.full(len(faces), int(organ), np.uint8))
        self._plant.append(np.repeat(instance_plant.astype(np.int32), faces_per_instance))
        self._node.append(np.repeat(instance_node.astype(np.int32), faces_per_instance))

    def build(self) -> CanopyMesh:
        if not self._f:
            return CanopyMesh.empty()
        return CanopyMesh(
            vertices=np.concatenate(self._v),
            faces=np.concatenate(self._f).astype(np.int32, copy=False),
            organ=np.concatenate(self._organ),
            plant=np.concatenate(self._plant),
            node=np.concatenate(self._node),
        )
