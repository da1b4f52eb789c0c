"""The procedural models' free parameters and their ranges (supplementary Tables
"Soybean/Maize model parameter ranges")."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from cropcraft_core.errors import ConfigError


@dataclass(frozen=True)
class ParamSpec:
    """One optimisable parameter: its name, closed range and meaning."""

    name: str
    low: float
    high: float
    doc: str

    @property
    def middle(self) -> float:
        return 0.5 * (self.low + self.high)


CROPS: dict[str, tuple[ParamSpec, ...]] = {
    "soybean": (
        ParamSpec("leaf_length", 0.5, 1.5, "multiplier on leaflet length and width"),
        ParamSpec("petiole_length", 0.5, 2.0, "multiplier on petiole length"),
        ParamSpec("petiole_angle", 0.5, 4.0, "multiplier on petiole angle from vertical"),
        ParamSpec("internode_length", 0.5, 2.0, "multiplier on internode length"),
        ParamSpec("num_nodes", 1.0, 14.0, "main-stem trifoliate nodes (fractional: last scaled)"),
    ),
    "maize": (
        ParamSpec("leaf_length", 0.8, 1.2, "multiplier on leaf length and width"),
        ParamSpec("leaf_order_shift", -4.0, 4.0, "additive shift of leaf order in the bending law"),
        ParamSpec("internode_length", 0.8, 1.2, "multiplier on internode length"),
        ParamSpec("num_nodes", 1.0, 18.0, "main-stem leaves (fractional: last scaled)"),
    ),
}


def check_crop(crop: str) -> str:
    if crop not in CROPS:
        raise ConfigError(f"unknown crop {crop!r}: choose one of {', '.join(CROPS)}")
    return crop


def param_space(crop: str) -> tuple[ParamSpec, ...]:
    return CROPS[check_crop(crop)]


def resolve_params(crop: str, given: Mapping[str, float] | None = None) -> dict[str, float]:
    """Complete ``given`` with the middle of each range; reject unknown names, non-finite values
    and values outside the range."""
    specs = {s.name: s for s in param_space(crop)}
    given = dict(given or {})
    unknown = sorted(set(given) - set(specs))
    if unknown:
        raise ConfigError(
            f"unknown {crop} parameter {unknown[0]!r}: choose from {', '.join(specs)}"
        )
    out: dict[str, float] = {}
    for name, spec in specs.items():
        value = given.get(name, spec.middle)
        try:
            value = float(value)
        except (TypeError, ValueError):
            raise ConfigError(f"{crop} parameter {name}={value!r} is not a number") from None
        if not math.isfinite(value) or not spec.low <= value <= spec.high:
            raise ConfigError(
                f"{crop} parameter {name}={value:g} is outside its range "
                f"[{spec.low:g}, {spec.high:g}]"
            )
        out[name] = value
    return out


def params_to_vector(crop: str, params: Mapping[str, float]) -> np.ndarray:
    return np.array([params[s.name] for s in param_space(crop)], dtype=np.float64)


#: Rounding excursion past a parameter's bound (as a fraction of its range) that
#: :func:`params_from_vector` moves back onto the bound: arithmetic on points of the box (the
#: mean of seeds' points, ``low + range * 1.0``) can land an ulp outside it (a maize fit's
#: re-scoring once failed on internode_length 0.8 "outside [0.8, 1.2]").
ROUNDING_TOLERANCE = 1e-9


def params_from_vector(crop: str, x: np.ndarray) -> dict[str, float]:
    """Parameters by name from a vector in :func:`param_space` order; values past a bound by
    no more than rounding (:data:`ROUNDING_TOLERANCE` of the range) are set on the bound,
    farther ones are left for :func:`resolve_params` to name."""
    specs = param_space(crop)
    if len(x) != len(specs):
        raise ConfigError(f"{crop} takes {len(specs)} parameters, got a vector of {len(x)}")
    out = {}
    for s, v in zip(specs, x, strict=True):
        v, tol = float(v), ROUNDING_TOLERANCE * (s.high - s.low)
        if s.low - tol <= v < s.low:
            v = s.low
        elif s.high < v <= s.high + tol:
            v = s.high
        out[s.name] = v
    return out


def bounds(crop: str) -> np.ndarray:
    """(d, 2) lower/upper bounds in parameter order."""
    return np.array([[s.low, s.high] for s in param_space(crop)], dtype=np.float64)
