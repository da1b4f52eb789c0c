"""The synthetic accuracy benchmark as a flow: one task per (method, scene, optimiser seed),
then one per (method, scene) that combines its seeds under every table row.

At the default budget a crop is 30 scenes × 10 seeds × 500 evaluations (~3 h per crop on one
2-core machine). Every seed is an independent task whose inputs are four small values (the
scene's observation is rebuilt deterministically inside the task), so ``runner="dask://host:port"``
spreads them over a Dask cluster's workers exactly like the scene flow's fit seeds. The table
(``benchmarks.bench_accuracy.score``) and every per-scene prediction are stored as JSON under
``benchmarks/accuracy/{crop}/`` in the scene store.
"""

from __future__ import annotations

import datetime as dt
from typing import Any

from prefect import flow, get_run_logger, task
from prefect.cache_policies import NO_CACHE

from cropcraft_core.errors import ConfigError
from cropcraft_core.fit import FitConfig, fit_seed
from cropcraft_core.store import SceneStore
from flows.runners import make_task_runner

#: Methods the flow maps seed by seed (the mlp baseline predicts directly: use the bench CLI).
SEED_METHODS = ("bo", "trust-region", "random")


@task(name="bench-seed", cache_policy=NO_CACHE)
def bench_seed(crop: str, scene: int, seed: int, fit: dict, scale: float) -> dict[str, Any]:
    """One optimiser seed on one synthetic scene; returns the seed's result (its evaluations,
    best point and loss) and its compute seconds."""
    from benchmarks.bench_accuracy import scene_observation, seed_seconds
    from cropcraft_core.parallel import numba_threads_per_job, reuse_freed_memory

    reuse_freed_memory()  # on a Dask worker: its nanny's malloc trim costs a seed ~1.9x
    _, obs = scene_observation(crop, scene, scale)
    cfg = FitConfig(**fit)
    with numba_threads_per_job(cfg.n_seeds):
        r = fit_seed(obs, seed, cfg)
    return {"scene": scene, "seed": seed, "result": r, "seconds": seed_seconds(r)}


@task(name="bench-combine", cache_policy=NO_CACHE)
def bench_combine(
    crop: str, scene: int, rows: list, results: list, seconds: float, scale: float
) -> dict[str, Any]:
    """One scene's answers under every table row (``[(row, FitConfig dict)]``) from its seeds'
    results: ``{row: (params, seconds)}``. Its own task because the re-scoring rows cost
    minutes per scene, so a cluster spreads them like the seeds."""
    from benchmarks.bench_accuracy import combine_scene, scene_observation
    from cropcraft_core.parallel import reuse_freed_memory

    reuse_freed_memory()
    configs = [(row, FitConfig(**fit)) for row, fit in rows]
    needs_obs = any(cfg.reevaluates(crop) for _, cfg in configs)
    obs = scene_observation(crop, scene, scale)[1] if needs_obs else None
    return combine_scene(crop, configs, results, seconds, obs)


