"""Per-crop settings of ground and row fitting (supplementary "Additional Row Fitting and Depth
Rendering Details"); every number can be overridden by name::

    p = preset("soybean")                         # the paper's soybean settings
    p = preset("maize", sample_count=200_000)     # fewer samples than the paper's 5 M
    p = preset("soybean", box_size=None)          # no scene-box crop

Units. ``box_center`` / ``box_size`` are in *scene* units (the frame of the input point cloud,
e.g. Nerfstudio's normalised frame, where the paper defines its boxes). Every other length is in
metres and is applied after the scene has been brought to metric scale (see
:func:`cropcraft_core.rowfit.fit.fit_ground_and_rows`).

Colour rules, in true CIELAB units (D65, L* in [0, 100], a*/b* roughly [-128, 127]; see
:mod:`cropcraft_core.rowfit.lab` -- *not* OpenCV's 8-bit scaling). Our reading of the paper:

* **Removal.** "All points with L* < 0 and b* < 1 are removed" (soybean); maize sets "the L*, a*
  and b* thresholds to 32, 0 and 0". We read the rule as a conjunction: a point is dropped when
  ``L* < remove_l_below`` **and** ``b* < remove_b_below`` -- dark *and* bluish points, i.e.
  shadows, sky and NeRF floaters, which are neither soil (b* > 0, yellow-brown) nor leaves
  (b* > 0, yellow-green). For soybean ``L* < 0`` never holds, so the rule removes nothing (the
  paper's soybean setting effectively disables it); for maize it drops points with
  ``L* < 32 and b* < 0``.
* **Ground / plant.** The paper says "points with a* < 2 are classified as ground points, and the
  rest are classified as plant points". Taken literally this calls green leaves (a* well below
  0) ground and red-brown soil (a* > 0) plant, which is physically backwards and would make the
  ground RANSAC fit the canopy. The threshold is on the red-green axis, so the paper's labels
  must be swapped relative to the sign convention we (and OpenCV/skimage) use; we therefore read
  it as **plant iff a* < plant_a_below, ground otherwise** (soybean 2, maize 0): green points
  are plant, neutral-to-red points are ground. A threshold slightly above zero (soybean 2) keeps
  grey-green, desaturated leaf points in the plant class; neutral grey soil (a* ~ 0) then counts
  as plant for soybean -- override ``plant_a_below`` for such fields.

Dense-canopy switch (soybean): when plant points are more than ``dense_plant_fraction`` (75 %)
of the points left after the removal rule, row fitting keeps plant points above the 70th (not
50th) height percentile, uses a 25 cm (not 20 cm) line threshold and renders from 1.25 m (not
1.0 m). The paper states it for soybean only; for maize (render height 5 m) a 1.25 m switch would
be meaningless, so it is off (``dense_plant_fraction=None``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace
from typing import Any

from cropcraft_core.errors import ConfigError


@dataclass(frozen=True)
class RowFitPreset:
    """Ground and row fitting settings of one crop (lengths in metres unless stated)."""

    crop: str
    """Crop name, ``"soybean"`` or ``"maize"``."""
    sample_count: int
    """At most this many points (randomly chosen, after the box crop) enter voxel downsampling
    (paper: soybean 100 000, maize 5 000 000 sampled from the NeRF; smaller values are faster)."""
    box_center: tuple[float, float, float] | None
    """Centre of the scene box, scene units (soybean (0, 0, -1.5), maize (0, 0, 0)). ``None``
    together with ``box_size=None`` disables the crop."""
    box_size: tuple[float, float, float] | None
    """Side lengths of the axis-aligned scene box, scene units (soybean 2 × 2 × 3, maize
    2 × 2 × 2); ``None`` = keep every point."""
    render_height: float
    """Height of the row camera above the ground (soybean 1.0, maize 5.0)."""
    ground_threshold: float
    """RANSAC inlier distance of the ground plane (soybean 0.05, maize 0.10)."""
    remove_l_below: float
    """Removal rule: a point with ``L* <`` this **and** ``b* < remove_b_below`` is dropped
    (soybean 0 = never, maize 32)."""
    remove_b_below: float
    """Removal rule: see ``remove_l_below`` (soybean 1, maize 0)."""
    plant_a_below: float
    """A point is plant (green) iff ``a* <`` this, else ground (soybean 2, maize 0). See the
    module docstring for why this swaps the paper's literal wording."""
    voxel_size: float = 0.01
    """Voxel-downsampling cell side (0.01); positions and colours are averaged per voxel."""
    ground_iterations: int = 1000
    """RANSAC hypotheses for the ground plane (1000)."""
    height_percentile: float = 50.0
    """Plant points lower above the ground than this percentile of their heights are discarded
    before row fitting (50)."""
    line_threshold: float = 0.20
    """RANSAC inlier distance of a row line, measured in the ground plane (0.20)."""
    line_iterations: int = 1000
    """RANSAC hypotheses per row line (the paper does not say; 1000 like the ground)."""
    stop_min_points: int = 1000
    """Sequential line fitting stops when fewer points than this remain (1000)."""
    stop_min_fraction: float = 0.20
    """... or when fewer than this fraction of the sliced plant points remain (0.2)."""
    min_row_inliers: int = 50
    """Safeguard (not in the paper): a line with fewer inliers than this is not a row and ends
    the sequential fitting."""
    max_rows: int = 20
    """Safeguard (not in the paper): at most this many lines are fitted."""
    refit_iterations: int = 1
    """Least-squares refits of each row: 1 = the paper (one orthogonal least-squares fit to the
    RANSAC inliers); more re-gather the inliers around the refitted line and fit again."""
    refine_direction_deg: float | None = 90.0
    """Refinement of the best row, not in the paper (``None`` = off, exactly the paper): search
    the direction within ± this many degrees of the RANSAC row (90 = all directions) along
    which all plant points' lateral profile is most periodic at the row spacing (the sharpest
    profile where no period shows), then take the ``line_threshold`` band holding the most
    points along it and mean-shift it. Plain RANSAC counts favour the scene box's diagonal on
    nearly closed canopies (errors up to 45° on synthetic mid-season soybean)."""
    direction_min_correlation: float = 0.1
    """Direction refinement: the row period counts as visible when the lateral profile's
    normalised autocorrelation at its best lag exceeds this (the threshold
    ``estimate_scale_from_rows`` uses); below it (a single row) the sharpest profile decides."""
    row_spacing: float | None = None
    """Known planting row spacing (metres), not in the paper (``None`` = off): with the refined
    direction, the best row's lateral position is moved to the nearest line of the periodic row
    pattern whose phase is the circular mean of all plant points' offsets modulo the spacing.
    Plants are symmetric about their row, so every row point votes for the centre lines; the
    band mean alone drifts towards the neighbour row's leaves on wide canopies (15 cm measured
    on mid-season soybean)."""
    dense_plant_fraction: float | None = 0.75
    """Plant-point fraction above which the dense-canopy settings apply (soybean 0.75; maize
    ``None`` = never)."""
    dense_height_percentile: float = 70.0
    """Height percentile used for a dense canopy (70)."""
    dense_line_threshold: float = 0.25
    """Row line threshold used for a dense canopy (0.25)."""
    dense_render_height: float = 1.25
    """Render height used for a dense canopy (1.25)."""
    lower_ground_share: float | None = None
    """Not in the paper (``None`` = off, the paper; maize 0.5): where the RANSAC ground plane
    cuts through the canopy (plant points on both its sides), a parallel plane of the
    ground-coloured points off it holding at least this share of its inliers, with fewer
    plant points across it, is the ground (``rowfit.fit._lower_ground``). From a drone 25 m
    up a maize canopy's soil-coloured leaf points outnumbered the soil seen between the
    plants, and the plane lay 0.78 m up a 1.13 m canopy (its top read 0.31 m; session 98)."""
    clear_canopy: bool = True
    """Not in the paper (``False`` = exactly the paper): raise the render height where the
    canopy's top (99.5th percentile of plant-point heights in the ROI) comes within the depth
    histogram's lower edge or the observation mask's colour band of the camera
    (``observe.clear_render_height``, ``observe.observed_clearance``: soybean 0.25 m)."""
    roi_radius: float | None = None
    """Row fitting only uses plant points within this distance of a vertical axis through the
    frame origin (the scene-box centre projected onto the ground); maize 2.0, soybean ``None``."""
    scale_radius: float | None = None
    """The row-spacing profile that measures the metric scale
    (:func:`~cropcraft_core.rowfit.fit.estimate_scale_from_rows`) uses plant points within this
    distance of the same axis (``None``: ``roi_radius``); maize 3.0. Within 2 m a maize profile
    holds five rows, whose lateral centres scatter by several cm (a few large leaves each, at
    random azimuths): on seven maize reconstructions (60 drone photos, SfM or true poses, and
    perfect points) the scale from 2 m was −4.3 to +1.7 % off (RMS 2.9 %), from 3 m −2.0 to
    +0.1 % (RMS 1.2 %)."""
    max_soil_coloured_canopy: float | None = 0.5
    """Not in the paper (``None`` = off, exactly the paper): the largest share of the canopy's
    points (those more than twice ``ground_threshold`` above the ground plane, where they are at
    least a tenth of all points) that may be soil-coloured. Above it the run stops with a
    named error: most leaves are not green (senescent, or the colours are off), so the colour
    split would read them as soil and the rows and the fit would stand on the few green points
    left. Green canopies read 0.002–0.083 (soybean, 34 stored reconstructions) and 0.04–0.28
    (maize, whose soil is a* >= 0: low-resolution drone scenes read the most); a senescent
    soybean canopy read 0.97, and its run had answered LAI 0.24 for 1.26 (session 95)."""
    min_points: int = 100
    """Fewer points than this after cropping and downsampling is an error ("too few points")."""
    min_ground_points: int = 50
    """Fewer ground-coloured points, or ground-plane inliers, than this is "no ground found"."""
    ransac_score_points: int = 20_000
    """RANSAC hypotheses are scored on a random subset of at most this many points; the winner's
    inliers are then taken over all points."""

    def __post_init__(self) -> None:
        if self.crop not in _BASE:
            raise ConfigError(f"unknown crop {self.crop!r}: choose one of {', '.join(_BASE)}")
        for name in (
            "sample_count",
            "ground_iterations",
            "line_iterations",
            "stop_min_points",
            "min_row_inliers",
            "max_rows",
            "refit_iterations",
            "min_points",
            "min_ground_points",
            "ransac_score_points",
        ):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ConfigError(f"{name} must be a positive integer, got {v!r}")
        for name in (
            "render_height",
            "ground_threshold",
            "voxel_size",
            "line_threshold",
            "dense_line_threshold",
            "dense_render_height",
        ):
            _positive(name, getattr(self, name))
        for name in ("remove_l_below", "remove_b_below", "plant_a_below"):
            v = getattr(self, name)
            if not _is_finite(v):
                raise ConfigError(f"{name} must be a finite number, got {v!r}")
        for name in ("height_percentile", "dense_height_percentile"):
            v = getattr(self, name)
            if not (_is_finite(v) and 0 <= v < 100):
                raise ConfigError(f"{name} must be in [0, 100), got {v!r}")
        if self.lower_ground_share is not None and not (
            _is_finite(self.lower_ground_share) and 0 < self.lower_ground_share <= 1
        ):
            raise ConfigError(
                f"lower_ground_share must be None or in (0, 1], got {self.lower_ground_share!r}"
            )
        if not (
            _is_finite(self.direction_min_correlation) and 0 <= self.direction_min_correlation < 1
        ):
            raise ConfigError(
                "direction_min_correlation must be in [0, 1), got "
                f"{self.direction_min_correlation!r}"
            )
        if not (_is_finite(self.stop_min_fraction) and 0 <= self.stop_min_fraction < 1):
            raise ConfigError(f"stop_min_fraction must be in [0, 1), got {self.stop_min_fraction}")
        if self.dense_plant_fraction is not None and not (
            _is_finite(self.dense_plant_fraction) and 0 < self.dense_plant_fraction < 1
        ):
            raise ConfigError(
                f"dense_plant_fraction must be in (0, 1) or None, got {self.dense_plant_fraction}"
            )
        if self.max_soil_coloured_canopy is not None and not (
            _is_finite(self.max_soil_coloured_canopy) and 0 < self.max_soil_coloured_canopy < 1
        ):
            raise ConfigError(
                "max_soil_coloured_canopy must be in (0, 1) or None, got "
                f"{self.max_soil_coloured_canopy!r}"
            )
        if not isinstance(self.clear_canopy, bool):
            raise ConfigError(f"clear_canopy must be true or false, got {self.clear_canopy!r}")
        for name in ("roi_radius", "scale_radius"):
            if getattr(self, name) is not None:
                _positive(name, getattr(self, name))
        if self.refine_direction_deg is not None:
            _positive("refine_direction_deg", self.refine_direction_deg)
        if self.row_spacing is not None:
            _positive("row_spacing", self.row_spacing)
        if (self.box_center is None) != (self.box_size is None):
            raise ConfigError("box_center and box_size must both be given or both be None")
        if self.box_size is not None:
            three = (tuple, list)
            if not (isinstance(self.box_size, three) and isinstance(self.box_center, three)):
                raise ConfigError(
                    f"box_center and box_size must be three numbers each (x, y, z), got "
                    f"{self.box_center!r} and {self.box_size!r}"
                )
            if len(self.box_size) != 3 or len(self.box_center) != 3:
                raise ConfigError("box_center and box_size must have three entries each")
            for v in self.box_size:
                _positive("box_size", v)
            for v in self.box_center:
                if not _is_finite(v):
                    raise ConfigError(f"box_center must be finite, got {self.box_center}")

    def dense(self) -> RowFitPreset:
        """This preset with the dense-canopy settings in place of the normal ones."""
        return replace(
            self,
            height_percentile=self.dense_height_percentile,
            line_threshold=self.dense_line_threshold,
            render_height=self.dense_render_height,
        )


