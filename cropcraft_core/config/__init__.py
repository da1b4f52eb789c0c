"""Parameter spaces, canopy layouts and per-crop presets (the paper's supplementary values)."""

from cropcraft_core.config.layout import CanopyLayout, default_layout
from cropcraft_core.config.params import (
    CROPS,
    ParamBox,
    ParamSpec,
    param_space,
    params_from_vector,
    params_to_vector,
    resolve_params,
)

__all__ = [
    "CROPS",
    "CanopyLayout",
    "ParamBox",
    "ParamSpec",
    "default_layout",
    "param_space",
    "params_from_vector",
    "params_to_vector",
    "resolve_params",
]
