"""Row fitting: ground plane, crop rows, gravity/metric alignment and the row camera."""

from cropcraft_core.rowfit.fit import (
    SCALE_SOURCES,
    Row,
    RowFit,
    RowFitError,
    ScaleEstimate,
    estimate_scale_from_rows,
    fit_ground_and_rows,
    fit_rows_with_scale,
    voxel_downsample,
)
from cropcraft_core.rowfit.lab import srgb_to_lab
from cropcraft_core.rowfit.presets import RowFitPreset, preset

__all__ = [
    "SCALE_SOURCES",
    "Row",
    "RowFit",
    "RowFitError",
    "RowFitPreset",
    "ScaleEstimate",
    "estimate_scale_from_rows",
    "fit_ground_and_rows",
    "fit_rows_with_scale",
    "preset",
    "srgb_to_lab",
    "voxel_downsample",
]