def _is_finite(v: Any) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)


def _positive(name: str, v: Any) -> None:
    if not (_is_finite(v) and v > 0):
        raise ConfigError(f"{name} must be a positive number, got {v!r}")


_BASE: dict[str, dict[str, Any]] = {
    "soybean": dict(
        crop="soybean",
        sample_count=100_000,
        box_center=(0.0, 0.0, -1.5),
        box_size=(2.0, 2.0, 3.0),
        render_height=1.0,
        ground_threshold=0.05,
        remove_l_below=0.0,
        remove_b_below=1.0,
        plant_a_below=2.0,
    ),
    "maize": dict(
        crop="maize",
        sample_count=5_000_000,
        box_center=(0.0, 0.0, 0.0),
        box_size=(2.0, 2.0, 2.0),
        render_height=5.0,
        ground_threshold=0.10,
        remove_l_below=32.0,
        remove_b_below=0.0,
        plant_a_below=0.0,
        dense_plant_fraction=None,
        lower_ground_share=0.5,
        roi_radius=2.0,
        scale_radius=3.0,
    ),
}


def preset(crop: str, **overrides: Any) -> RowFitPreset:
    """The paper's row-fitting settings for ``crop``, with ``overrides`` by field name."""
    if crop not in _BASE:
        raise ConfigError(f"unknown crop {crop!r}: choose one of {', '.join(_BASE)}")
    names = {f.name for f in fields(RowFitPreset)}
    unknown = sorted(set(overrides) - names)
    if unknown:
        raise ConfigError(
            f"unknown row-fit setting(s) {', '.join(unknown)}; known: {', '.join(sorted(names))}"
        )
    if "crop" in overrides and overrides["crop"] != crop:
        raise ConfigError("crop cannot be overridden; call preset() with the other crop")
    box_size = overrides.get("box_size", _BASE[crop]["box_size"])
    if box_size is None and "box_center" not in overrides:
        overrides = {**overrides, "box_center": None}
    return RowFitPreset(**{**_BASE[crop], **overrides})
