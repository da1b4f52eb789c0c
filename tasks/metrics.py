"""Stage ``metrics``: the canopy traits (LAI, leaf angles, nodes, internodes, height) with units."""

from __future__ import annotations

from typing import Any

from cropcraft_core.metrics import HEADLINE_TRAITS
from tasks.common import Timer, artefact, key_of, make_record, open_store, stage_task
from tasks.generate import canopy_from_recipe


@stage_task("metrics")
def metrics(
    store_root: str, scene: str, config: dict[str, Any], upstream: dict[str, Any]
) -> dict[str, Any]:
    """:func:`cropcraft_core.metrics.canopy_metrics` of the generated canopy (on the wider
    canopy of :func:`cropcraft_core.bundle.gap_fraction_canopy`, so gap-fraction rays see no
    edge); stores ``{scene}/metrics/metrics.json`` with a ``definitions`` block (unit, method).

    config: ``gap_fraction`` (bool), ``seed`` (gap-fraction sensor randomness).
    """
    from cropcraft_core.bundle import gap_fraction_canopy
    from cropcraft_core.metrics import canopy_metrics

    store = open_store(store_root)
    recipe = store.get_json(key_of(upstream["generate"], "recipe"))
    with Timer() as t:
        canopy = canopy_from_recipe(recipe)
        gap = bool(config.get("gap_fraction", True))
        values = canopy_metrics(
            gap_fraction_canopy(canopy) if gap else canopy,
            gap_fraction=gap,
            rng=int(config.get("seed", 0)),
        )
        key = artefact(scene, "metrics", "metrics.json")
        digest = store.put_json(key, values)
    summary = {k: values.get(k) for k in HEADLINE_TRAITS}
    return make_record("metrics", scene, {"metrics": key}, {key: digest}, summary, t.seconds)
