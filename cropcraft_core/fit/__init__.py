"""Fitting the procedural models to row observations (forward model, per-seed fits, aggregation,
and the MLP baseline)."""

from cropcraft_core.fit.fitting import (
    METHODS,
    FitConfig,
    FitResult,
    combine,
    fit_observation,
    fit_observations,
    fit_seed,
)
from cropcraft_core.fit.forward import ForwardModel, observe_canopy, row_frame_camera

__all__ = [
    "METHODS",
    "FitConfig",
    "FitResult",
    "ForwardModel",
    "combine",
    "fit_observation",
    "fit_observations",
    "fit_seed",
    "observe_canopy",
    "row_frame_camera",
]
