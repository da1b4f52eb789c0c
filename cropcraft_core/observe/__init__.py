"""Row observations, their histogram statistics and the CropCraft histogram loss.

An :class:`Observation` holds a row-camera depth map, foreground mask, optional RGB render, the
row camera and the :class:`HistogramStats` of the foreground (z-depth, lateral |y| and
depth-derivative histograms, mask area). :func:`loss` compares an observation's statistics with
a procedural render's (``Observation.loss_of(depth)`` does both steps). All settings live in
per-crop presets: ``preset("soybean", **overrides)``.
"""

from cropcraft_core.observe.histograms import (
    HistogramStats,
    bin_edges,
    blur_depth,
    compute_stats,
    mean_stats,
)
from cropcraft_core.observe.loss import LossBreakdown, loss
from cropcraft_core.observe.observation import (
    NO_SURFACE_REFUSE,
    NO_SURFACE_WARN,
    Observation,
    check_coverage,
    check_row_camera,
    coverage_warning,
    no_surface_fraction,
    observation_mask,
    observe_views,
    predicted_mask,
)
from cropcraft_core.observe.presets import (
    CROPS,
    LossPreset,
    ObservePreset,
    check_prediction_blur,
    clear_render_height,
    observed_clearance,
    preset,
    resolve_depth_range,
    soybean_render_height,
    with_overrides,
)

__all__ = [
    "CROPS",
    "NO_SURFACE_REFUSE",
    "NO_SURFACE_WARN",
    "HistogramStats",
    "LossBreakdown",
    "LossPreset",
    "Observation",
    "ObservePreset",
    "bin_edges",
    "blur_depth",
    "check_coverage",
    "check_prediction_blur",
    "check_row_camera",
    "compute_stats",
    "coverage_warning",
    "no_surface_fraction",
    "loss",
    "mean_stats",
    "observation_mask",
    "observe_views",
    "predicted_mask",
    "preset",
    "resolve_depth_range",
    "clear_render_height",
    "observed_clearance",
    "soybean_render_height",
    "with_overrides",
]
