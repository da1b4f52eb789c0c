"""Stage ``fit_seed``: one optimiser seed of the procedural-model fit (mapped over seeds)."""

from __future__ import annotations

import json
import math
import time
from pathlib import Path
from typing import Any

import numpy as np
from prefect import get_run_logger

from cropcraft_core.errors import InputError
from cropcraft_core.fit import FitConfig, fit_seed
from cropcraft_core.parallel import numba_threads_per_job
from tasks.common import (
    Timer,
    artefact,
    checkpoint_dir,
    load_observation,
    make_record,
    open_store,
    report_progress,
    stage_key,
    stage_task,
    workdir,
)


def fit_config(config: dict[str, Any]) -> FitConfig:
    """The ``FitConfig`` of a fit stage config (extra keys such as ``layout`` ignored)."""
    names = set(FitConfig.__dataclass_fields__)
    return FitConfig(**{k: v for k, v in config.items() if k in names}).validate()


def layout_of(crop: str, config: dict[str, Any]):
    """The planting layout: ``default_layout(crop)`` with ``config["layout"]`` overrides
    (``plot_width``, ``plot_length``, ``row_spacing``, ``density``)."""
    from cropcraft_core.config import default_layout

    return default_layout(crop, **dict(config.get("layout") or {}))


def row_spacing_used(crop: str, config: dict[str, Any]) -> dict[str, Any]:
    """``{"m": ..., "given": ...}``: the planting row spacing a run of ``crop`` fits its rows
    and builds its canopies with (:func:`layout_of`), and whether ``config["layout"]`` gave
    one other than the crop's default (a stage's config leaves the default out:
    ``flows.scene.stage_configs``)."""
    from cropcraft_core.config import default_layout

    m = float(layout_of(crop, config).row_spacing)
    return {"m": m, "given": m != default_layout(crop).row_spacing}


def _best_so_far(checkpoint: Path) -> float:
    """The lowest loss a seed's checkpoint holds (it resumes from there), else +inf."""
    if not checkpoint.exists():
        return float("inf")
    from cropcraft_core.optimize import SeedResult

    try:
        y = np.asarray(SeedResult.load(checkpoint).y, dtype=np.float64)
    except Exception:  # unreadable: the optimiser names it when it loads the checkpoint
        return float("inf")
    finite = y[np.isfinite(y)]
    return float(finite.min()) if finite.size else float("inf")


def _run_name() -> str:
    """``fit_seed-3`` (the best row), ``fit_seed-3@row_p1`` (a neighbour row)."""
    from prefect.runtime import task_run

    from cropcraft_core.rowfit import row_label

    p = task_run.parameters
    row = p.get("row")
    return f"fit_seed-{p.get('seed')}" + ("" if row is None else f"@{row_label(row)}")


@stage_task("fit_seed", task_run_name=_run_name)
def fit_seed_task(
    store_root: str,
    scene: str,
    config: dict[str, Any],
    upstream: dict[str, Any],
    seed: int,
    row: int | None = None,
    lease: str | None = None,
) -> dict[str, Any]:
    """:func:`cropcraft_core.fit.fit_seed` for optimiser ``seed`` against the scene's
    observation (``upstream["observe"]``); stores the
    :class:`~cropcraft_core.optimize.SeedResult` as ``{scene}/fit/seed-{seed}.npz``, or for a
    neighbour ``row`` (its observation from ``observe_rows``) as
    ``{scene}/fit/row_p1/seed-{seed}.npz``.

    A local checkpoint (``$CROPCRAFT_WORK/checkpoints``, named by the cache key) lets a seed
    killed halfway continue where it stopped on the same machine; it is removed on success.
    Progress (with the seed's best loss so far, a resumed seed's stored evaluations included)
    goes to :func:`tasks.common.report_progress` every evaluation and to the run's log every
    10 %. Under ``combine="floors"`` (then part of this stage's config) the seed also polishes
    its point to its floor, stored in the seed's record for the aggregate to rank.

    ``lease``: the token of the run's scene lease (not part of the cache key). On a Dask
    cluster a seed goes on after its run has ended -- failed, interrupted, its client lost --
    so the seed checks that its run still holds the scene before it starts, every 10 % and
    before it writes, and stops without writing where it does not
    (:func:`~cropcraft_core.lease.require_holder`): it never writes over a later run's seeds.
    """
    log = get_run_logger()
    store = open_store(store_root, scene=scene, lease=lease, what=f"fit seed {seed}")
    # the store's own check before each write (its run's lease), asked at the start and every
    # 10 % too: a seed whose run ended stops instead of fitting on for no one
    still_held = store.before_write or (lambda: None)
    still_held()
    cfg = fit_config(config)
    crop = scene.split("/")[1]
    digest = stage_key("fit_seed", scene, config, upstream, {"seed": seed, "row": row})
    digest = digest.rsplit("/", 1)[-1]
    ckpt = checkpoint_dir() / f"{digest}.json"
    total = cfg.n_evals
    step = max(1, total // 10)
    if row is None:
        tag: int | str = int(seed)
    else:
        from cropcraft_core.rowfit import row_label

        tag = f"{row_label(row)}/{int(seed)}"

    best = [_best_so_far(ckpt)]

    def callback(i: int, x: Any, y: float) -> None:
        done = i + 1
        best[0] = min(best[0], float(y))
        report_progress(scene, tag, done, total, best[0])
        if done % step == 0 or done == total:
            log.info("seed %s: %d/%d evaluations, best loss %.4g", tag, done, total, best[0])
            still_held()

    with Timer() as t:
        obs = load_observation(store, upstream)
        with numba_threads_per_job(cfg.n_seeds):  # the seeds run side by side
            try:
                result = fit_seed(obs, int(seed), cfg, layout_of(crop, config), ckpt, callback)
            except InputError as exc:  # a checkpoint cut short or damaged: only a cache
                if str(ckpt) not in str(exc) or not ckpt.exists():
                    raise
                aside = ckpt.with_name(f"{ckpt.stem}.unreadable-{time.time_ns()}.json")
                ckpt.replace(aside)
                log.warning(
                    "seed %s: its checkpoint cannot be used (%s): kept as %s, and the seed "
                    "starts afresh", tag, exc, aside,
                )  # fmt: skip
                best[0] = math.inf
                result = fit_seed(obs, int(seed), cfg, layout_of(crop, config), ckpt, callback)
        # a local search may converge early
        report_progress(scene, tag, total, total, float(result.best_y))
        key = artefact(scene, "fit_seed", f"seed-{int(seed)}.npz", row=row)
        with workdir("seed") as tmp:
            path = result.save(tmp / "seed.npz")
            digest_out = store.put_file(path, key)  # asks the lease too (open_store)
    ckpt.unlink(missing_ok=True)
    summary = {
        "seed": int(seed),
        "row": row,
        "best_loss": float(result.best_y),
        "n_evals": int(result.n_evals),
        "seconds_objective": float(result.seconds_objective),
        "seconds_optimizer": float(result.seconds_optimizer),
    }
    json.dumps(summary)
    return make_record("fit_seed", scene, {"seed": key}, {key: digest_out}, summary, t.seconds)
