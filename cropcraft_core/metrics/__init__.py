"""Canopy metrics: traits with units and definitions, instrument-style LAI, and the paper's errors.

``canopy_metrics(canopy)`` gives the flat, JSON-ready dict that goes into ``metrics.json``;
``gap_fraction_lai`` "measures" a mesh like an LAI-2200; ``evaluate`` scores predicted against true
metric dicts with the paper's LAIE, LAIPE, AME, ASDE, NDPE and NCPE.
"""

from cropcraft_core.metrics.evaluation import (
    ERROR_KEYS,
    evaluate,
    mean_abs_percent_error,
    rmse,
)
from cropcraft_core.metrics.gap_fraction import (
    RING_WEIGHTS,
    RING_ZENITH_DEG,
    BorderWarning,
    GapFractionResult,
    SensorRegion,
    canopy_gap_fraction,
    gap_fraction_lai,
    lai_from_transmittance,
    ring_directions,
    sensor_points,
)
from cropcraft_core.metrics.traits import (
    HEADLINE_TRAITS,
    LEAFLETS_PER_NODE,
    REFERENCE_DISTRIBUTIONS,
    Trait,
    beta_fit,
    canopy_metrics,
    canopy_traits,
    join_metrics,
    leaf_angle_histogram,
    leaf_inclinations,
    nearest_reference_distribution,
    traits_to_dict,
    weighted_angle_stats,
)

__all__ = [
    "HEADLINE_TRAITS",
    "ERROR_KEYS",
    "LEAFLETS_PER_NODE",
    "REFERENCE_DISTRIBUTIONS",
    "RING_WEIGHTS",
    "RING_ZENITH_DEG",
    "BorderWarning",
    "GapFractionResult",
    "SensorRegion",
    "Trait",
    "beta_fit",
    "canopy_gap_fraction",
    "canopy_metrics",
    "canopy_traits",
    "evaluate",
    "gap_fraction_lai",
    "join_metrics",
    "lai_from_transmittance",
    "leaf_angle_histogram",
    "leaf_inclinations",
    "mean_abs_percent_error",
    "nearest_reference_distribution",
    "ring_directions",
    "rmse",
    "sensor_points",
    "traits_to_dict",
    "weighted_angle_stats",
]