@flow(name="benchmark", persist_result=False, task_runner=make_task_runner())
def benchmark(
    crop: str = "soybean",
    methods: list[str] | None = None,
    quick: bool = True,
    scenes: int | None = None,
    store: str | None = None,
    overrides: dict[str, Any] | None = None,
    image_scale: float | None = None,
) -> dict[str, Any]:
    """Synthetic accuracy (the paper's table): truth canopies with random parameters, fitted per
    method; LAIE, LAIPE, AME, ASDE, NDPE, NCPE per method. Stores the full result as JSON and
    returns ``{"key": store key, "url": ..., "errors": {method: {...}}, "seconds_per_scene":
    {...}, "predictions": {method: [params per scene]}, "budget": {...}}``. ``overrides``
    (FitConfig fields, e.g. ``{"n_seeds": 3}``) and ``image_scale`` change the budget as in
    ``cropcraft bench accuracy``."""
    from benchmarks.bench_accuracy import budget, rules, score, seed_coverage, truth_record

    log = get_run_logger()
    methods = list(methods or ["bo", "trust-region", "random"])
    bad = [m for m in methods if m not in SEED_METHODS]
    if bad:
        raise ConfigError(
            f"benchmark flow methods {bad}: choose from {', '.join(SEED_METHODS)} "
            "(mlp runs in `cropcraft bench accuracy`)"
        )
    st = SceneStore.connect(store)
    b0 = budget(quick, scenes, "bo", overrides=overrides, scale=image_scale)
    truths = [truth_record(crop, i) for i in range(b0.scenes)]
    configs = {
        m: budget(quick, scenes, m, overrides=overrides, scale=image_scale).fit for m in methods
    }
    jobs = [(m, i, s) for m in methods for i in range(b0.scenes) for s in range(configs[m].n_seeds)]
    futures = bench_seed.map(
        [crop] * len(jobs),
        [i for _, i, _ in jobs],
        [s for _, _, s in jobs],
        [configs[m].to_dict() for m, _, _ in jobs],
        [b0.scale] * len(jobs),
    )
    done = [f.result() for f in futures]
    out: dict[str, Any] = {"crop": crop, "quick": quick, "scenes": b0.scenes, "methods": {}}
    for m in methods:
        mine = [d for (mm, _, _), d in zip(jobs, done, strict=True) if mm == m]
        rows = rules(crop, m, configs[m])
        scenes = range(b0.scenes)
        by_scene = [[d for d in mine if d["scene"] == i] for i in scenes]  # in seed order
        answers = bench_combine.map(
            [crop] * b0.scenes,
            list(scenes),
            [[(row, cfg.to_dict()) for row, cfg in rows]] * b0.scenes,
            [[d["result"] for d in ds] for ds in by_scene],
            [sum(d["seconds"] for d in ds) for ds in by_scene],
            [b0.scale] * b0.scenes,
        )
        answers = [a.result() for a in answers]
        for row, cfg in rows:
            params = [a[row][0] for a in answers]
            seconds = [a[row][1] for a in answers]
            out["methods"][row] = score(crop, params, truths, seconds, log=log.info)
            out["methods"][row]["budget"] = {**cfg.to_dict(), "image_scale": b0.scale}
        # the seeds' own answers around the truth (bench_accuracy.seed_coverage)
        box = configs[m].param_box(crop)
        out["methods"][m]["seed_spread"] = seed_coverage(
            crop,
            [[box.params(d["result"].reported_x) for d in ds] for ds in by_scene],
            truths,
            list(scenes),
        )
    out["truths"] = truths
    stamp = dt.datetime.now(dt.UTC).strftime("%Y%m%dT%H%M%SZ")
    key = f"benchmarks/accuracy/{crop}/{stamp}{'-quick' if quick else ''}.json"
    st.put_json(key, out)
    rows = out["methods"]
    return {
        "key": key,
        "url": st.url(key),
        "errors": {m: r["errors"] for m, r in rows.items()},
        "seconds_per_scene": {m: r["seconds_per_scene"] for m, r in rows.items()},
        "predictions": {m: [p["params"] for p in r["predictions"]] for m, r in rows.items()},
        "seed_spread": {m: r["seed_spread"] for m, r in rows.items() if "seed_spread" in r},
        "budget": {**b0.fit.to_dict(), "image_scale": b0.scale},
    }


def run_benchmark(
    runner: str | None = None, workers: int | None = None, **kwargs: Any
) -> dict[str, Any]:
    """:func:`benchmark` on ``runner`` (processes, threads, dask, dask://HOST:PORT; default
    the scene flows' ``processes``, ``flows.runners.DEFAULT_RUNNER``) of ``workers`` processes
    or threads (a local pool's or cluster's; default :func:`~flows.runners.make_task_runner`'s)."""
    runner_ = make_task_runner(runner, workers=workers)
    return benchmark.with_options(task_runner=runner_)(**kwargs)
