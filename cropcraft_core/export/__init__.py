"""Exporters: crash-safe writes, PLY/OBJ/GLB mesh files and Helios XML."""

from cropcraft_core.export.atomic import (
    atomic_path,
    atomic_write_bytes,
    atomic_write_text,
    publish,
)
from cropcraft_core.export.helios import HELIOS_LABELS, helios_transforms, write_helios_xml
from cropcraft_core.export.meshio import (
    ORGAN_COLORS,
    PointCloud,
    read_geometry,
    read_ply,
    write_glb,
    write_obj,
    write_ply,
)

__all__ = [
    "HELIOS_LABELS",
    "ORGAN_COLORS",
    "PointCloud",
    "atomic_path",
    "atomic_write_bytes",
    "atomic_write_text",
    "helios_transforms",
    "publish",
    "read_geometry",
    "read_ply",
    "write_glb",
    "write_helios_xml",
    "write_obj",
    "write_ply",
]
