"""Per-crop settings of the row observation, its foreground mask and the histogram loss.

Every number comes from the CropCraft paper ("Loss Function", supplementary "Additional Row
Fitting and Depth Rendering Details" and "Mask and Histogram Details"); every one can be
overridden by name::

    p = preset("soybean")                       # the paper's soybean settings
    p = preset("soybean", render_height=1.25)   # dense canopy (> 75 % plant points)
    p = preset("maize", lambda_sobel=0.5, normalisation="foreground")

Frame and units. The row camera looks straight down from ``render_height`` metres above the
ground (ground at height 0 in the row frame), image x along the row. In the camera frame the
ground is therefore the plane z_cam = ``render_height``; a pixel with z-depth ``d`` sees a point
at height ``render_height - d`` above the ground and at lateral offset
``y_cam = (v + 0.5 - cy) / fy * d`` from the row line. All lengths are metres.

Bin ranges that the paper ties to the render height (depth bins up to the render height, lateral
bins up to half of it) are stored as ``None`` and resolved by :meth:`ObservePreset.depth_range`
and :meth:`ObservePreset.lateral_range`, so overriding ``render_height`` moves them too.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Any

import numpy as np

from cropcraft_core.errors import ConfigError, InputError
from cropcraft_core.geometry.camera import ROW_CAMERA_SIZE, ROW_CAMERA_VFOV_DEG, PinholeCamera

#: Histogram normalisations understood by :func:`cropcraft_core.observe.compute_stats`.
NORMALISATIONS = ("image", "foreground")

#: Soybean render height when more than 75 % of the sampled points are plant points (supplementary).
SOYBEAN_DENSE_RENDER_HEIGHT = 1.25
#: Plant-point fraction above which the dense soybean render height is used.
SOYBEAN_DENSE_PLANT_FRACTION = 0.75


@dataclass(frozen=True)
class LossPreset:
    """Histogram bins, depth-derivative blur and loss weights (paper eq. for L).

    The loss is ``L = L_depth + lambda_lateral * L_lateral + lambda_sobel * L_sobel
    + lambda_mask * L_mask``; each histogram term is the squared L2 distance between the
    observed and predicted histograms, the mask term the squared difference of mask areas.
    Histograms follow ``numpy.histogram(values, bins=n, range=(lo, hi))``: equal-width bins,
    half-open ``[lo_i, hi_i)`` except the last, which includes ``hi``; values outside
    ``[lo, hi]`` are not counted (they still count in the mask area).
    """

    depth_bins: int
    """Number of equal-width z-depth bins (soybean 20, maize 10)."""
    depth_min: float
    """Lower edge of the depth histogram, metres of z-depth (soybean 0.1, maize 2.0)."""
    depth_max: float | None = None
    """Upper edge of the depth histogram, metres of z-depth; ``None`` = the render height."""
    depth_top_margin: float | None = None
    """Soybean ``None``: the paper's fixed depth range; maize 0.25. A number ``m`` (maize's
    departure from the paper, measured in README's *Where the fit departs*): the
    observation starts its depth histogram just above its own canopy's top instead of at
    ``depth_min``: at z-depth ``max(depth_min, t - m * (hi - t))``, with ``t`` the 0.5th
    percentile of its foreground depths and ``hi`` the upper edge, so that a short canopy spans
    all the bins instead of one or two (:func:`resolve_depth_range`). The observation keeps
    the resolved edge as its preset's ``depth_min`` (and this field as ``None``), and its
    predictions are binned alike; a prediction taller than ``t - m * (hi - t)`` leaves its top
    out of the depth histogram (the mask area still counts it)."""
    lateral_bins: int = 10
    """Number of equal-width bins of |y|, the lateral offset from the row line (10)."""
    lateral_min: float = 0.0
    """Lower edge of the lateral histogram, metres (0)."""
    lateral_max: float | None = None
    """Upper edge of the lateral histogram, metres; ``None`` = half the render height."""
    sobel_bins: int = 10
    """Number of equal-width bins of the depth-derivative magnitude (10)."""
    sobel_max: float = 0.004
    """Upper edge of the depth-derivative histogram (0.004; lower edge 0). The magnitude is
    ``|Sx| + |Sy|`` of OpenCV's unnormalised 3×3 Sobel of the blurred depth in metres, i.e.
    about 8 × the depth change per pixel along x plus the same along y."""
    blur_kernel: int = 25
    """Side of the Gaussian kernel applied to the depth map before the Sobel derivatives, pixels;
    odd (soybean 25, maize 55; 1 = no blur)."""
    blur_sigma: float = 0.0
    """Gaussian standard deviation, pixels; 0 = OpenCV's rule from the kernel size,
    ``0.3 * ((blur_kernel - 1) / 2 - 1) + 0.8`` (4.1 px for 25, 8.9 px for 55)."""
    lambda_lateral: float = 2.0
    """Weight of the lateral-profile term (soybean 2, maize 1)."""
    lambda_sobel: float = 4.0
    """Weight of the depth-derivative term (soybean 4, maize 0: NeRF maize depth is too noisy)."""
    lambda_mask: float = 1.0
    """Weight of the mask-area term (1 for both crops)."""
    normalisation: str = "image"
    """How histogram counts are scaled: ``"image"`` divides every count by the image's pixel
    count W·H (so each histogram sums to at most the mask area), ``"foreground"`` by the number
    of foreground pixels (each histogram sums to at most 1; all zeros for an empty mask). The
    mask area is always the foreground fraction of the image's pixels. See
    :mod:`cropcraft_core.observe.histograms` for why ``"image"`` is the default."""

    def __post_init__(self) -> None:
        for name in ("depth_bins", "lateral_bins", "sobel_bins", "blur_kernel"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ConfigError(f"{name} must be a positive integer, got {v!r}")
        if self.blur_kernel % 2 == 0:
            raise ConfigError(f"blur_kernel must be odd, got {self.blur_kernel}")
        for name in ("depth_min", "lateral_min", "sobel_max", "blur_sigma"):
            _finite(name, getattr(self, name), minimum=0.0)
        for name in ("depth_max", "lateral_max", "depth_top_margin"):
            if getattr(self, name) is not None:
                _finite(name, getattr(self, name), minimum=0.0)
        if self.sobel_max <= 0:
            raise ConfigError(f"sobel_max must be positive, got {self.sobel_max}")
        for name in ("lambda_lateral", "lambda_sobel", "lambda_mask"):
            _finite(name, getattr(self, name), minimum=0.0)
        if self.normalisation not in NORMALISATIONS:
            raise ConfigError(
                f"normalisation must be one of {', '.join(NORMALISATIONS)}, "
                f"got {self.normalisation!r}"
            )


@dataclass(frozen=True)
class ObservePreset:
    """The row camera, the observation's foreground-mask rules and the :class:`LossPreset`.

    Mask rules (supplementary "Mask and Histogram Details"), with height ``h = render_height -
    depth`` above the ground and lateral offset ``|y|`` from the row line: a pixel is background
    if (``a* < mask_a_max`` [and ``L* > mask_l_min``] and ``h > render_height - mask_top_band``)
    or ``h < mask_min_height`` or ``|y| >= mask_max_lateral``, or its depth is not finite.
    L*, a* are CIELAB (OpenCV, D65, sRGB input): L* in [0, 100], a* in about [-127, 127].
    """

    crop: str
    """Crop name, ``"soybean"`` or ``"maize"``."""
    render_height: float
    """Height of the row camera above the ground, metres (soybean 1.0, or 1.25 when plant points
    exceed 75 % of the sampled points; maize 5.0)."""
    loss: LossPreset
    """Histogram bins, blur and loss weights."""
    image_width: int = ROW_CAMERA_SIZE[0]
    """Row-camera image width, pixels (994)."""
    image_height: int = ROW_CAMERA_SIZE[1]
    """Row-camera image height, pixels (738)."""
    vfov_deg: float = ROW_CAMERA_VFOV_DEG
    """Row-camera vertical field of view, degrees (50)."""
    mask_a_max: float = -8.0
    """Colour rule: a pixel's a* must be below this for the colour rule to apply (−8)."""
    mask_l_min: float | None = None
    """Colour rule: its L* must also be above this (maize 40; soybean ``None`` = no L* test)."""
    mask_top_band: float = 0.25
    """Colour rule: ... and its height must be above ``render_height - mask_top_band``, metres
    (soybean 0.25, maize 2.0)."""
    mask_min_height: float = 0.1
    """Pixels lower than this above the ground are background, metres (0.1)."""
    mask_max_lateral: float = 0.5
    """Pixels with ``|y| >=`` this are background, metres (soybean 0.5, maize 3.0)."""
    mask_predictions: bool = True
    """Cut a prediction by the same box (``mask_min_height``, ``mask_max_lateral``) whenever
    the observation's own mask is cut by it (``Observation.box_mask``). False: the paper's
    predicted mask, every rendered pixel, which counts the low leaves the observation drops on
    the predicted side only (README, "Where the fit departs from the paper")."""
    prediction_blur_m: float = 0.0
    """Standard deviation, metres at the observed canopy's median depth, of a Gaussian blur of
    each predicted depth map before its statistics (:func:`~cropcraft_core.observe.blur_depth`:
    normalised over the rendered pixels, so an edge pixel averages its own and its rendered
    neighbours' depths and the predicted mask is unchanged); 0 = none, the paper's prediction.
    An error model for observations of fused surfaces (benchmarks/RESULTS.md, *#blur*). Of six
    soybean reconstructions only one (the 1.1 m canopy) is closer to its true mesh blurred than
    unblurred, mostly through the derivative term: it lost the deep leaves seen through gaps
    and their steep steps (*#blur-match*); the observe stage sets it
    (``observe.prediction_blur``)."""
    views_along: int = 1
    """Row cameras along the row whose statistics the observation pools (bin by bin): an odd
    number, centred on the row camera, ``view_step`` apart. 1: the paper's single camera.
    One row camera sees one draw of the canopy, and on some scenes that draw is far from its
    parameters' average (benchmarks/RESULTS.md, *#views*); the prediction's statistics are
    the same wherever along a uniform canopy the camera stands, so only the observation needs
    the extra views."""
    view_step: float = 0.5
    """Distance between the pooled row cameras along the row, metres."""
    views_across: int = 0
    """Neighbouring rows pooled on each side of the row camera's row (each with the same
    cameras along it), one row spacing apart; 0: the camera's own row only."""

    def __post_init__(self) -> None:
        if self.crop not in _BASE:
            raise ConfigError(f"unknown crop {self.crop!r}: choose one of {', '.join(_BASE)}")
        _finite("render_height", self.render_height, minimum=0.0)
        if self.render_height <= 0:
            raise ConfigError(f"render_height must be positive, got {self.render_height}")
        if not isinstance(self.loss, LossPreset):
            raise ConfigError(f"loss must be a LossPreset, got {type(self.loss).__name__}")
        for name in ("image_width", "image_height"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ConfigError(f"{name} must be a positive integer, got {v!r}")
        _finite("vfov_deg", self.vfov_deg)
        if not 0 < self.vfov_deg < 180:
            raise ConfigError(f"vfov_deg must be in (0, 180), got {self.vfov_deg}")
        _finite("mask_a_max", self.mask_a_max)
        if self.mask_l_min is not None:
            _finite("mask_l_min", self.mask_l_min)
        for name in ("mask_top_band", "mask_min_height", "mask_max_lateral"):
            _finite(name, getattr(self, name), minimum=0.0)
        _finite("prediction_blur_m", self.prediction_blur_m, minimum=0.0)
        if not isinstance(self.mask_predictions, bool):
            raise ConfigError(
                f"mask_predictions must be true or false, got {self.mask_predictions!r}"
            )
        for name in ("views_along", "views_across"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 0:
                raise ConfigError(f"{name} must be a non-negative integer, got {v!r}")
        if self.views_along % 2 == 0:
            raise ConfigError(
                f"views_along must be odd (centred on the row camera), got {self.views_along}"
            )
        _finite("view_step", self.view_step, minimum=0.0)
        if self.view_step <= 0:
            raise ConfigError(f"view_step must be positive, got {self.view_step}")
        lo, hi, _ = self.depth_range
        if not hi > lo:
            raise ConfigError(
                f"depth histogram range [{lo:g}, {hi:g}] m is empty: depth_min must be below "
                f"depth_max (or the render height {self.render_height:g} m)"
            )
        lo, hi, _ = self.lateral_range
        if not hi > lo:
            raise ConfigError(
                f"lateral histogram range [{lo:g}, {hi:g}] m is empty: lateral_min must be below "
                f"lateral_max (or half the render height)"
            )

    # ----------------------------------------------------------------- resolved bins
    @property
    def depth_range(self) -> tuple[float, float, int]:
        """(lo, hi, bins) of the z-depth histogram, metres."""
        lp = self.loss
        hi = self.render_height if lp.depth_max is None else lp.depth_max
        return float(lp.depth_min), float(hi), lp.depth_bins

    @property
    def lateral_range(self) -> tuple[float, float, int]:
        """(lo, hi, bins) of the |y| histogram, metres."""
        lp = self.loss
        hi = 0.5 * self.render_height if lp.lateral_max is None else lp.lateral_max
        return float(lp.lateral_min), float(hi), lp.lateral_bins

    @property
    def sobel_range(self) -> tuple[float, float, int]:
        """(lo, hi, bins) of the depth-derivative-magnitude histogram."""
        return 0.0, float(self.loss.sobel_max), self.loss.sobel_bins

    def stats_spec(self) -> tuple:
        """Everything that determines the histogram statistics (not the loss weights); two
        :class:`~cropcraft_core.observe.HistogramStats` can be compared only if equal."""
        lp = self.loss
        return (
            ("render_height", float(self.render_height)),
            ("depth", self.depth_range),
            ("lateral", self.lateral_range),
            ("sobel", self.sobel_range),
            ("blur_kernel", lp.blur_kernel),
            ("blur_sigma", float(lp.blur_sigma)),
            ("normalisation", lp.normalisation),
        )

    # ----------------------------------------------------------------- views
    @property
    def n_views(self) -> int:
        """How many row cameras the observation's statistics pool."""
        return self.views_along * (2 * self.views_across + 1)

    def view_offsets(self, row_spacing: float | None = None) -> list[tuple[float, float]]:
        """The pooled cameras' offsets (along, across) from the row camera in metres, the row
        camera's own (0, 0) first; ``row_spacing`` (m) places the neighbouring rows and is
        needed only when ``views_across`` > 0."""
        half = self.views_along // 2
        along = [0.0] + [s * k * self.view_step for k in range(1, half + 1) for s in (-1, 1)]
        across = [0.0]
        if self.views_across:
            if row_spacing is None or not math.isfinite(row_spacing) or row_spacing <= 0:
                raise ConfigError(
                    f"views_across={self.views_across} needs the row spacing, got {row_spacing!r}"
                )
            across += [
                s * k * row_spacing for k in range(1, self.views_across + 1) for s in (-1, 1)
            ]
        return [(float(a), float(c)) for c in across for a in along]

    # ----------------------------------------------------------------- camera
    def row_camera(
        self,
        center_xy: tuple[float, float] = (0.0, 0.0),
        row_direction: tuple[float, float] = (1.0, 0.0),
    ) -> PinholeCamera:
        """The row camera: ``image_width × image_height``, ``vfov_deg``, straight down from
        ``render_height`` above the ground (z = 0) over ``center_xy``, image x along
        ``row_direction``."""
        return PinholeCamera.look_down(
            center_xy=center_xy,
            height_m=self.render_height,
            row_direction=row_direction,
            ground_z=0.0,
            size=(self.image_width, self.image_height),
            vfov_deg=self.vfov_deg,
        )

    # ----------------------------------------------------------------- persistence
    def to_dict(self) -> dict[str, Any]:
        """Flat JSON-ready record; ``preset(**d)`` (with ``crop``) rebuilds it exactly."""
        out: dict[str, Any] = {f.name: getattr(self, f.name) for f in fields(self)}
        out.pop("loss")
        out.update({f.name: getattr(self.loss, f.name) for f in fields(self.loss)})
        return out

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> ObservePreset:
        """Inverse of :meth:`to_dict`; unknown keys raise ``ConfigError``. A record without
        ``depth_top_margin`` (older than it) reads as the fixed range it was made with."""
        if not isinstance(d, dict) or "crop" not in d:
            raise ConfigError("preset record must be a mapping with a 'crop' entry")
        rest = dict(d)
        # a record written before the field existed had the paper's fixed depth range
        rest.setdefault("depth_top_margin", None)
        return preset(rest.pop("crop"), **rest)


def check_prediction_blur(setting: Any, name: str = "prediction blur") -> Any:
    """``setting`` if it is a prediction-blur setting (``"auto"``, the surfaces' own softening,
    or a finite number of metres >= 0); ``ConfigError`` naming ``name`` otherwise."""
    if setting == "auto":
        return setting
    if (
        isinstance(setting, bool)
        or not isinstance(setting, int | float)
        or not math.isfinite(setting)
        or setting < 0
    ):
        raise ConfigError(f"{name} must be 'auto' or a number of metres >= 0, got {setting!r}")
    return setting


def _finite(name: str, value: Any, minimum: float | None = None) -> None:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise ConfigError(f"{name} must be a finite number, got {value!r}")
    if minimum is not None and value < minimum:
        raise ConfigError(f"{name} must be >= {minimum:g}, got {value!r}")


_BASE: dict[str, dict[str, Any]] = {
    "soybean": dict(
        render_height=1.0,
        mask_a_max=-8.0,
        mask_l_min=None,
        mask_top_band=0.25,
        mask_min_height=0.1,
        mask_max_lateral=0.5,
        depth_bins=20,
        depth_min=0.1,
        blur_kernel=25,
        lambda_lateral=2.0,
        lambda_sobel=4.0,
        lambda_mask=1.0,
    ),
    "maize": dict(
        render_height=5.0,
        mask_a_max=-8.0,
        mask_l_min=40.0,
        mask_top_band=2.0,
        mask_min_height=0.1,
        mask_max_lateral=3.0,
        depth_bins=10,
        depth_min=2.0,
        depth_top_margin=0.25,
        blur_kernel=55,
        lambda_lateral=1.0,
        lambda_sobel=0.0,
        lambda_mask=1.0,
    ),
}

CROPS: tuple[str, ...] = tuple(_BASE)

_OBS_FIELDS = {f.name: f for f in fields(ObservePreset) if f.name not in ("crop", "loss")}
_LOSS_FIELDS = {f.name: f for f in fields(LossPreset)}
_BOOL_FIELDS = {"mask_predictions"}
_INT_FIELDS = {"image_width", "image_height", "depth_bins", "lateral_bins", "sobel_bins"}
_INT_FIELDS |= {"blur_kernel", "views_along", "views_across"}
_OPTIONAL_FIELDS = {"depth_max", "lateral_max", "mask_l_min", "depth_top_margin"}


def _coerce(name: str, value: Any) -> Any:
    """JSON/CLI values to the field's type (ints stay ints, ``None`` where allowed)."""
    if value is None:
        if name in _OPTIONAL_FIELDS:
            return None
        raise ConfigError(f"{name} cannot be None")
    if name in _BOOL_FIELDS:
        if not isinstance(value, bool):
            raise ConfigError(f"{name} must be true or false, got {value!r}")
        return value
    if name == "normalisation":
        if not isinstance(value, str):
            raise ConfigError(f"normalisation must be a string, got {value!r}")
        return value
    if isinstance(value, bool):
        raise ConfigError(f"{name} must be a number, got {value!r}")
    try:
        f = float(value)
    except (TypeError, ValueError):
        raise ConfigError(f"{name}={value!r} is not a number") from None
    if name in _INT_FIELDS:
        if not math.isfinite(f) or f != int(f):
            raise ConfigError(f"{name} must be an integer, got {value!r}")
        return int(f)
    return f


def preset(crop: str, **overrides: Any) -> ObservePreset:
    """The paper's settings for ``crop`` ("soybean" or "maize") with ``overrides`` applied.

    Any field of :class:`ObservePreset` or :class:`LossPreset` may be overridden by name
    (flat namespace, e.g. ``render_height=1.25, lambda_sobel=0``). Unknown crops, unknown
    names and out-of-range values raise ``ConfigError``.
    """
    if not isinstance(crop, str) or crop not in _BASE:
        raise ConfigError(f"unknown crop {crop!r}: choose one of {', '.join(_BASE)}")
    unknown = sorted(set(overrides) - set(_OBS_FIELDS) - set(_LOSS_FIELDS))
    if unknown:
        valid = ", ".join(sorted([*_OBS_FIELDS, *_LOSS_FIELDS]))
        raise ConfigError(f"unknown {crop} preset setting {unknown[0]!r}: choose from {valid}")
    values = {**_BASE[crop], **{k: _coerce(k, v) for k, v in overrides.items()}}
    loss_kw = {k: v for k, v in values.items() if k in _LOSS_FIELDS}
    obs_kw = {k: v for k, v in values.items() if k in _OBS_FIELDS}
    return ObservePreset(crop=crop, loss=LossPreset(**loss_kw), **obs_kw)


def with_overrides(p: ObservePreset, **overrides: Any) -> ObservePreset:
    """``p`` with some fields replaced (same names and checks as :func:`preset`)."""
    d = p.to_dict()
    unknown = sorted(set(overrides) - set(d) - {"crop"})
    if unknown or "crop" in overrides:
        bad = unknown[0] if unknown else "crop"
        raise ConfigError(f"cannot override preset setting {bad!r}")
    d.update(overrides)
    return ObservePreset.from_dict(d)


#: Percentile of an observation's foreground depths taken as its canopy's top by
#: :func:`resolve_depth_range` (a few stray pixels above the canopy do not move it).
CANOPY_TOP_PERCENTILE = 0.5


def resolve_depth_range(p: ObservePreset, foreground_depths: np.ndarray) -> ObservePreset:
    """``p`` with its depth histogram fitted to an observed canopy when ``p`` asks for it
    (``depth_top_margin`` set): ``depth_min`` raised to ``t - margin * (hi - t)`` but never
    past the top ``t`` (the :data:`CANOPY_TOP_PERCENTILE` th percentile of the observation's
    foreground z-depths, metres), so a canopy reaching nearer the camera than ``depth_min``
    moves it down to its top, where the fixed bins would drop the canopy's top from both
    sides of the loss; ``depth_top_margin`` cleared, so the result
    is an ordinary fixed-range preset that predictions share. ``p`` itself when it does not
    ask. ``InputError`` for no finite foreground depth."""
    margin = p.loss.depth_top_margin
    if margin is None:
        return p
    d = np.asarray(foreground_depths, dtype=np.float64).ravel()
    d = d[np.isfinite(d)]
    if d.size == 0:
        raise InputError("depth_top_margin: the observation has no finite foreground depth")
    lo, hi, _ = p.depth_range
    top = float(np.percentile(d, CANOPY_TOP_PERCENTILE))
    if top >= hi:  # nothing above the histogram's far edge to fit the bins to
        return with_overrides(p, depth_top_margin=None)
    new_lo = min(max(lo, top - float(margin) * (hi - top)), top)
    return with_overrides(p, depth_min=float(new_lo), depth_top_margin=None)


def soybean_render_height(plant_fraction: float) -> float:
    """Soybean render height for a scene whose sampled points are ``plant_fraction`` plant
    points: 1.25 m above 75 %, else 1.0 m (supplementary)."""
    _finite("plant_fraction", plant_fraction, minimum=0.0)
    if plant_fraction > 1:
        raise ConfigError(f"plant_fraction must be in [0, 1], got {plant_fraction}")
    if plant_fraction > SOYBEAN_DENSE_PLANT_FRACTION:
        return SOYBEAN_DENSE_RENDER_HEIGHT
    return float(_BASE["soybean"]["render_height"])


def clear_render_height(
    crop: str, render_height: float, canopy_top: float, clearance: float | None = None
) -> float:
    """``render_height``, raised where the canopy's top (metres above the ground) comes closer
    to the camera than ``clearance`` -- by default the depth histogram's lower edge
    (``depth_min``: soybean 0.1 m, maize 2 m): the row camera must look down on the canopy,
    not from inside it. Raised to ``canopy_top + clearance``, rounded up to 5 cm. An observed
    canopy (a reconstruction, with colour) needs :func:`observed_clearance`.

    Not in the paper, whose fixed soybean camera (1.0 m, 1.25 m dense) assumes canopies below
    0.9 m; 5 of the accuracy benchmark's 30 uniformly drawn soybean canopies reach 0.90-1.48 m,
    three of them above the 1.0 m camera, where the loss could not tell LAI 2.6 from the true
    5.5 (``fit/select.py``)."""
    if crop not in _BASE:
        raise ConfigError(f"unknown crop {crop!r}: choose one of {', '.join(_BASE)}")
    _finite("render_height", render_height, minimum=0.0)
    _finite("canopy_top", canopy_top)
    if clearance is None:
        clearance = float(_BASE[crop]["depth_min"])
    _finite("clearance", clearance, minimum=0.0)
    need = float(canopy_top) + float(clearance)
    if need <= render_height:
        return float(render_height)
    return math.ceil(round(need / 0.05, 9)) * 0.05


def observed_clearance(crop: str) -> float:
    """How far below the row camera an observed canopy's top must stay (metres): the depth
    histogram's lower edge, and the observation mask's colour band (``mask_top_band``: soybean
    0.25 m), inside which plant-green pixels count as background -- a leaf there would be cut
    from the observation while a prediction keeps it."""
    if crop not in _BASE:
        raise ConfigError(f"unknown crop {crop!r}: choose one of {', '.join(_BASE)}")
    return float(max(_BASE[crop]["depth_min"], _BASE[crop]["mask_top_band"]))


__all__ = [
    "CROPS",
    "NORMALISATIONS",
    "SOYBEAN_DENSE_PLANT_FRACTION",
    "SOYBEAN_DENSE_RENDER_HEIGHT",
    "LossPreset",
    "ObservePreset",
    "clear_render_height",
    "observed_clearance",
    "preset",
    "resolve_depth_range",
    "soybean_render_height",
    "with_overrides",
]
