"""Parameter search for the procedural crop models: Bayesian optimisation and the paper's baselines.

Everything here is generic over the objective: a callable ``objective(x, eval_index) -> float``
taking a parameter vector ``x`` of shape ``(d,)`` inside a box ``bounds`` of shape ``(d, 2)``.
The caller owns the objective's randomness and must make it a function of (seed, eval_index)
(see :func:`evaluation_rng`) so that runs are reproducible and resumable.
"""

from cropcraft_core.optimize.baselines import METHODS, run_method, run_random, run_trust_region
from cropcraft_core.optimize.bo import (
    Aggregate,
    BOConfig,
    SeedResult,
    aggregate,
    check_bounds,
    check_in_bounds,
    evaluation_rng,
    run_seed,
)

__all__ = [
    "Aggregate",
    "BOConfig",
    "SeedResult",
    "aggregate",
    "check_bounds",
    "check_in_bounds",
    "evaluation_rng",
    "run_seed",
    "METHODS",
    "run_method",
    "run_random",
    "run_trust_region",
]
