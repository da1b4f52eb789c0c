"""Stage ``rows``: the scene's answer beside its neighbour rows' answers, and their spread."""

from __future__ import annotations

from typing import Any

from tasks.common import Timer, artefact, key_of, make_record, open_store, stage_task
from tasks.fit_seed import layout_of


@stage_task("rows")
def rows(
    store_root: str, scene: str, config: dict[str, Any], upstream: dict[str, Any]
) -> dict[str, Any]:
    """:func:`cropcraft_core.metrics.rows.compare_rows` over the best row's fit
    (``upstream["aggregate"]``) and every neighbour row's (``upstream["aggregate@{index}"]``,
    offsets from ``upstream["observe_rows"]``); stores ``{scene}/rows/rows.json`` (with
    ``tried``: every neighbour considered, its view's no-surface share and whether it was kept).

    config: ``layout`` (planting) and ``seed`` (the canopy seed: the generate stage's, so that
    the best row's traits are the scene's own).
    """
    from cropcraft_core.metrics.rows import compare_rows

    store = open_store(store_root)
    crop = scene.split("/")[1]
    tried = upstream["observe_rows"]["summary"]["rows"]
    offsets = {int(e["index"]): e["offset_m"] for e in tried}
    with Timer() as t:
        fitted = []
        for name, rec in upstream.items():
            if name == "aggregate" or name.startswith("aggregate@"):
                index = 0 if name == "aggregate" else int(name.split("@", 1)[1])
                fit = store.get_json(key_of(rec, "fit"))
                fitted.append(
                    {
                        "index": index,
                        "offset_m": offsets.get(index, 0.0),
                        "params": fit["params"],
                        "params_std": fit.get("params_std"),
                    }
                )
        table = compare_rows(crop, fitted, layout_of(crop, config), int(config.get("seed", 0)))
        table["tried"] = tried  # every neighbour considered, with its view's coverage
        key = artefact(scene, "rows", "rows.json")
        digest = store.put_json(key, table)
    lai = table["spread"]["lai"]
    summary = {
        "n_rows": table["n_rows"],
        "lai": {str(r["index"]): r["traits"]["lai"] for r in table["rows"]},
        "lai_spread": lai,
        "node_count": {str(r["index"]): r["traits"]["node_count"] for r in table["rows"]},
        # neighbours whose view lies (partly) outside the reconstruction: no-surface share
        "left_out": {str(e["index"]): e["no_surface_fraction"] for e in tried if not e["kept"]},
    }
    return make_record("rows", scene, {"rows": key}, {key: digest}, summary, t.seconds)
