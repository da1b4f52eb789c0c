"""The CropCraft histogram loss (paper "Loss Function")::

    L = L_depth + λ_lateral · L_lateral + λ_sobel · L_sobel + λ_mask · L_mask

with ``L_depth = ||h_obs − h_pred||²`` over the depth histograms, the same for the lateral and
depth-derivative histograms, and ``L_mask = (area_obs − area_pred)²``. Histograms and areas are
normalised as described in :mod:`cropcraft_core.observe.histograms` (default: by the image's pixel
count). λ = (2, 4, 1) for soybean and (1, 0, 1) for maize, from the preset.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from cropcraft_core.errors import ConfigError
from cropcraft_core.observe.histograms import HistogramStats
from cropcraft_core.observe.presets import LossPreset, ObservePreset


@dataclass(frozen=True)
class LossBreakdown:
    """One evaluation of the loss.

    total: the weighted sum ``depth + λ_lateral·lateral + λ_sobel·sobel + λ_mask·mask``.
    depth, lateral, sobel, mask: the unweighted terms L_depth, L_lateral, L_sobel, L_mask
    (``sobel`` is 0 when λ_sobel = 0 and either side skipped its derivative histogram).
    """

    total: float
    depth: float
    lateral: float
    sobel: float
    mask: float

    def to_dict(self) -> dict[str, float]:
        return asdict(self)


def _sq(a: np.ndarray, b: np.ndarray, name: str) -> float:
    if a.shape != b.shape:
        raise ConfigError(
            f"{name} histograms have {a.shape[0]} and {b.shape[0]} bins: compute both with the "
            "same preset"
        )
    diff = a - b
    return float(diff @ diff)


def loss(
    obs_stats: HistogramStats, pred_stats: HistogramStats, preset: ObservePreset | LossPreset
) -> LossBreakdown:
    """The weighted histogram loss between an observation's and a prediction's statistics.

    Both statistics must have been computed with the same bins, blur, normalisation and render
    height (their ``spec``), and, if ``preset`` is an ``ObservePreset``, with that preset's;
    otherwise ``ConfigError`` (e.g. a soybean observation against maize statistics). Only the λ
    weights are read from ``preset``. Identical statistics give exactly zero.
    """
    if isinstance(preset, ObservePreset):
        lp = preset.loss
        if obs_stats.spec != preset.stats_spec():
            raise ConfigError(
                f"observation statistics were computed with a different preset than the "
                f"{preset.crop} preset given: {_diff(obs_stats.spec, preset.stats_spec())}"
            )
    elif isinstance(preset, LossPreset):
        lp = preset
    else:
        raise ConfigError(
            f"preset must be an ObservePreset or LossPreset, got {type(preset).__name__}"
        )
    if obs_stats.spec != pred_stats.spec:
        raise ConfigError(
            "observed and predicted statistics were computed with different presets: "
            + _diff(obs_stats.spec, pred_stats.spec)
        )
    l_depth = _sq(obs_stats.depth, pred_stats.depth, "depth")
    l_lateral = _sq(obs_stats.lateral, pred_stats.lateral, "lateral")
    if obs_stats.has_sobel and pred_stats.has_sobel:
        l_sobel = _sq(obs_stats.sobel, pred_stats.sobel, "sobel")
    elif lp.lambda_sobel > 0:
        raise ConfigError(
            "lambda_sobel > 0 but the depth-derivative histogram was skipped for the "
            f"{'observed' if not obs_stats.has_sobel else 'predicted'} statistics: compute them "
            "with compute_stats(..., sobel=True)"
        )
    else:
        l_sobel = 0.0
    l_mask = (obs_stats.mask_area - pred_stats.mask_area) ** 2
    total = l_depth
    total += lp.lambda_lateral * l_lateral
    total += lp.lambda_sobel * l_sobel
    total += lp.lambda_mask * l_mask
    return LossBreakdown(
        total=float(total),
        depth=l_depth,
        lateral=l_lateral,
        sobel=l_sobel,
        mask=float(l_mask),
    )


def _diff(a: tuple, b: tuple) -> str:
    da, db = dict(a), dict(b)
    parts = [f"{k}: {da.get(k)!r} vs {db.get(k)!r}" for k in da if da.get(k) != db.get(k)]
    return "; ".join(parts) or "different specs"


__all__ = ["LossBreakdown", "loss"]
