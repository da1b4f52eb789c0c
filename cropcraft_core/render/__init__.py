"""Depth rendering and previews: numba z-buffer rasterizer, Open3D ray casting, shaded images."""

from cropcraft_core.render.raycast import build_scene, cast_rays, raycast_depth
from cropcraft_core.render.result import RenderResult

__all__ = ["RenderResult", "build_scene", "cast_rays", "raycast_depth"]
