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
    if not isinstance(crop, str) or crop not in CROPS:
        raise ConfigError(f"unknown crop {crop!r}: choose one of {', '.join(CROPS)}")
    return crop


def param_space(crop: str) -> tuple[ParamSpec, ...]:
    return CROPS[check_crop(crop)]


def resolve_params(crop: str, given: Mapping[str, float] | None = None) -> dict[str, float]:
    """Complete ``given`` with the middle of each range; reject unknown names, non-finite values
    and values outside the range."""
    specs = {s.name: s for s in param_space(crop)}
    if given is not None and not isinstance(given, Mapping):
        raise ConfigError(f"{crop} parameters must map names to values, got {given!r}")
    given = dict(given or {})
    unknown = sorted(set(given) - set(specs))
    if unknown:
        raise ConfigError(
            f"unknown {crop} parameter {unknown[0]!r}: choose from {', '.join(specs)}"
        )
    out: dict[str, float] = {}
    for name, spec in specs.items():
        value = given.get(name, spec.middle)
        if isinstance(value, bool):  # float(True) is 1.0: no parameter is a yes or no
            raise ConfigError(f"{crop} parameter {name}={value!r} is not a number")
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


@dataclass(frozen=True, eq=False)
class ParamBox:
    """The box a fit searches: the crop's :func:`bounds`, narrowed by what the user already
    knows. ``limits`` maps a parameter to a known value (fixed, not fitted: e.g. the main-stem
    nodes counted in the field) or to ``[low, high]`` inside the model's range. The optimisers
    see only the free parameters (``bounds``, in :func:`param_space` order); :meth:`vector`
    and :meth:`params` put the fixed values back."""

    crop: str
    low: np.ndarray
    high: np.ndarray

    @classmethod
    def of(cls, crop: str, limits: Mapping[str, object] | None = None) -> ParamBox:
        """The crop's box with ``limits`` applied; unknown names, values that are not numbers,
        ``low > high``, limits outside the model's range and a box with nothing left to fit
        are named errors."""
        specs = param_space(crop)
        full = bounds(crop)
        low, high = full[:, 0].copy(), full[:, 1].copy()
        index = {s.name: i for i, s in enumerate(specs)}
        if limits is not None and not isinstance(limits, Mapping):
            raise ConfigError(
                f"the parameter box must map names to a value or [low, high], got {limits!r}"
            )
        for name, given in (limits or {}).items():
            if name not in index:
                raise ConfigError(
                    f"unknown {crop} parameter {name!r} in the parameter box: choose from "
                    f"{', '.join(index)}"
                )
            lo, hi = _limit_pair(crop, name, given)
            s = specs[index[name]]
            if lo > hi:
                raise ConfigError(f"{crop} parameter {name}: low {lo:g} is above high {hi:g}")
            if lo < s.low or hi > s.high:
                raise ConfigError(
                    f"{crop} parameter {name}: [{lo:g}, {hi:g}] reaches outside the model's "
                    f"range [{s.low:g}, {s.high:g}]"
                )
            low[index[name]], high[index[name]] = lo, hi
        if not np.any(low < high):
            raise ConfigError(f"every {crop} parameter is fixed: nothing is left to fit")
        return cls(crop, low, high)

    @property
    def free(self) -> np.ndarray:
        """(d,) bool: the parameters the optimiser varies."""
        return self.low < self.high

    @property
    def names(self) -> tuple[str, ...]:
        """The free parameters' names."""
        return tuple(s.name for s, f in zip(param_space(self.crop), self.free, strict=True) if f)

    @property
    def bounds(self) -> np.ndarray:
        """(k, 2) the free parameters' bounds: what the optimisers search."""
        f = self.free
        return np.column_stack([self.low[f], self.high[f]])

    @property
    def is_full(self) -> bool:
        """Whether this is the crop's whole box (nothing narrowed or fixed)."""
        return bool(np.array_equal(np.column_stack([self.low, self.high]), bounds(self.crop)))

    def vector(self, x: np.ndarray) -> np.ndarray:
        """(d,) every parameter from the free ones' (k,) values; free values are clipped onto
        the box."""
        x = np.asarray(x, dtype=np.float64)
        if x.shape != (int(self.free.sum()),):
            raise ConfigError(
                f"{self.crop} box has {int(self.free.sum())} free parameters, got a vector of "
                f"shape {x.shape}"
            )
        out = self.low.copy()
        out[self.free] = np.clip(x, self.low[self.free], self.high[self.free])
        return out

    def params(self, x: np.ndarray) -> dict[str, float]:
        """Every parameter by name from the free ones' values."""
        return params_from_vector(self.crop, self.vector(x))

    def spread(self, s: np.ndarray) -> dict[str, float]:
        """A per-free-parameter spread (k,) by name; 0 for the fixed parameters."""
        out = np.zeros(len(self.low))
        out[self.free] = np.asarray(s, dtype=np.float64)
        return {spec.name: float(v) for spec, v in zip(param_space(self.crop), out, strict=True)}

    def clip(self, params: Mapping[str, float]) -> dict[str, float]:
        """``params`` moved into the box (fixed parameters set to their values)."""
        x = np.clip(params_to_vector(self.crop, params), self.low, self.high)
        return params_from_vector(self.crop, x)


def is_range(given: object) -> bool:
    """Whether a parameter box entry (``ParamBox.of``'s ``limits`` value, as stored in a
    fit's config) is a searched ``[low, high]`` rather than a given value."""
    return isinstance(given, list | tuple)


def _limit_pair(crop: str, name: str, given: object) -> tuple[float, float]:
    if is_range(given) and len(given) == 2:
        pair = given
    elif is_range(given):
        raise ConfigError(
            f"{crop} parameter {name}: give a value or [low, high], got {len(given)} numbers"
        )
    else:
        pair = (given, given)
    try:
        lo, hi = (float(v) for v in pair)
    except (TypeError, ValueError):
        raise ConfigError(f"{crop} parameter {name}={given!r} is not a number") from None
    if (
        isinstance(pair[0], bool)
        or isinstance(pair[1], bool)
        or not (math.isfinite(lo) and math.isfinite(hi))
    ):
        raise ConfigError(f"{crop} parameter {name}={given!r} is not a finite number")
    return lo, hi
