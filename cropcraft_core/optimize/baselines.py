"""The paper's optimisation baselines, returning the same :class:`SeedResult` as BO.

* ``random``: ``n_evals`` uniform samples of the box, keep the lowest loss.
* ``trust-region``: SciPy ``minimize(method="trust-constr")`` with 2-point finite-difference
  gradients (BFGS Hessian approximation, SciPy's default), at most 500 iterations per start,
  10 uniform random starts, keep the lowest loss seen (supplementary "Baseline Implementation
  Details"). It works in unit-cube coordinates (the boxes' sides differ by up to 26x) with
  ``keep_feasible`` bounds so neither steps nor finite differences leave the box. SciPy's
  2-point step (sqrt(eps), ~1.5e-8 of the unit box) can be below what the rendered
  histograms resolve: on maize with common random numbers no pixel crosses a bin, the
  gradient is exactly zero and each start stops after d + 1 evaluations, so the baseline is
  the best of its random starts (benchmarks/RESULTS.md, *baselines*); soybean's starts, and
  maize's without common random numbers, use their whole budget. Kept as the paper's.

Both are deterministic given (seed, objective values), so a checkpoint resumes them by replaying
its stored evaluations through the algorithm (their own overhead is negligible) and then calling
the objective for the rest. Every evaluation is recorded, so ``X``/``y`` show the whole search.
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np
from scipy.optimize import Bounds, minimize

from cropcraft_core.errors import ConfigError
from cropcraft_core.optimize.bo import (
    BOConfig,
    Callback,
    Objective,
    SeedResult,
    _blas_threads,
    _Evaluations,
    check_bounds,
    load_checkpoint,
    run_seed,
    with_run_id,
)

METHODS = ("bo", "random", "trust-region")


class _Budget(Exception):
    """Internal: the evaluation cap was reached."""


def _check_int(name: str, v: Any, lo: int) -> int:
    if isinstance(v, bool) or not isinstance(v, int | np.integer) or v < lo:
        raise ConfigError(f"{name}={v!r}: must be an integer >= {lo}")
    return int(v)


def _finish(ev: _Evaluations, method: str, seed: int, cfg: dict, checkpoint) -> SeedResult:
    res = ev.result(method, seed, cfg, complete=True)
    if checkpoint is not None:
        res.save(checkpoint)
    return res


def run_random(
    objective: Objective,
    bounds: Any,
    n_evals: int = 500,
    seed: int = 0,
    checkpoint: str | os.PathLike | None = None,
    callback: Callback | None = None,
    checkpoint_every: int = 50,
    run_id: str | None = None,
) -> SeedResult:
    """Random search: ``low + (high - low) * default_rng(seed).random((n_evals, d))``, keep the
    lowest loss. ``bounds`` (d, 2). Checkpointed like :func:`~cropcraft_core.optimize.run_seed`
    (``run_id`` as there)."""
    b = check_bounds(bounds)
    n_evals = _check_int("n_evals", n_evals, 1)
    seed = _check_int("seed", seed, 0)
    checkpoint_every = _check_int("checkpoint_every", checkpoint_every, 1)
    cfg = with_run_id({"n_evals": n_evals}, run_id)
    prev = load_checkpoint(checkpoint, "random", seed, b, cfg)
    if prev is not None and prev.complete:
        return prev
    ev = _Evaluations(objective, b, callback, prev)
    P = b[:, 0] + (b[:, 1] - b[:, 0]) * np.random.default_rng(seed).random((n_evals, b.shape[0]))
    done = False
    try:
        for x in P:
            ev(x)
            if checkpoint is not None and ev.new_since_checkpoint >= checkpoint_every:
                ev.result("random", seed, cfg, complete=False).save(checkpoint)
                ev.new_since_checkpoint = 0
        done = True
        return _finish(ev, "random", seed, cfg, checkpoint)
    finally:
        if not done and checkpoint is not None and ev.n > 0:
            ev.result("random", seed, cfg, complete=False).save(checkpoint)


def run_trust_region(
    objective: Objective,
    bounds: Any,
    seed: int = 0,
    n_starts: int = 10,
    maxiter: int = 500,
    max_evals: int | None = None,
    checkpoint: str | os.PathLike | None = None,
    callback: Callback | None = None,
    checkpoint_every: int = 50,
    run_id: str | None = None,
) -> SeedResult:
    """SciPy trust-constr from ``n_starts`` uniform random starts (``default_rng(seed)``), each
    at most ``maxiter`` iterations with 2-point finite differences; keep the lowest loss seen.

    ``bounds`` (d, 2). ``max_evals`` optionally caps the total evaluations (the paper has no
    cap; with a ~100 ms objective a start costs at most ~(d + 1) x maxiter calls). ``run_id``:
    the objective's identity, as :func:`~cropcraft_core.optimize.run_seed`'s.
    """
    b = check_bounds(bounds)
    seed = _check_int("seed", seed, 0)
    n_starts = _check_int("n_starts", n_starts, 1)
    maxiter = _check_int("maxiter", maxiter, 1)
    if max_evals is not None:
        max_evals = _check_int("max_evals", max_evals, 1)
    checkpoint_every = _check_int("checkpoint_every", checkpoint_every, 1)
    cfg = with_run_id({"n_starts": n_starts, "maxiter": maxiter, "max_evals": max_evals}, run_id)
    prev = load_checkpoint(checkpoint, "trust-region", seed, b, cfg)
    if prev is not None and prev.complete:
        return prev
    d = b.shape[0]
    lo, width = b[:, 0], b[:, 1] - b[:, 0]
    ev = _Evaluations(objective, b, callback, prev)
    starts = np.random.default_rng(seed).random((n_starts, d))

    def f(u: np.ndarray) -> float:
        if max_evals is not None and ev.n >= max_evals:
            raise _Budget
        v = ev(lo + width * np.clip(u, 0.0, 1.0))
        if checkpoint is not None and ev.new_since_checkpoint >= checkpoint_every:
            ev.result("trust-region", seed, cfg, complete=False).save(checkpoint)
            ev.new_since_checkpoint = 0
        return v

    box = Bounds(np.zeros(d), np.ones(d), keep_feasible=True)
    done = False
    try:
        with _blas_threads(1):
            for u0 in starts:
                try:
                    minimize(
                        f,
                        u0,
                        method="trust-constr",
                        jac="2-point",
                        bounds=box,
                        options={"maxiter": maxiter},
                    )
                except _Budget:
                    break
        done = True
        return _finish(ev, "trust-region", seed, cfg, checkpoint)
    finally:
        if not done and checkpoint is not None and ev.n > 0:
            ev.result("trust-region", seed, cfg, complete=False).save(checkpoint)


def run_method(
    method: str,
    objective: Objective,
    bounds: Any,
    seed: int = 0,
    config: BOConfig | None = None,
    checkpoint: str | os.PathLike | None = None,
    callback: Callback | None = None,
) -> SeedResult:
    """Dispatch for a ``--method`` option: ``"bo"`` (:func:`run_seed` with ``config``),
    ``"random"`` (``config.n_evals`` uniform samples) or ``"trust-region"`` (paper settings).
    ``bounds`` (d, 2). Unknown methods raise :class:`ConfigError`."""
    cfg = (config or BOConfig()).validate()
    if method == "bo":
        return run_seed(objective, bounds, cfg, seed, checkpoint, callback)
    if method == "random":
        return run_random(
            objective, bounds, cfg.n_evals, seed, checkpoint, callback, cfg.checkpoint_every
        )
    if method == "trust-region":
        return run_trust_region(
            objective,
            bounds,
            seed,
            checkpoint=checkpoint,
            callback=callback,
            checkpoint_every=cfg.checkpoint_every,
        )
    raise ConfigError(f"unknown optimisation method {method!r}: choose one of {', '.join(METHODS)}")
