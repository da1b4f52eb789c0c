"""The answers of one plot fitted over several of its rows, side by side, and their spread.

A scene observed over the row fit's best row and its neighbours (``observe_rows``) gets one fit
per row. Each row's parameters build a canopy (the same layout and canopy seed as the scene's
own); its traits are measured as for ``metrics.json`` (without the gap-fraction reading), and the
spread over the rows is what a user reads as the answer's dependence on the row observed.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from cropcraft_core.errors import InputError

#: Traits compared across rows (names of ``canopy_metrics``).
ROW_TRAITS = (
    "lai",
    "leaf_angle_mean_deg",
    "node_count",
    "internode_mean_m",
    "plant_height_m",
)


def row_traits(crop: str, params: Mapping[str, float], layout: Any, seed: int) -> dict[str, Any]:
    """:data:`ROW_TRAITS` of the canopy ``params`` builds (``generate_canopy`` with ``layout``
    and ``seed``); values as in ``metrics.json`` (None where undefined)."""
    from cropcraft_core.metrics.traits import canopy_metrics
    from cropcraft_core.procedural import generate_canopy

    canopy = generate_canopy(crop, dict(params), layout, seed=int(seed))
    values = canopy_metrics(canopy, gap_fraction=False)
    return {k: values.get(k) for k in ROW_TRAITS}


def spread(values: Sequence[float | None]) -> dict[str, float | None]:
    """median, min, max, mean, sd (ddof 0) and relative range ((max − min) / |mean|) of the
    finite ``values``; None each when there are none (relative range None when the mean is
    0)."""
    v = np.array([x for x in values if x is not None and math.isfinite(float(x))], float)
    if v.size == 0:
        keys = ("median", "min", "max", "mean", "sd", "relative_range")
        return dict.fromkeys(keys)
    mean = float(v.mean())
    return {
        "median": float(np.median(v)),
        "min": float(v.min()),
        "max": float(v.max()),
        "mean": mean,
        "sd": float(v.std()),
        "relative_range": None if mean == 0 else float((v.max() - v.min()) / abs(mean)),
    }


def compare_rows(
    crop: str, rows: Sequence[Mapping[str, Any]], layout: Any, seed: int
) -> dict[str, Any]:
    """Each row's answer beside the others.

    rows: one mapping per fitted row: ``index`` (0 the best row, ±k its neighbours),
    ``offset_m``, ``params`` (the row's fitted parameters) and optionally ``params_std``.
    Returns ``{"rows": [...], "spread": {...}, "definitions": {...}}``: each row with its
    :func:`row_traits`, rows in index order; ``spread[name]`` is :func:`spread` over the rows
    for every trait and parameter. The best row's answer is the scene's own (the paper's); the
    mean over rows is the plot's answer when the rows stand for it equally.
    """
    if not rows:
        raise InputError("compare_rows needs at least one fitted row")
    indices = [int(r["index"]) for r in rows]
    if len(set(indices)) != len(indices):
        raise InputError(f"row indices repeat: {indices}")
    out = []
    for r in sorted(rows, key=lambda r: int(r["index"])):
        params = {k: float(v) for k, v in dict(r["params"]).items()}
        out.append(
            {
                "index": int(r["index"]),
                "offset_m": float(r.get("offset_m", 0.0)),
                "params": params,
                "params_std": dict(r.get("params_std") or {}),
                "traits": row_traits(crop, params, layout, seed),
            }
        )
    names = list(out[0]["params"])
    table = {t: spread([r["traits"][t] for r in out]) for t in ROW_TRAITS}
    table.update({f"param:{p}": spread([r["params"].get(p) for r in out]) for p in names})
    return {
        "n_rows": len(out),
        "rows": out,
        "spread": table,
        "definitions": {
            "traits": "canopy_metrics of the canopy each row's parameters build (the scene's "
            "layout and canopy seed; no gap-fraction reading)",
            "spread": "over the rows: median, min, max, mean, sd (population) and "
            "(max - min) / |mean|",
            "index": "0 the row fit's best row (the scene's answer), +k / -k the k-th row to "
            "the right / left of it, looking along the row camera's image x from above",
        },
    }


#: How a scene fitted over several rows gets its one answer: ``best`` keeps the row fit's best
#: row's (the paper's one row; the others are reported beside it), ``mean`` takes every
#: parameter's mean over the rows' answers (the plot's rows standing for it equally).
ROW_ANSWERS = ("best", "mean")


def rows_answer(fits: Mapping[int, Mapping[str, Any]], how: str = "mean") -> dict[str, Any]:
    """One ``fit.json`` (``FitResult.to_dict()`` shape) from the fits of several rows.

    fits: ``{row index: that row's fit.json}``, 0 the best row. ``how="mean"``: ``params`` the
    per-parameter mean of the rows' answers, ``params_std`` their spread over the rows (ddof 0),
    ``seed_params`` the rows' answers (row order: index), ``seed_losses`` empty (the rows' losses
    are on different observations), ``config`` the best row's, ``extra["rows"]`` each row's
    answer by index. ``how="best"``: the best row's fit unchanged.
    """
    if how not in ROW_ANSWERS:
        raise InputError(f"unknown row answer {how!r}: one of {', '.join(ROW_ANSWERS)}")
    if 0 not in fits:
        raise InputError("the rows' fits must include the best row (index 0)")
    best = dict(fits[0])
    if how == "best":
        return best
    order = sorted(int(k) for k in fits)
    P = [{k: float(v) for k, v in fits[i]["params"].items()} for i in order]
    names = list(best["params"])
    return {
        "crop": best.get("crop"),
        "method": f"{best.get('method', 'bo')}, mean of {len(order)} rows",
        "params": {n: float(np.mean([p[n] for p in P])) for n in names},
        "params_std": {n: float(np.std([p[n] for p in P])) for n in names},
        "seed_params": P,
        "seed_losses": [],
        "seconds": float(sum(float(fits[i].get("seconds", 0.0)) for i in order)),
        "config": best.get("config", {}),
        "extra": {"rows": {str(i): p for i, p in zip(order, P, strict=True)}, "answer": how},
    }


__all__ = ["ROW_ANSWERS", "ROW_TRAITS", "compare_rows", "row_traits", "rows_answer", "spread"]
