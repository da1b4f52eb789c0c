"""The synthetic accuracy benchmark as a flow: one task per fitting method (mapped), the
results written to the scene store under ``benchmarks/accuracy/{crop}/``."""

from __future__ import annotations

import datetime as dt
from typing import Any

from prefect import flow, get_run_logger, task
from prefect.cache_policies import NO_CACHE

from cropcraft_core.store import SceneStore


@task(name="bench-accuracy-method", cache_policy=NO_CACHE)
def bench_method(crop: str, method: str, quick: bool, scenes: int | None) -> dict[str, Any]:
    """``benchmarks.bench_accuracy.run`` for one method; returns its errors and timing (the
    per-scene predictions stay in the stored JSON)."""
    from benchmarks.bench_accuracy import run

    log = get_run_logger()
    res = run(crop, [method], quick, scenes, log=log.info)
    return {"method": method, **res["methods"][method], "truths": res["truths"]}


@flow(name="benchmark", persist_result=False)
def benchmark(
    crop: str = "soybean",
    methods: list[str] | None = None,
    quick: bool = True,
    scenes: int | None = None,
    store: str | None = None,
) -> dict[str, Any]:
    """Synthetic accuracy (the paper's table): truth canopies with random parameters, fitted per
    method; LAIE, LAIPE, AME, ASDE, NDPE, NCPE per method. Stores the full result as JSON and
    returns ``{"key": ..., "errors": {method: {...}}, "seconds_per_scene": {...}}``."""
    st = SceneStore.connect(store)
    methods = list(methods or ["bo", "trust-region", "random"])
    futures = bench_method.map(crop, methods, quick, scenes)
    results = [f.result() for f in futures]
    stamp = dt.datetime.now(dt.UTC).strftime("%Y%m%dT%H%M%SZ")
    key = f"benchmarks/accuracy/{crop}/{stamp}{'-quick' if quick else ''}.json"
    st.put_json(key, {"crop": crop, "quick": quick, "methods": results})
    return {
        "key": st.url(key),
        "errors": {r["method"]: r["errors"] for r in results},
        "seconds_per_scene": {r["method"]: r["seconds_per_scene"] for r in results},
    }
