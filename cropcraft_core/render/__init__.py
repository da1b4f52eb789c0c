"""Depth rendering and previews: numba z-buffer rasterizer, Open3D ray casting, shaded images."""

from cropcraft_core.render.preview import (
    depth_to_rgb,
    oblique_camera,
    save_png,
    shade_rgb,
)
from cropcraft_core.render.raster import render_depth
from cropcraft_core.render.raycast import build_scene, cast_rays, raycast_depth
from cropcraft_core.render.result import RenderResult

__all__ = [
    "RenderResult",
    "build_scene",
    "cast_rays",
    "depth_to_rgb",
    "oblique_camera",
    "raycast_depth",
    "render_depth",
    "save_png",
    "shade_rgb",
]
