"""How far the fit's seeds disagree, in traits.

A scene's answer combines the best parameters of several independent optimiser seeds
(``fit.json``'s ``seed_params``). Each seed's parameters build a canopy (the answer's own layout
and canopy seed: only the parameters differ) whose traits are measured as for ``metrics.json``
(without the gap-fraction reading). Their spread is not a confidence interval: it is how far
equally good searches of the same observation land apart, which on a loss surface with broad
valleys can be wide (the demo scene's ten seeds read LAI 1.10 to 1.63 around its answer of 1.44,
README; 1.12 to 2.11 around 1.50 when benchmarks/RESULTS.md *#seed-traits* was measured).
A user reads it as how firmly the observation pins each trait down, beside the answer itself.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

from cropcraft_core.errors import InputError
from cropcraft_core.metrics.rows import ROW_TRAITS, row_traits, spread

#: The traits measured on every seed's canopy (those compared across rows).
SEED_TRAITS = ROW_TRAITS

#: ``metrics.json``'s flat keys for the seeds' LAI range (season summary columns).
LAI_SEEDS_MIN, LAI_SEEDS_MAX = "lai_seeds_min", "lai_seeds_max"


def seed_traits(
    crop: str, seed_params: Sequence[Mapping[str, float]], layout: Any, seed: int
) -> dict[str, Any]:
    """The traits of every seed's answer and their spread.

    seed_params: each seed's best parameters (``fit.json``'s ``seed_params``, every fitted and
    given parameter); layout, seed: the answer's canopy layout and canopy seed
    (``generate``'s recipe). Returns ``{"n_seeds": n, "traits": {name: {"values": [per seed],
    "median", "min", "max", "mean", "sd", "relative_range"}}}`` for :data:`SEED_TRAITS`
    (values None where a trait is undefined for a seed's canopy).
    """
    if len(seed_params) < 2:
        raise InputError(f"the seeds' spread needs at least two seeds, got {len(seed_params)}")
    per = [row_traits(crop, dict(p), layout, seed) for p in seed_params]
    traits = {}
    for name in SEED_TRAITS:
        values = [r[name] for r in per]
        traits[name] = {"values": values, **spread(values)}
    return {"n_seeds": len(per), "traits": traits}


def answer_seeds(fit: Mapping[str, Any]) -> list[dict[str, float]] | None:
    """The seeds' best parameters of a ``fit.json`` whose answer combines two or more seeds
    of one fit; None where it has fewer, or where its "seeds" are several rows' answers
    (``rows_answer``'s mean: ``rows.json`` has their spread)."""
    if (fit.get("extra") or {}).get("answer") == "mean":
        return None
    seeds = list(fit.get("seed_params") or [])
    return seeds if len(seeds) >= 2 else None


def seed_metrics(block: Mapping[str, Any]) -> dict[str, Any]:
    """``metrics.json``'s entries for a :func:`seed_traits` block: the block itself under
    ``seeds``, the LAI's range as flat keys (:data:`LAI_SEEDS_MIN`, :data:`LAI_SEEDS_MAX`), and
    their definitions."""
    lai = block["traits"]["lai"]
    n = block["n_seeds"]
    return {
        "seeds": dict(block),
        LAI_SEEDS_MIN: lai["min"],
        LAI_SEEDS_MAX: lai["max"],
        "definitions": {
            "seeds": {
                "unit": "as each trait",
                "method": f"the traits ({', '.join(SEED_TRAITS)}) of the canopy each of the "
                f"{n} optimiser seeds' best parameters builds (the answer's layout and canopy "
                "seed; no gap-fraction reading): per seed, and their median, min, max, mean, "
                "sd (population) and (max - min) / |mean|. How far equally good searches land "
                "apart, not a confidence interval",
            },
            LAI_SEEDS_MIN: {
                "unit": "m2 m-2",
                "method": f"lowest LAI of the {n} seeds' answers (seeds.traits.lai)",
            },
            LAI_SEEDS_MAX: {
                "unit": "m2 m-2",
                "method": f"highest LAI of the {n} seeds' answers (seeds.traits.lai)",
            },
        },
    }


__all__ = [
    "LAI_SEEDS_MAX",
    "LAI_SEEDS_MIN",
    "SEED_TRAITS",
    "answer_seeds",
    "seed_metrics",
    "seed_traits",
]
