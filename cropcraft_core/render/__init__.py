"""Depth rendering and previews: numba z-buffer rasterizer, Open3D ray casting, shaded images.

The ray-casting names load Open3D on first use, so that the z-buffer and the previews without
shadows import on a host without it (the lent GPU machines, for the nerfacto acceptance test).
"""

from typing import Any

from cropcraft_core.render.preview import (
    depth_to_rgb,
    oblique_camera,
    save_png,
    shade_rgb,
)
from cropcraft_core.render.raster import depth_map, render_depth
from cropcraft_core.render.result import RenderResult

_RAYCAST = ("build_scene", "cast_rays", "raycast_depth")


def __getattr__(name: str) -> Any:
    if name in _RAYCAST:
        from cropcraft_core.render import raycast

        return getattr(raycast, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = [
    "RenderResult",
    "build_scene",
    "cast_rays",
    "depth_map",
    "depth_to_rgb",
    "oblique_camera",
    "raycast_depth",
    "render_depth",
    "save_png",
    "shade_rgb",
]
