"""The paper's optimiser, for benchmarks only: scikit-optimize ``gp_minimize`` with a Matérn
kernel and expected improvement, 200 random initial points, 500 evaluations.

scikit-optimize (archived upstream in 2024) is imported lazily so the package does not need it.
Its per-iteration cost grows roughly as n^1.9 (a full scikit-learn GP hyper-parameter fit with
restarts on every iteration): ~25 minutes of optimiser time per seed at n = 500.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from cropcraft_core.errors import ConfigError
from cropcraft_core.optimize.bo import (
    Callback,
    Objective,
    SeedResult,
    _blas_threads,
    _Evaluations,
    check_bounds,
)


def run_skopt(
    objective: Objective,
    bounds: Any,
    *,
    seed: int = 0,
    n_evals: int = 500,
    n_initial: int = 200,
    xi: float = 0.01,
    blas_threads: int | None = 1,
    callback: Callback | None = None,
) -> SeedResult:
    """Run ``skopt.gp_minimize(acq_func="EI", n_initial_points=n_initial, n_calls=n_evals,
    initial_point_generator="random", random_state=seed)`` (its default base estimator: Matérn-5/2
    ARD + white noise, normalised outputs; EI maximised by L-BFGS from random starts).

    Returns a :class:`SeedResult` with method ``"skopt"``: ``best_x`` is gp_minimize's answer
    (lowest observation), ``best_x_posterior`` the observed point with the lowest mean of its
    last GP. ``seconds_per_eval`` (n,) is skopt's own overhead before each evaluation.
    """
    try:
        from skopt import gp_minimize
    except ImportError as e:  # pragma: no cover
        raise ConfigError("scikit-optimize is not installed: pip install scikit-optimize") from e
    b = check_bounds(bounds)
    if n_initial > n_evals:
        raise ConfigError(f"n_initial={n_initial} exceeds n_evals={n_evals}")
    ev = _Evaluations(objective, b, callback)

    def f(x: list[float]) -> float:
        return ev(np.asarray(x, dtype=np.float64))

    with _blas_threads(blas_threads):
        res = gp_minimize(
            f,
            [(float(lo), float(hi)) for lo, hi in b],
            n_calls=n_evals,
            n_initial_points=n_initial,
            initial_point_generator="random",
            acq_func="EI",
            xi=xi,
            random_state=seed,
        )
        X, _ = ev.arrays()
        post_x, post_mu = None, None
        if res.models:
            model = res.models[-1]
            Xt = np.asarray(res.space.transform(X.tolist()))
            mu = model.predict(Xt)
            k = int(np.argmin(mu))
            post_x, post_mu = X[k].copy(), float(mu[k])
    out = ev.result(
        "skopt",
        seed,
        {"n_evals": n_evals, "n_initial": n_initial, "xi": xi, "acq_func": "EI"},
        best_x_posterior=post_x,
        best_mean_posterior=post_mu,
    )
    return out
