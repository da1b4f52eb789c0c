"""Where plants stand: plot size, rows, planting density, row direction.

World frame: z up, ground z = 0, plot centred on the origin. With ``row_azimuth_deg = 0`` rows run
along x; ``plot_length`` is the extent along the rows, ``plot_width`` across them. Rows sit at
y = k · row_spacing (one row passes through the plot centre, where the row camera looks).
Defaults follow Midwest practice (domain-facts.md): soybean 0.76 m rows at 27.5 plants/m²,
maize 0.76 m rows at 8.25 plants/m².
"""

from __future__ import annotations

import math
import numbers
from dataclasses import asdict, dataclass, replace

from cropcraft_core.errors import ConfigError


@dataclass(frozen=True)
class CanopyLayout:
    plot_length: float = 2.0
    """extent of the measured plot along the rows (m)"""
    plot_width: float = 2.0
    """extent of the measured plot across the rows (m)"""
    row_spacing: float = 0.76
    """distance between rows (m)"""
    density: float = 27.5
    """plants per m² of ground"""
    row_azimuth_deg: float = 0.0
    """direction of the rows in the world xy plane, degrees from +x"""
    jitter_along: float = 0.25
    """standard deviation of a plant's position along its row, as a fraction of in-row spacing"""
    jitter_across: float = 0.01
    """standard deviation of a plant's position across its row (m)"""
    margin: float = 1.0
    """planted border around the plot (m), so that views of the plot centre see no edge"""

    def __post_init__(self) -> None:
        # numbers of any real type (numpy's stored as floats, for JSON); a bool is no length
        # (``true`` in a settings file was a 1 m margin)
        for name in ("plot_length", "plot_width", "row_spacing", "density"):
            v = getattr(self, name)
            if not (_real(v) and math.isfinite(v) and v > 0):
                raise ConfigError(f"{name.replace('_', ' ')} must be a positive number, got {v!r}")
            _plain(self, name)
        for name in ("jitter_along", "jitter_across", "margin"):
            v = getattr(self, name)
            if not (_real(v) and math.isfinite(v) and v >= 0):
                raise ConfigError(
                    f"{name.replace('_', ' ')} must be a non-negative number, got {v!r}"
                )
            _plain(self, name)
        a = self.row_azimuth_deg
        if not (_real(a) and math.isfinite(a)):
            raise ConfigError(f"row azimuth must be a number of degrees, got {a!r}")
        _plain(self, "row_azimuth_deg")
        if self.plot_width < self.row_spacing:
            raise ConfigError(
                f"plot width {self.plot_width:g} m holds no full row at row spacing "
                f"{self.row_spacing:g} m"
            )
        if self.plot_length < self.in_row_spacing:
            raise ConfigError(
                f"plot length {self.plot_length:g} m holds no plant at {self.density:g} plants "
                f"per m² and row spacing {self.row_spacing:g} m (one per "
                f"{self.in_row_spacing:.3g} m along the row)"
            )

    @property
    def in_row_spacing(self) -> float:
        """Distance between plants along a row (m)."""
        return 1.0 / (self.density * self.row_spacing)

    def with_(self, **changes) -> CanopyLayout:
        return replace(self, **changes)

    def to_dict(self) -> dict:
        return asdict(self)


def _real(v: object) -> bool:
    return isinstance(v, numbers.Real) and not isinstance(v, bool)


def _plain(layout: CanopyLayout, name: str) -> None:
    """A numpy number as a float; Python's ints and floats as given (their JSON, and so the
    stored scenes' cache keys, unchanged)."""
    v = getattr(layout, name)
    if not isinstance(v, int | float):
        object.__setattr__(layout, name, float(v))


def default_layout(crop: str, **overrides) -> CanopyLayout:
    base = {
        "soybean": CanopyLayout(),
        "maize": CanopyLayout(
            plot_length=4.0, plot_width=4.0, density=8.25, margin=3.5, jitter_along=0.15
        ),
    }
    if crop not in base:
        raise ConfigError(f"unknown crop {crop!r}: choose one of {', '.join(base)}")
    return replace(base[crop], **{k: v for k, v in overrides.items() if v is not None})
