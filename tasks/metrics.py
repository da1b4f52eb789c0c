"""Stage ``metrics``: the canopy traits (LAI, leaf angles, nodes, internodes, height) with units."""

from __future__ import annotations

from typing import Any

from cropcraft_core.metrics import HEADLINE_TRAITS
from tasks.common import Timer, artefact, key_of, make_record, open_store, stage_task
from tasks.generate import canopy_from_recipe


@stage_task("metrics")
def metrics(
    store_root: str,
    scene: str,
    config: dict[str, Any],
    upstream: dict[str, Any],
    lease: str | None = None,
) -> dict[str, Any]:
    """:func:`cropcraft_core.bundle.measure_canopy` of the generated canopy (gap-fraction rays
    through a wider border, so they see no edge); stores ``{scene}/metrics/metrics.json``
    with a ``definitions`` block (unit, method).
    With the answer's ``aggregate`` record upstream and ``seed_traits`` on, also the traits of
    every optimiser seed's answer and their spread
    (:func:`cropcraft_core.metrics.seeds.seed_traits`: ``seeds``, ``lai_seeds_min``,
    ``lai_seeds_max``), where the answer combines two or more seeds
    (:func:`~cropcraft_core.metrics.seeds.answer_seeds`; not the mean of several rows' answers:
    ``rows.json`` has their spread).

    config: ``gap_fraction`` (bool), ``seed`` (gap-fraction sensor randomness; null: the
    canopy's seed, as ``cropcraft generate`` measures it), ``seed_traits`` (bool, default on).
    """
    from cropcraft_core.bundle import measure_canopy
    from cropcraft_core.config import CanopyLayout
    from cropcraft_core.metrics import join_metrics
    from cropcraft_core.metrics.seeds import (
        LAI_SEEDS_MAX,
        LAI_SEEDS_MIN,
        answer_seeds,
        seed_metrics,
        seed_traits,
    )

    store = open_store(store_root, scene=scene, lease=lease, what="metrics")
    recipe = store.get_json(key_of(upstream["generate"], "recipe"))
    seeds = None
    if "aggregate" in upstream and config.get("seed_traits", True):
        seeds = answer_seeds(store.get_json(key_of(upstream["aggregate"], "fit")))
    with Timer() as t:
        canopy = canopy_from_recipe(recipe)
        values = measure_canopy(canopy, bool(config.get("gap_fraction", True)), config.get("seed"))
        if seeds is not None:
            layout = CanopyLayout(**recipe["layout"])
            block = seed_traits(recipe["crop"], seeds, layout, int(recipe["seed"]))
            values = join_metrics(values, seed_metrics(block))
        key = artefact(scene, "metrics", "metrics.json")
        digest = store.put_json(key, values)
    summary = {k: values.get(k) for k in HEADLINE_TRAITS}
    if seeds is not None:
        summary.update({k: values[k] for k in (LAI_SEEDS_MIN, LAI_SEEDS_MAX)})
    return make_record("metrics", scene, {"metrics": key}, {key: digest}, summary, t.seconds)
