"""Visible surfaces of a posed photo scene (the paper's NeRF stage): point cloud and renders.

``make_backend(SurfacesConfig(backend=...))`` → ``fit(images, cameras, bbox)`` →
``point_cloud(n_max)`` / ``render(camera)`` / ``save(dir)``; ``load_surfaces(dir)`` reads any
saved backend back. See ``cropcraft_core.surfaces.base``.
"""

from cropcraft_core.surfaces.base import (
    BACKENDS,
    CROP_SURFACES,
    NERF_PAPER,
    SurfaceBackend,
    SurfacesConfig,
    SurfacesError,
    load_surfaces,
    make_backend,
    prediction_blur_m,
    resolve_bbox,
    views_in_box,
)

__all__ = [
    "BACKENDS",
    "CROP_SURFACES",
    "NERF_PAPER",
    "SurfaceBackend",
    "SurfacesConfig",
    "SurfacesError",
    "load_surfaces",
    "make_backend",
    "prediction_blur_m",
    "resolve_bbox",
    "views_in_box",
]
