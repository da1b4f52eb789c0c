"""Stage ``rows``: the scene's answer beside its neighbour rows' answers, and their spread."""

from __future__ import annotations

from typing import Any

from tasks.common import Timer, artefact, key_of, make_record, open_store, stage_task
from tasks.fit_seed import layout_of


@stage_task("rows")
def rows(
    store_root: str,
    scene: str,
    config: dict[str, Any],
    upstream: dict[str, Any],
    lease: str | None = None,
) -> dict[str, Any]:
    """:func:`cropcraft_core.metrics.rows.compare_rows` over the best row's fit
    (``upstream["aggregate"]``) and every neighbour row's (``upstream["aggregate@{index}"]``,
    offsets from ``upstream["observe_rows"]``); stores ``{scene}/rows/rows.json`` (with
    ``tried``: every neighbour considered, its view's no-surface share and whether it was kept).

    config: ``layout`` (planting), ``seed`` (the canopy seed: the generate stage's, so that
    the best row's traits are its canopy's) and ``answer`` (``ROW_ANSWERS``): other than
    ``best``, the scene's answer is :func:`~cropcraft_core.metrics.rows.rows_answer`'s, stored
    as ``{scene}/rows/fit.json`` (artefact ``fit``, shaped as the aggregate stage's) for the
    stages after it.
    """
    from cropcraft_core.metrics.rows import compare_rows, rows_answer

    store = open_store(store_root, scene=scene, lease=lease, what="rows")
    crop = scene.split("/")[1]
    tried = upstream["observe_rows"]["summary"]["rows"]
    offsets = {int(e["index"]): e["offset_m"] for e in tried}
    with Timer() as t:
        fitted, fits = [], {}
        for name, rec in upstream.items():
            if name == "aggregate" or name.startswith("aggregate@"):
                index = 0 if name == "aggregate" else int(name.split("@", 1)[1])
                fit = fits[index] = store.get_json(key_of(rec, "fit"))
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
        how = str(config.get("answer", "best"))
        table["answer"] = how
        answer = rows_answer(fits, how)
        table["answer_params"] = answer["params"]  # the scene's answer, for the season summary
        key = artefact(scene, "rows", "rows.json")
        arts, hashes = {"rows": key}, {key: store.put_json(key, table)}
        if how != "best":  # the scene's answer from the rows' answers, as aggregate's fit.json
            fkey = artefact(scene, "rows", "fit.json")
            arts["fit"], hashes[fkey] = fkey, store.put_json(fkey, answer)
    lai = table["spread"]["lai"]
    summary = {
        "n_rows": table["n_rows"],
        "lai": {str(r["index"]): r["traits"]["lai"] for r in table["rows"]},
        "lai_spread": lai,
        "node_count": {str(r["index"]): r["traits"]["node_count"] for r in table["rows"]},
        # neighbours whose view lies (partly) outside the reconstruction: no-surface share
        "left_out": {str(e["index"]): e["no_surface_fraction"] for e in tried if not e["kept"]},
        "answer": how,
    }
    if "fit" in arts:
        summary.update(params=answer["params"], params_std=answer["params_std"])
    return make_record("rows", scene, arts, hashes, summary, t.seconds)
