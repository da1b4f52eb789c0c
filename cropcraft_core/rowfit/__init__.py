"""Row fitting: ground plane, crop rows, gravity/metric alignment and the row camera."""

from cropcraft_core.rowfit.fit import (
    SCALE_SOURCES,
    Row,
    RowFit,
    RowFitError,
    ScaleEstimate,
    camera_to_scene,
    estimate_scale_from_rows,
    fit_ground_and_rows,
    fit_rows_with_scale,
    voxel_downsample,
)
from cropcraft_core.rowfit.lab import srgb_to_lab
from cropcraft_core.rowfit.neighbours import (
    MAX_NEIGHBOURS,
    RowView,
    neighbour_row_views,
    row_label,
)
from cropcraft_core.rowfit.presets import RowFitPreset, preset

__all__ = [
    "MAX_NEIGHBOURS",
    "SCALE_SOURCES",
    "Row",
    "RowFit",
    "RowFitError",
    "RowFitPreset",
    "RowView",
    "ScaleEstimate",
    "camera_to_scene",
    "estimate_scale_from_rows",
    "fit_ground_and_rows",
    "fit_rows_with_scale",
    "neighbour_row_views",
    "preset",
    "row_label",
    "srgb_to_lab",
    "voxel_downsample",
]
