"""Labelled meshes, pinhole cameras and rigid transforms."""

from cropcraft_core.geometry.camera import PinholeCamera
from cropcraft_core.geometry.mesh import ORGAN_NAMES, CanopyMesh, Organ

__all__ = ["ORGAN_NAMES", "CanopyMesh", "Organ", "PinholeCamera"]
