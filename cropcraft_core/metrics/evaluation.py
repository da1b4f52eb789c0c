"""The paper's reconstruction errors over a set of scenes.

Given, for each scene, the predicted and the true metric dicts (as ``canopy_metrics`` writes them,
or a hand-made dict of field measurements with the same keys):

==========  ======================================================  ===========================
error       definition                                              metric key
==========  ======================================================  ===========================
LAIE        RMSE of LAI (m² m⁻²)                                    ``lai``
LAIPE       mean |pred − true| / |true| of LAI, a fraction            ``lai``
AME         RMSE of the leaf-angle means (degrees)                  ``leaf_angle_mean_deg``
ASDE        RMSE of the leaf-angle standard deviations (degrees)    ``leaf_angle_std_deg``
NDPE        mean abs. percent error (fraction) of mean internode    ``internode_mean_m``
NCPE        mean abs. percent error (fraction) of node count        ``node_count``
==========  ======================================================  ===========================

A metric is computed over the scenes where both dicts hold a number for its key (field data often
lack some: the paper's maize scenes have LAI only); it is ``None`` where no scene has it, and
``n_used`` says how many scenes went into each. Percent errors are fractions (0.23 = 23 %).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from cropcraft_core.errors import InputError

ERROR_KEYS: dict[str, tuple[str, str]] = {
    "LAIE": ("lai", "rmse"),
    "LAIPE": ("lai", "mape"),
    "AME": ("leaf_angle_mean_deg", "rmse"),
    "ASDE": ("leaf_angle_std_deg", "rmse"),
    "NDPE": ("internode_mean_m", "mape"),
    "NCPE": ("node_count", "mape"),
}
"""error name → (metric key it compares, "rmse" or "mape")."""


def _pair_arrays(pred: Sequence[float], true: Sequence[float]) -> tuple[np.ndarray, np.ndarray]:
    p = np.asarray(pred, dtype=np.float64)
    t = np.asarray(true, dtype=np.float64)
    if p.ndim != 1 or t.ndim != 1:
        raise InputError(f"expected 1-D value lists, got shapes {p.shape} and {t.shape}")
    if len(p) != len(t):
        raise InputError(f"{len(p)} predicted values but {len(t)} true values")
    if len(p) == 0:
        raise InputError("no values to compare")
    if not (np.all(np.isfinite(p)) and np.all(np.isfinite(t))):
        raise InputError("values to compare must be finite numbers")
    return p, t


def rmse(pred: Sequence[float], true: Sequence[float]) -> float:
    """Root mean squared error sqrt(mean((pred − true)²)) of (n,) values, n ≥ 1."""
    p, t = _pair_arrays(pred, true)
    return float(np.sqrt(np.mean((p - t) ** 2)))


def mean_abs_percent_error(pred: Sequence[float], true: Sequence[float]) -> float:
    """mean(|pred − true| / |true|) of (n,) values, as a fraction; every true value must be ≠ 0."""
    p, t = _pair_arrays(pred, true)
    zero = np.flatnonzero(t == 0)
    if len(zero):
        raise InputError(
            f"percent error is undefined where the true value is 0 (scene {int(zero[0])})"
        )
    return float(np.mean(np.abs(p - t) / np.abs(t)))


def _value(d: Mapping[str, Any], key: str, i: int, side: str) -> float | None:
    v = d.get(key)
    if v is None:
        return None
    if isinstance(v, bool) or not isinstance(v, int | float | np.integer | np.floating):
        raise InputError(f"{side} scene {i}: {key} must be a number, got {v!r}")
    v = float(v)
    if math.isnan(v):
        return None
    if not math.isfinite(v):
        raise InputError(f"{side} scene {i}: {key} is {v}")
    return v


def evaluate(
    predicted: Sequence[Mapping[str, Any]],
    truth: Sequence[Mapping[str, Any]],
    *,
    lai_key: str = "lai",
    truth_lai_key: str | None = None,
) -> dict[str, Any]:
    """LAIE, LAIPE, AME, ASDE, NDPE, NCPE over scenes ``predicted[i]`` ↔ ``truth[i]``.

    predicted, truth: equally long, non-empty lists of metric dicts. ``lai_key`` names the LAI
    entry of the predicted dicts and ``truth_lai_key`` (default: the same) of the true ones, e.g.
    ``truth_lai_key="lai_gap_fraction"`` to score against an instrument reading. Returns
    ``{"LAIE": float | None, ..., "NCPE": ..., "n_scenes": n, "n_used": {error: k}}``.
    """
    if isinstance(predicted, Mapping) or isinstance(truth, Mapping):
        raise InputError("pass lists of metric dicts (one per scene), not a single dict")
    if len(predicted) != len(truth):
        raise InputError(
            f"{len(predicted)} predicted scenes but {len(truth)} true scenes: they must pair up"
        )
    if len(predicted) == 0:
        raise InputError("no scenes to evaluate")
    for i, (p, t) in enumerate(zip(predicted, truth, strict=True)):
        if not isinstance(p, Mapping) or not isinstance(t, Mapping):
            raise InputError(f"scene {i}: expected two metric dicts, got {type(p)} and {type(t)}")

    out: dict[str, Any] = {}
    n_used: dict[str, int] = {}
    for name, (key, kind) in ERROR_KEYS.items():
        pkey = lai_key if key == "lai" else key
        tkey = (truth_lai_key or lai_key) if key == "lai" else key
        pairs = []
        for i, (p, t) in enumerate(zip(predicted, truth, strict=True)):
            pv, tv = _value(p, pkey, i, "predicted"), _value(t, tkey, i, "true")
            if pv is not None and tv is not None:
                pairs.append((i, pv, tv))
        n_used[name] = len(pairs)
        if not pairs:
            out[name] = None
            continue
        scenes, pv, tv = zip(*pairs, strict=True)
        if kind == "mape" and 0.0 in tv:
            raise InputError(
                f"{name}: percent error is undefined where the true {tkey} is 0 "
                f"(scene {scenes[tv.index(0.0)]})"
            )
        out[name] = rmse(pv, tv) if kind == "rmse" else mean_abs_percent_error(pv, tv)
    out["n_scenes"] = len(predicted)
    out["n_used"] = n_used
    return out
