"""Stage ``aggregate``: the final parameters from the per-seed results (``fit.combine``, by
default the crop's rule: soybean the per-parameter median of the seeds' best points unless
re-scoring finds a significantly deeper basin, maize the seeds' candidates re-scored against the
observation on fresh canopies) and their spread."""

from __future__ import annotations

from typing import Any

from cropcraft_core.errors import InputError
from tasks.common import (
    Timer,
    artefact,
    key_of,
    load_observation,
    make_record,
    open_store,
    stage_task,
    workdir,
)
from tasks.fit_seed import fit_config

#: The records in ``FitResult.extra`` that name the chosen candidate, the final one first.
_VERDICTS = ("floors", "guard", "selection")


def _run_name() -> str:
    """``aggregate`` (the best row), ``aggregate@row_p1`` (a neighbour row)."""
    from prefect.runtime import task_run

    from cropcraft_core.rowfit import row_label

    row = task_run.parameters.get("row")
    return "aggregate" + ("" if row is None else f"@{row_label(row)}")


@stage_task("aggregate", task_run_name=_run_name)
def aggregate(
    store_root: str,
    scene: str,
    config: dict[str, Any],
    upstream: dict[str, Any],
    row: int | None = None,
    lease: str | None = None,
) -> dict[str, Any]:
    """:func:`cropcraft_core.fit.combine` over every ``seed-*`` record in ``upstream``
    (re-scored against ``upstream["observe"]``'s observation where the rule needs it); stores
    ``FitResult.to_dict()`` as ``{scene}/fit/fit.json`` (params, params_std, per-seed params and
    losses, the re-scored candidates under ``extra.selection``; ``seconds`` = the seeds' summed
    optimisation time plus the re-scoring); for a neighbour ``row``, its seeds' answer as
    ``{scene}/fit/row_p1/fit.json``."""
    from cropcraft_core.fit import combine
    from cropcraft_core.optimize import SeedResult
    from tasks.fit_seed import layout_of

    store = open_store(store_root, scene=scene, lease=lease, what="aggregate")
    cfg = fit_config(config)
    crop = scene.split("/")[1]
    seeds = sorted(
        (rec for name, rec in upstream.items() if name.startswith("seed-")),
        key=lambda r: r["summary"]["seed"],
    )
    with Timer() as t, workdir("aggregate") as tmp:
        results = []
        for rec in seeds:
            key = key_of(rec, "seed")
            path = store.get_file(key, tmp / f"{rec['summary']['seed']}.npz")
            try:
                results.append(SeedResult.load(path))
            except InputError as exc:  # named as stored, not as the scratch copy
                message = str(exc).replace(str(path), store.url(key))
                raise InputError(f"{message}: rerun the scene to fit that seed again") from None
        seconds = sum(float(r["seconds"]) for r in seeds)
        obs = load_observation(store, upstream) if cfg.reevaluates(crop) else None
        fit = combine(crop, results, cfg, seconds, obs, layout_of(crop, config))
        key = artefact(scene, "aggregate", "fit.json", row=row)
        digest = store.put_json(key, fit.to_dict())
    return make_record(
        "aggregate",
        scene,
        {"fit": key},
        {key: digest},
        {
            "params": fit.params,
            "params_std": fit.params_std,
            "n_seeds": len(results),
            "row": row,
            "chosen": next(
                (fit.extra[k]["chosen"] for k in _VERDICTS if k in fit.extra),
                cfg.combine_rule(crop),
            ),
        },
        t.seconds,
    )
