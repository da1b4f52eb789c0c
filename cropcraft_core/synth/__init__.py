"""Synthetic photo scenes with known truth (test data and the demo): ``make_scene``."""

from cropcraft_core.synth.scene import (
    TRAJECTORIES,
    camera_from_angles,
    drone_trajectory,
    face_colors,
    make_scene,
    render_view,
    views_region,
    walk_trajectory,
)

__all__ = [
    "TRAJECTORIES",
    "camera_from_angles",
    "drone_trajectory",
    "face_colors",
    "make_scene",
    "render_view",
    "views_region",
    "walk_trajectory",
]
