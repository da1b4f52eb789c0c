"""Bayesian optimisation of a noisy black-box objective over a box: one seed at a time.

:func:`run_seed` is a pure, resumable function ``(objective, bounds, config, seed) -> SeedResult``;
the orchestration layer maps it over seeds (one process each, single-threaded BLAS) and combines
the results with :func:`aggregate` (the paper averages the 10 seeds' best parameters).

Objective contract: ``objective(x, eval_index) -> float`` with ``x`` of shape ``(d,)`` inside
``bounds`` ``(d, 2)`` and ``eval_index`` = 0, 1, 2, ... the position of the call in the seed's run.
Its randomness (the procedural model samples leaf angles) must be a function of the caller's
(seed, eval_index), e.g. through :func:`evaluation_rng`; with that, a seed's run is reproducible
and a resumed run is identical to an uninterrupted one.

Noise treatment (measured in ``benchmarks/bench_optimizer.py``): *common random numbers* within a
seed, i.e. ``evaluation_rng(seed, i, common=True)`` ignores ``i`` and every evaluation of a seed
re-uses the same random draws. The objective seen by one seed is then a deterministic function of
x (smooth where the model is), the GP does not have to average noise away, and the different
seeds see different draws, so averaging the seeds' answers (the paper's aggregation) also averages
the draw-specific bias. Independent draws per evaluation remain possible (``common=False``); the
GP then learns the noise level and the posterior-mean argmin (``best_x_posterior``) is the robust
report. Measured (``benchmarks/bench_optimizer.py``: 5-D Hartmann, n = 500 / 200 initial,
noise-free f at the reported point, optimum -3.322):

* noise sd 0.1 (5 seeds): common random numbers -3.296 +- 0.020 per seed, -3.321 at the seeds'
  mean point; independent draws -3.201 +- 0.207 (one seed never left a local basin), -3.295.
* noise sd 0.3 (3 seeds): common random numbers -3.060 +- 0.27 (one realisation's argmin is
  biased by the noise field); independent draws -3.242 +- 0.04.

So common random numbers help while the loss's sampling noise is small against its variation
over the box (the expected case for a histogram over thousands of leaves); when it is not,
use independent draws and report ``best_x_posterior``. Measure the ratio first: the standard
deviation of the loss over ~10 draws at one point versus that over the initial design.

Two settings go beyond the paper's optimiser (both off by default here; the fitting layer
chooses per crop): ``local_evals`` spends the last evaluations on Nelder-Mead from the lowest
observed point, and ``output_transform="log"`` lets the GP model log(loss). Why: on the
soybean accuracy scenes the histogram loss spans 0.005-2.3 over one seed's run, and a
stationary GP over the whole box leaves narrow valleys unresolved. On scene 1 the seed's
best point was 0.04 of the box from the truth, yet scored 2.6e-2 against the truth's 3.2e-3
on that seed's own (deterministic) objective, and the loss fell monotonically along the line
between them; 100 Nelder-Mead evaluations from it reached 9e-4. Paired runs, soybean scenes
0-11, optimiser seed 0, 500 evaluations (200 initial, the same design in each):

=============================  ====================  =========================================
GP output, closing local       geo-mean best loss    mean |error| of the seed's point, box units
=============================  ====================  =========================================
loss, none (paper)             1.14e-2               0.188
log(loss), 100 Nelder-Mead     6.3e-3                0.183
loss, 100 Nelder-Mead          4.5e-3                0.153
=============================  ====================  =========================================

On all 10 seeds of scenes 0-15 (160 pairs) the closing search still halved the loss (5.5e-3
against 1.1e-2, lower on 143), but the mean error was 0.187 against 0.182: below the paper's
optimiser's level, lower minima of one seed's canopies fit those canopies, not the parameters.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import threading
import time
import zipfile
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
from scipy.optimize import minimize
from scipy.stats import qmc

from cropcraft_core.errors import ConfigError, InputError
from cropcraft_core.optimize import gp as gpmod

Objective = Callable[[np.ndarray, int], float]
Callback = Callable[[int, np.ndarray, float], None]

CHECKPOINT_VERSION = 1
OUTPUT_TRANSFORMS = ("none", "log")


# --------------------------------------------------------------------------------------------
# Configuration and validation
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class BOConfig:
    """Settings of one Bayesian-optimisation seed (paper defaults where the paper gives one)."""

    n_evals: int = 500
    """Total objective evaluations, initial design included (paper: 500)."""
    n_initial: int = 200
    """Uniform random initial evaluations drawn from ``default_rng(seed)`` (paper: 200)."""
    refit_every: int = 10
    """Refit the GP hyper-parameters (L-BFGS-B, warm start) every this many evaluations;
    between refits the Cholesky factor grows by O(n^2) rank-one extensions."""
    first_fit_restarts: int = 3
    """Extra random L-BFGS-B starts for the first hyper-parameter fit (later fits warm-start)."""
    noise_variance: float | None = None
    """Observation-noise variance in standardised output units; ``None`` learns it by maximum
    likelihood within [1e-6, 1] (right for both common-random-number and independent noise)."""
    candidates: int = 1024
    """Scrambled-Sobol candidates over the whole box per acquisition step (rounded to 2^k)."""
    local_candidates: int = 512
    """Gaussian perturbations of the current best points added to the candidate set."""
    local_scale: float = 0.05
    """Standard deviation of those perturbations, as a fraction of each box side."""
    n_polish: int = 5
    """Best candidates polished by L-BFGS-B on log EI (analytic gradient)."""
    polish_maxiter: int = 50
    """Iteration cap of each polish."""
    output_transform: str = "none"
    """What the GP models: ``none``, the objective's values; ``log``, ``log(y + log_offset)``
    (for a non-negative loss spanning orders of magnitude, so that the region near the optimum
    is not flattened by the far worse values of the initial design)."""
    log_offset: float = 1e-6
    """``log`` transform: added before the logarithm, so a loss of exactly 0 stays finite."""
    local_evals: int = 0
    """The last this many of ``n_evals`` go to a local search: Nelder-Mead from the lowest
    observed point (in the unit cube, first simplex a ``local_step`` along each axis towards the
    box's inside). A stationary GP over the whole box resolves a narrow valley poorly, while
    the objective under common random numbers is deterministic, so a simplex can follow the
    valley to its floor. It may stop early once the simplex has shrunk to 1e-3."""
    local_step: float = 0.05
    """Side of the local search's first simplex, as a fraction of each box side."""
    xi: float = 0.01
    """EI exploration margin in standardised output units (scikit-optimize's default 0.01)."""
    checkpoint_every: int = 10
    """Write the checkpoint (atomically) every this many new evaluations, and always on exit."""
    blas_threads: int | None = 1
    """BLAS/OpenMP threads while a seed runs (seeds run in parallel processes); None: leave."""

    def validate(self) -> BOConfig:
        """Raise :class:`ConfigError` naming the first bad field; return self."""
        ints = {
            "n_evals": (1, None),
            "n_initial": (2, None),
            "refit_every": (1, None),
            "first_fit_restarts": (0, None),
            "candidates": (1, None),
            "local_candidates": (0, None),
            "n_polish": (0, None),
            "polish_maxiter": (1, None),
            "checkpoint_every": (1, None),
            "local_evals": (0, None),
        }
        for name, (lo, _) in ints.items():
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int | np.integer) or v < lo:
                raise ConfigError(f"BOConfig.{name}={v!r}: must be an integer >= {lo}")
        if self.n_initial > self.n_evals:
            raise ConfigError(
                f"BOConfig.n_initial={self.n_initial} exceeds n_evals={self.n_evals}: "
                "lower n_initial or raise n_evals"
            )
        if self.local_evals > self.n_evals - self.n_initial:
            raise ConfigError(
                f"BOConfig.local_evals={self.local_evals} exceeds the "
                f"{self.n_evals - self.n_initial} evaluations after the initial design"
            )
        if not (_number(self.local_step) and 0 < self.local_step <= 0.5):
            raise ConfigError(f"BOConfig.local_step={self.local_step!r}: must be in (0, 0.5]")
        if self.output_transform not in OUTPUT_TRANSFORMS:
            raise ConfigError(
                f"BOConfig.output_transform={self.output_transform!r}: "
                f"choose one of {', '.join(OUTPUT_TRANSFORMS)}"
            )
        if not (
            _number(self.log_offset) and math.isfinite(self.log_offset) and self.log_offset > 0
        ):
            raise ConfigError(
                f"BOConfig.log_offset={self.log_offset!r}: must be a finite number > 0"
            )
        for name in ("xi", "local_scale"):
            v = getattr(self, name)
            if not _number(v) or not math.isfinite(v) or v < 0:
                raise ConfigError(f"BOConfig.{name}={v!r}: must be a finite number >= 0")
        if self.local_scale > 1:  # a fraction of the box's side
            raise ConfigError(f"BOConfig.local_scale={self.local_scale!r}: must be at most 1")
        if self.noise_variance is not None and not (
            _number(self.noise_variance)
            and gpmod.NOISE_VARIANCE_BOUNDS[0] <= self.noise_variance <= 10.0
        ):
            raise ConfigError(
                f"BOConfig.noise_variance={self.noise_variance!r}: None (learned) or in [1e-6, 10]"
            )
        if self.blas_threads is not None and (
            not isinstance(self.blas_threads, int)
            or isinstance(self.blas_threads, bool)
            or self.blas_threads < 1
        ):
            raise ConfigError(f"BOConfig.blas_threads={self.blas_threads!r}: None or >= 1")
        return self

    def result_fields(self) -> dict[str, Any]:
        """The fields that change the evaluated points (a resumed run must match them), as
        plain Python values (a numpy integer from a sweep is stored as a JSON number)."""
        d = {k: v.item() if isinstance(v, np.generic) else v for k, v in asdict(self).items()}
        for k in ("checkpoint_every", "blas_threads"):
            d.pop(k)
        # as recorded before these settings existed, where they change nothing
        if self.output_transform == "none":
            d.pop("output_transform")
            d.pop("log_offset")
        if self.local_evals == 0:
            d.pop("local_evals")
            d.pop("local_step")
        return d

    def model_values(self, y: np.ndarray) -> np.ndarray:
        """The objective's values ``y`` as the GP models them (``output_transform``)."""
        y = np.asarray(y, dtype=np.float64)
        if self.output_transform == "none":
            return y
        if np.any(y < 0):
            raise InputError(
                f"the objective returned {float(y.min()):g} < 0, which output_transform='log' "
                "cannot model: use output_transform='none' for objectives that go negative"
            )
        return np.log(y + self.log_offset)

    def objective_value(self, z: float) -> float:
        """The inverse of :meth:`model_values` (a GP mean back in the objective's units)."""
        return z if self.output_transform == "none" else math.exp(z) - self.log_offset


def _number(v: Any) -> bool:
    """A real number, not a boolean (``True`` passed for 1.0 where a setting was misparsed)."""
    return isinstance(v, int | float) and not isinstance(v, bool)


def check_bounds(bounds: Any) -> np.ndarray:
    """Validate a parameter box: finite, shape (d, 2), low < high. Returns it as float64."""
    try:
        b = np.array(bounds, dtype=np.float64)
    except (TypeError, ValueError):
        raise ConfigError(f"bounds must be a (d, 2) array of numbers, got {bounds!r}") from None
    if b.ndim != 2 or b.shape[1] != 2 or b.shape[0] < 1:
        raise ConfigError(f"bounds must have shape (d, 2) with d >= 1, got shape {b.shape}")
    if not np.all(np.isfinite(b)):
        raise ConfigError("bounds must be finite")
    bad = np.flatnonzero(~(b[:, 0] < b[:, 1]))
    if bad.size:
        i = int(bad[0])
        raise ConfigError(f"bounds[{i}] = [{b[i, 0]:g}, {b[i, 1]:g}]: low must be < high")
    with np.errstate(over="ignore"):
        wide = np.flatnonzero(~np.isfinite(b[:, 1] - b[:, 0]))
    if wide.size:
        i = int(wide[0])
        raise ConfigError(f"bounds[{i}] = [{b[i, 0]:g}, {b[i, 1]:g}]: its width overflows")
    return b


def check_in_bounds(x: Any, bounds: np.ndarray, *, what: str = "x", rtol: float = 1e-9) -> None:
    """Raise :class:`ConfigError` if ``x`` (d,) is not finite or lies outside ``bounds`` (d, 2)
    by more than ``rtol`` of the box side."""
    x = np.asarray(x, dtype=np.float64)
    if x.shape != (bounds.shape[0],):
        raise ConfigError(f"{what} has shape {x.shape}, the parameter box has {bounds.shape[0]}")
    if not np.all(np.isfinite(x)):
        raise ConfigError(f"{what} = {x.tolist()} is not finite")
    tol = rtol * (bounds[:, 1] - bounds[:, 0])
    out = np.flatnonzero((x < bounds[:, 0] - tol) | (x > bounds[:, 1] + tol))
    if out.size:
        i = int(out[0])
        raise ConfigError(
            f"{what}[{i}] = {x[i]:g} is outside the parameter box "
            f"[{bounds[i, 0]:g}, {bounds[i, 1]:g}]"
        )


def evaluation_rng(seed: int, eval_index: int, *, common: bool = True) -> np.random.Generator:
    """The Generator an objective should use for evaluation ``eval_index`` of seed ``seed``.

    ``common=True`` (recommended): common random numbers, the same stream for every evaluation
    of the seed (different seeds differ). ``common=False``: an independent stream per evaluation.
    Either way a function of (seed, eval_index) only, so runs are reproducible and resumable.
    """
    key = [int(seed), 0xC0DE] if common else [int(seed), 0xC0DE, int(eval_index) + 1]
    return np.random.default_rng(key)


# --------------------------------------------------------------------------------------------
# Result type
# --------------------------------------------------------------------------------------------


def _arr(v: Any) -> np.ndarray | None:
    return None if v is None else np.asarray(v, dtype=np.float64)


@dataclass
class SeedResult:
    """Everything one seed's run produced. JSON- and npz-serialisable (:meth:`save`, :meth:`load`).

    Arrays: ``bounds`` (d, 2); ``X`` (n, d) every evaluated point in order; ``y`` (n,) their
    losses; ``seconds_per_eval`` (n,) optimiser (not objective) wall seconds spent before each
    evaluation; ``best_x`` (d,) the lowest observed point and ``best_y`` its loss;
    ``best_x_posterior`` (d,) the observed point with the lowest GP posterior mean (the robust
    answer under noise; None for methods without a model) and ``best_mean_posterior`` that mean.
    """

    method: str
    seed: int
    bounds: np.ndarray
    X: np.ndarray
    y: np.ndarray
    best_x: np.ndarray
    best_y: float
    seconds_optimizer: float
    seconds_objective: float
    seconds_per_eval: np.ndarray
    best_x_posterior: np.ndarray | None = None
    best_mean_posterior: float | None = None
    cpu_seconds_optimizer: float = math.nan
    """Process CPU seconds of the optimiser (robust to a loaded machine; = wall single-threaded)."""
    cpu_per_eval: np.ndarray | None = None
    """(n,) optimiser CPU seconds before each evaluation."""
    hyperparameters: dict[str, Any] | None = None
    config: dict[str, Any] = field(default_factory=dict)
    complete: bool = True
    state: dict[str, Any] = field(default_factory=dict)
    """Method-private resume state (GP hyper-parameter history); empty when complete."""
    floor: dict[str, Any] | None = None
    """The seed's reported point polished on the fit's shared re-scoring canopies, where the
    fit's answer rule asks each seed for it (``combine="floors"``: ``fit.select.seed_floor``):
    ``{"x", "loss", "evals", "canopy_seeds", "polish_evals", "seconds"}``; None otherwise."""

    @property
    def n_evals(self) -> int:
        return int(self.y.shape[0])

    @property
    def reported_x(self) -> np.ndarray:
        """The seed's answer (d,): the posterior-mean argmin when there is one, else best_x."""
        return self.best_x if self.best_x_posterior is None else self.best_x_posterior

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-able dict (floats round-trip exactly through ``json``)."""
        out: dict[str, Any] = {"version": CHECKPOINT_VERSION}
        for f in fields(self):
            v = getattr(self, f.name)
            out[f.name] = v.tolist() if isinstance(v, np.ndarray) else v
        return out

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> SeedResult:
        if not isinstance(d, dict):
            raise InputError(f"not a SeedResult record: a {type(d).__name__}")
        if d.get("version", CHECKPOINT_VERSION) != CHECKPOINT_VERSION:
            raise InputError(
                f"a SeedResult of format {d.get('version')!r}, not {CHECKPOINT_VERSION}"
            )
        try:
            n_d = len(d["bounds"])
            X = np.asarray(d["X"], dtype=np.float64).reshape(-1, n_d)
            return cls(
                method=str(d["method"]),
                seed=int(d["seed"]),
                bounds=np.asarray(d["bounds"], dtype=np.float64),
                X=X,
                y=np.asarray(d["y"], dtype=np.float64),
                best_x=np.asarray(d["best_x"], dtype=np.float64),
                best_y=float(d["best_y"]),
                seconds_optimizer=float(d["seconds_optimizer"]),
                seconds_objective=float(d["seconds_objective"]),
                seconds_per_eval=np.asarray(d["seconds_per_eval"], dtype=np.float64),
                best_x_posterior=_arr(d.get("best_x_posterior")),
                best_mean_posterior=d.get("best_mean_posterior"),
                cpu_seconds_optimizer=float(d.get("cpu_seconds_optimizer", math.nan)),
                cpu_per_eval=_arr(d.get("cpu_per_eval")),
                hyperparameters=d.get("hyperparameters"),
                config=dict(d.get("config") or {}),
                complete=bool(d.get("complete", True)),
                state=dict(d.get("state") or {}),
                floor=d.get("floor"),
            )
        except (KeyError, TypeError, ValueError) as e:
            raise InputError(f"not a SeedResult record: {e!r}") from None

    def save(self, path: str | os.PathLike) -> Path:
        """Write atomically to ``path``: ``.npz`` as arrays (+ a JSON header), else JSON."""
        path = Path(path)
        if path.suffix == ".npz":
            d = self.to_dict()
            arrays = {k: np.asarray(getattr(self, k)) for k in ("bounds", "X", "y")}
            meta = {k: v for k, v in d.items() if k not in arrays}
            payload = {**arrays, "meta": np.array(json.dumps(meta))}
            _atomic_write(path, lambda f: np.savez(f, **payload))
        else:
            text = json.dumps(self.to_dict())
            _atomic_write(path, lambda f: f.write(text.encode()))
        return path

    @classmethod
    def load(cls, path: str | os.PathLike) -> SeedResult:
        path = Path(path)
        try:
            if path.suffix == ".npz":
                with np.load(path, allow_pickle=False) as z:
                    d = json.loads(str(z["meta"]))
                    for k in ("bounds", "X", "y"):
                        d[k] = z[k]
            else:
                d = json.loads(path.read_text())
        except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as e:
            raise InputError(f"cannot read seed result {path}: {e}") from None
        try:
            return cls.from_dict(d)
        except InputError as e:
            raise InputError(f"cannot read seed result {path}: {e}") from None


def _atomic_write(path: Path, write: Callable[[Any], Any]) -> None:
    """Write via a temp file in the same folder + fsync + os.replace (no torn checkpoints), with
    the usual file mode (:func:`cropcraft_core.export.atomic_path`)."""
    from cropcraft_core.export.atomic import atomic_path

    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        write(f)


class Aggregate(NamedTuple):
    """Combination of several seeds: ``mean_x`` (d,), ``std_x`` (d,) (sample spread, ddof=1
    when there are >= 2 seeds) and ``per_seed`` (S, d), each seed's reported point."""

    mean_x: np.ndarray
    std_x: np.ndarray
    per_seed: np.ndarray


def aggregate(seed_results: list[SeedResult], *, use: str = "reported") -> Aggregate:
    """The paper's final parameters: the mean over seeds of each seed's best parameters.

    ``use``: ``"reported"`` (posterior-mean argmin when available, else lowest observed),
    ``"posterior"`` or ``"observed"``. The mean of points in a box stays in the box.
    """
    if not seed_results:
        raise ConfigError("aggregate needs at least one seed result")
    if use not in ("reported", "posterior", "observed"):
        raise ConfigError(f"aggregate use={use!r}: choose reported, posterior or observed")
    rows = []
    for r in seed_results:
        if use == "observed":
            rows.append(r.best_x)
        elif use == "posterior":
            if r.best_x_posterior is None:
                raise ConfigError(f"seed {r.seed} ({r.method}) has no posterior best point")
            rows.append(r.best_x_posterior)
        else:
            rows.append(r.reported_x)
    first = seed_results[0]
    for r, row in zip(seed_results, rows, strict=True):
        if np.shape(row) != np.shape(rows[0]):
            raise ConfigError(
                f"seed {r.seed} has {np.size(row)} parameters, seed {first.seed} "
                f"{np.size(rows[0])}: seeds of one fit share its parameter box"
            )
    P = np.vstack(rows)
    std = P.std(0, ddof=1) if P.shape[0] > 1 else np.zeros(P.shape[1])
    return Aggregate(P.mean(0), std, P)


# --------------------------------------------------------------------------------------------
# Evaluation bookkeeping shared by BO and the baselines
# --------------------------------------------------------------------------------------------


class _Evaluations:
    """Calls the objective in order, times optimiser vs objective, checks the box, replays a
    checkpoint's stored values and writes checkpoints."""

    def __init__(
        self,
        objective: Objective,
        bounds: np.ndarray,
        callback: Callback | None = None,
        replay: SeedResult | None = None,
    ):
        self.objective = objective
        self.bounds = bounds
        self.callback = callback
        self.X: list[np.ndarray] = []
        self.y: list[float] = []
        self.t_opt: list[float] = []
        self.c_opt: list[float] = []
        self.seconds_objective = 0.0
        self.cpu_before = 0.0
        self.seconds_optimizer_before = 0.0
        self._replay_X = np.empty((0, bounds.shape[0])) if replay is None else replay.X
        self._replay_y = np.empty(0) if replay is None else replay.y
        if replay is not None:
            self.seconds_objective = replay.seconds_objective
            self.seconds_optimizer_before = replay.seconds_optimizer - float(
                np.sum(replay.seconds_per_eval)
            )
            self._replay_t = list(replay.seconds_per_eval)
            self._replay_c = list(replay.cpu_per_eval) if replay.cpu_per_eval is not None else []
            self._replay_c += [0.0] * (len(self._replay_t) - len(self._replay_c))
            if math.isfinite(replay.cpu_seconds_optimizer):
                self.cpu_before = replay.cpu_seconds_optimizer - float(sum(self._replay_c))
        else:
            self._replay_t, self._replay_c = [], []
        self.new_since_checkpoint = 0
        self._mark = time.perf_counter()
        self._cmark = time.process_time()

    @property
    def n(self) -> int:
        return len(self.y)

    def restore_all(self, limit: int | None = None) -> None:
        """Adopt the first ``limit`` (default: every) stored evaluations as-is (BO resume: its
        state is rebuilt, not replayed); later ones are replayed through :meth:`__call__`."""
        n = len(self._replay_y) if limit is None else min(limit, len(self._replay_y))
        for i in range(n):
            self.X.append(self._replay_X[i].copy())
            self.y.append(float(self._replay_y[i]))
            self.t_opt.append(float(self._replay_t[i]))
            self.c_opt.append(float(self._replay_c[i]))
        self._mark = time.perf_counter()
        self._cmark = time.process_time()

    def __call__(self, x: np.ndarray) -> float:
        x = np.asarray(x, dtype=np.float64).copy()
        check_in_bounds(x, self.bounds, what=f"evaluation {self.n} point")
        x = np.clip(x, self.bounds[:, 0], self.bounds[:, 1])
        i = self.n
        if i < len(self._replay_y):
            # Deterministic replay (baselines): the algorithm re-proposes the same point.
            if not np.array_equal(x, self._replay_X[i]):
                raise InputError(
                    f"checkpoint replay diverged at evaluation {i}: the stored point differs; "
                    "the checkpoint belongs to another run (delete it to start over)"
                )
            self.X.append(x)
            self.y.append(float(self._replay_y[i]))
            self.t_opt.append(float(self._replay_t[i]))
            self.c_opt.append(float(self._replay_c[i]))
            self._mark = time.perf_counter()
            self._cmark = time.process_time()
            return self.y[-1]
        t0, c0 = time.perf_counter(), time.process_time()
        self.t_opt.append(t0 - self._mark)
        self.c_opt.append(c0 - self._cmark)
        value = self.objective(x.copy(), i)
        self.seconds_objective += time.perf_counter() - t0
        c1 = time.process_time()
        try:
            value = float(value)
        except (TypeError, ValueError):
            raise InputError(
                f"objective returned {value!r} at evaluation {i}, not a number"
            ) from None
        if not math.isfinite(value):
            raise InputError(f"objective returned {value} at evaluation {i} (x = {x.tolist()})")
        self.X.append(x)
        self.y.append(value)
        self.new_since_checkpoint += 1
        if self.callback is not None:
            self.callback(i, x, value)
        self._mark = time.perf_counter()
        self._cmark = c1
        return value

    def arrays(self) -> tuple[np.ndarray, np.ndarray]:
        d = self.bounds.shape[0]
        return np.asarray(self.X, dtype=np.float64).reshape(-1, d), np.asarray(self.y, float)

    def seconds_optimizer(self) -> float:
        tail = time.perf_counter() - self._mark
        return self.seconds_optimizer_before + float(np.sum(self.t_opt)) + tail

    def cpu_optimizer(self) -> float:
        tail = time.process_time() - self._cmark
        return self.cpu_before + float(np.sum(self.c_opt)) + tail

    def result(self, method: str, seed: int, config: dict, **extra: Any) -> SeedResult:
        X, y = self.arrays()
        if y.size:
            i = int(np.argmin(y))
            best_x, best_y = X[i].copy(), float(y[i])
        else:
            best_x, best_y = np.full(self.bounds.shape[0], np.nan), math.inf
        return SeedResult(
            method=method,
            seed=int(seed),
            bounds=self.bounds.copy(),
            X=X,
            y=y,
            best_x=best_x,
            best_y=best_y,
            seconds_optimizer=self.seconds_optimizer(),
            seconds_objective=self.seconds_objective,
            seconds_per_eval=np.asarray(self.t_opt, dtype=np.float64),
            cpu_seconds_optimizer=self.cpu_optimizer(),
            cpu_per_eval=np.asarray(self.c_opt, dtype=np.float64),
            config=config,
            **extra,
        )


def with_run_id(config: dict, run_id: str | None) -> dict:
    """An optimiser's result config with the objective's identity (none: as it was)."""
    return config if run_id is None else {**config, "objective": str(run_id)}


def _run_differences(
    r: SeedResult, method: str, seed: int, bounds: np.ndarray, config: dict
) -> list[str]:
    """What makes stored run ``r`` another run than (method, seed, bounds, config), in words."""
    out = []
    if r.method != method:
        out.append(f"method {r.method!r}, now {method!r}")
    if r.seed != int(seed):
        out.append(f"seed {r.seed}, now {int(seed)}")
    if r.bounds.shape != bounds.shape or not np.array_equal(r.bounds, bounds):
        out.append(f"box {r.bounds.tolist()}, now {bounds.tolist()}")
    for k in sorted(set(r.config) | set(config)):
        was, now = r.config.get(k), config.get(k)
        if was == now:
            continue
        if k == "objective":  # the fit's seed_identity: the observation and fit settings
            out.append("the objective (observation or fit settings) differs")
        else:
            out.append(f"{k} {was!r}, now {now!r}")
    return out


def load_checkpoint(
    checkpoint: str | os.PathLike | None, method: str, seed: int, bounds: np.ndarray, config: dict
) -> SeedResult | None:
    """The stored run at ``checkpoint`` if it exists, after checking it is this run's and
    whole (finite losses, points inside the bounds, a finished run of its full budget)."""
    if checkpoint is None or not Path(checkpoint).exists():
        return None
    r = SeedResult.load(checkpoint)
    differs = _run_differences(r, method, seed, bounds, config)
    if differs:
        raise ConfigError(
            f"checkpoint {checkpoint} belongs to another run ({'; '.join(differs)}): "
            "use another checkpoint path or delete it"
        )
    try:  # every stored point as the evaluations checked it
        for i, x in enumerate(r.X):
            check_in_bounds(x, bounds, what=f"evaluation {i} point")
        inside = True
    except ConfigError:
        inside = False
    budget = config.get("n_evals")
    # a finished run used its whole budget, but for BO's closing Nelder-Mead, which may stop
    # once its simplex has shrunk (up to local_evals early), and trust-region's own stops
    fewest = budget - int(config.get("local_evals") or 0) if budget else None
    if (
        len(r.X) != len(r.y)
        or not np.all(np.isfinite(r.y))
        or not inside
        or (r.complete and method != "trust-region" and budget and not fewest <= len(r.y) <= budget)
    ):
        raise InputError(
            f"checkpoint {checkpoint} is damaged (non-finite losses, points outside the box, "
            "or a finished run short of its budget): delete it to start the seed afresh"
        )
    return r


_BLAS_LOCK = threading.Lock()
_BLAS_HOLDERS: dict[int, int] = {}
"""Seeds now inside :func:`_blas_threads`, by limit."""
_BLAS_LIMITER: Any = None


@contextlib.contextmanager
def _blas_threads(n: int | None):
    """Hold the process's BLAS/OpenMP pools at ``n`` threads while any seed runs.

    The limit is process-wide (threadpoolctl sets it in the libraries), so seeds running on
    threads of one process share it: the first seed in sets it, the last one out restores it. A
    plain ``threadpool_limits`` per seed restores the old limit when the first seed finishes,
    under the feet of the others, and OpenBLAS with 2 threads gives other last bits than with 1
    — which, over a BO trajectory, makes another fit (measured: the CI failure of session 1).
    threadpoolctl ≥ 3.8 lets only one "controlling" thread limit a pthreads OpenBLAS and
    silently ignores the others, so the thread that sets or restores takes control first
    (``clear_controlling_thread(force=True)``, its documented escape hatch), under our lock.
    """
    global _BLAS_LIMITER
    if n is None:
        yield
        return
    from threadpoolctl import OpenBLASController, threadpool_limits

    with _BLAS_LOCK:
        others = {k: v for k, v in _BLAS_HOLDERS.items() if v > 0 and k != n}
        if others:
            raise RuntimeError(
                f"seeds with blas_threads={sorted(others)} are running in this process; "
                f"a seed with blas_threads={n} would change their results"
            )
        if _BLAS_HOLDERS.get(n, 0) == 0:
            OpenBLASController.clear_controlling_thread(force=True)
            _BLAS_LIMITER = threadpool_limits(limits=n)
        _BLAS_HOLDERS[n] = _BLAS_HOLDERS.get(n, 0) + 1
    try:
        yield
    finally:
        with _BLAS_LOCK:
            _BLAS_HOLDERS[n] -= 1
            if _BLAS_HOLDERS[n] == 0:
                OpenBLASController.clear_controlling_thread(force=True)
                _BLAS_LIMITER.restore_original_limits()
                OpenBLASController.clear_controlling_thread(force=True)
                _BLAS_LIMITER = None


# --------------------------------------------------------------------------------------------
# Bayesian optimisation
# --------------------------------------------------------------------------------------------


def _is_refit_point(n: int, cfg: BOConfig) -> bool:
    return n >= cfg.n_initial and (n - cfg.n_initial) % cfg.refit_every == 0


class _Surrogate:
    """GP state as a pure function of (evaluations so far, stored hyper-parameter history)."""

    def __init__(self, cfg: BOConfig, seed: int, history: dict[int, list[float]]):
        self.cfg = cfg
        self.seed = seed
        self.history = {int(k): np.asarray(v, dtype=np.float64) for k, v in history.items()}
        self.gp: gpmod.MaternGP | None = None

    def _theta_at(self, n: int, U: np.ndarray, y: np.ndarray) -> np.ndarray:
        if n not in self.history:
            prev = [k for k in self.history if k < n]
            warm = self.history[max(prev)] if prev else None
            first = not prev
            rng = np.random.default_rng([self.seed, 0xF17, n])
            self.history[n] = gpmod.fit_hyperparameters(
                U[:n],
                y[:n],
                warm,
                noise_variance=self.cfg.noise_variance,
                n_restarts=self.cfg.first_fit_restarts if first else 0,
                rng=rng,
                maxiter=200 if first else 60,
            )
        return self.history[n]

    def model_for(self, n: int, U: np.ndarray, y: np.ndarray) -> gpmod.MaternGP:
        """The GP on the first ``n`` points, built exactly as an uninterrupted run builds it."""
        if _is_refit_point(n, self.cfg):
            self.gp = gpmod.MaternGP(U[:n], y[:n], self._theta_at(n, U, y))
        elif self.gp is None or self.gp.n != n - 1:
            n_r = max(k for k in self.history if k <= n)
            self.gp = gpmod.MaternGP(U[:n_r], y[:n_r], self.history[n_r])
            for j in range(n_r, n):
                self.gp.append(U[j], y[j])
        else:
            self.gp.append(U[n - 1], y[n - 1])
        return self.gp

    def final_model(self, U: np.ndarray, y: np.ndarray) -> gpmod.MaternGP:
        n = U.shape[0]
        self.gp = gpmod.MaternGP(U, y, self._theta_at(n, U, y))
        return self.gp


def _propose(model: gpmod.MaternGP, cfg: BOConfig, rng: np.random.Generator) -> np.ndarray:
    """Maximise log EI over the unit cube: Sobol + local candidates, L-BFGS-B polish. (d,)"""
    d = model.d
    mu_obs = model.mean_at_observed()
    best_s = model.standardise_value(float(mu_obs.min()))
    m = 1 << max(0, int(math.ceil(math.log2(cfg.candidates))))
    cands = [qmc.Sobol(d, scramble=True, seed=rng).random(m)]
    if cfg.local_candidates:
        top = model.X[np.argsort(mu_obs)[: min(5, model.n)]]
        centres = top[rng.integers(0, top.shape[0], cfg.local_candidates)]
        local = centres + cfg.local_scale * rng.standard_normal((cfg.local_candidates, d))
        cands.append(np.clip(local, 0.0, 1.0))
    C = np.vstack(cands)
    lei = model.log_ei(C, best_s, cfg.xi)
    order = np.argsort(-lei)
    best_x, best_v = C[order[0]].copy(), float(lei[order[0]])
    box = [(0.0, 1.0)] * d
    for j in order[: cfg.n_polish]:
        res = minimize(
            lambda u: tuple(-v for v in model.log_ei_and_grad(u, best_s, cfg.xi)),
            C[j],
            jac=True,
            method="L-BFGS-B",
            bounds=box,
            options={"maxiter": cfg.polish_maxiter},
        )
        if np.isfinite(res.fun) and -float(res.fun) > best_v:
            best_x, best_v = np.clip(np.asarray(res.x, dtype=np.float64), 0.0, 1.0), -float(res.fun)
    return best_x


def first_simplex(u0: np.ndarray, step: float, turn_above: float = 0.5) -> np.ndarray:
    """Nelder-Mead's first simplex in the unit cube, (d + 1, d): ``u0`` and ``u0`` moved by
    ``step`` along each axis, backwards where that coordinate is above ``turn_above`` (so the
    vertices stay inside the cube)."""
    u0 = np.asarray(u0, dtype=np.float64)
    return np.vstack([u0, u0 + np.diag(np.where(u0 < turn_above, step, -step))])


def _local_search(
    ev: _Evaluations,
    cfg: BOConfig,
    lo: np.ndarray,
    width: np.ndarray,
    save: Callable[[SeedResult], None],
    snapshot: Callable[..., SeedResult],
) -> None:
    """``cfg.local_evals`` Nelder-Mead evaluations from the lowest observed point (its value is
    reused, not re-evaluated). Deterministic in the values it is given, so a resumed run replays
    the stored evaluations through ``ev`` and continues where it stopped."""
    X, y = ev.arrays()
    k = int(np.argmin(y))
    u0, y0 = np.clip((X[k] - lo) / width, 0.0, 1.0), float(y[k])
    d = u0.size

    class _Spent(Exception):
        """The budget is used up (SciPy checks its maxfev only between iterations)."""

    def f(u: np.ndarray) -> float:
        u = np.clip(u, 0.0, 1.0)
        if np.array_equal(u, u0):
            return y0
        if ev.n >= cfg.n_evals:
            raise _Spent
        value = ev(lo + width * u)
        if ev.new_since_checkpoint >= cfg.checkpoint_every:
            save(snapshot(False))
        return value

    simplex = first_simplex(u0, cfg.local_step)
    with contextlib.suppress(_Spent):
        minimize(
            f,
            u0,
            method="Nelder-Mead",
            # SciPy's own caps (200 d by default) must not end the search before the budget
            options={
                "initial_simplex": simplex,
                "xatol": 1e-3,
                "fatol": 0.0,
                "maxiter": cfg.local_evals + d + 1,
                "maxfev": cfg.local_evals + d + 1,
            },
        )


def run_seed(
    objective: Objective,
    bounds: Any,
    config: BOConfig | None = None,
    seed: int = 0,
    checkpoint: str | os.PathLike | None = None,
    callback: Callback | None = None,
    run_id: str | None = None,
) -> SeedResult:
    """One seed of Bayesian optimisation (Matérn-5/2 ARD GP, log expected improvement).

    ``objective(x (d,), eval_index) -> float``; ``bounds`` (d, 2). The first
    ``config.n_initial`` points are ``low + (high - low) * default_rng(seed).random((n_initial,
    d))``; each later point maximises EI on a GP fitted to all previous evaluations (inputs
    scaled to the unit cube, hyper-parameters refitted every ``refit_every`` evaluations), with
    the randomness of step n drawn from ``default_rng([seed, n])``. Pure and resumable: with
    ``checkpoint`` set, progress is written there atomically every ``checkpoint_every`` new
    evaluations and on any exit; calling again with the same arguments continues from it and
    returns exactly what an uninterrupted run returns (X, y, best points), timings aside. A
    finished checkpoint is returned as-is. ``callback(eval_index, x, y)`` after each new
    evaluation. ``run_id``: the objective's identity (the fit's ``seed_identity``), kept in the
    result's config, so that a checkpoint of another objective is refused.
    """
    cfg = (config or BOConfig()).validate()
    b = check_bounds(bounds)
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer) or seed < 0:
        raise ConfigError(f"seed={seed!r}: must be an integer >= 0")
    seed = int(seed)
    cfg_d = with_run_id(cfg.result_fields(), run_id)
    prev = load_checkpoint(checkpoint, "bo", seed, b, cfg_d)
    if prev is not None and prev.complete:
        return prev
    d = b.shape[0]
    lo, width = b[:, 0], b[:, 1] - b[:, 0]
    ev = _Evaluations(objective, b, callback, prev)
    n_model = cfg.n_evals - cfg.local_evals  # evaluations proposed by the design and the GP
    ev.restore_all(n_model)
    surrogate = _Surrogate(cfg, seed, (prev.state.get("theta_history", {}) if prev else {}))

    def snapshot(complete: bool, **extra: Any) -> SeedResult:
        state = (
            {}
            if complete
            else {"theta_history": {str(k): v.tolist() for k, v in surrogate.history.items()}}
        )
        return ev.result("bo", seed, cfg_d, complete=complete, state=state, **extra)

    def save(res: SeedResult) -> None:
        if checkpoint is not None:
            res.save(checkpoint)
        ev.new_since_checkpoint = 0

    finished = False
    try:
        with _blas_threads(cfg.blas_threads):
            initial = lo + width * np.random.default_rng(seed).random((cfg.n_initial, d))
            for i in range(ev.n, cfg.n_initial):
                ev(initial[i])
                if ev.new_since_checkpoint >= cfg.checkpoint_every:
                    save(snapshot(False))
            while ev.n < n_model:
                n = ev.n
                X, y = ev.arrays()
                U = (X - lo) / width
                model = surrogate.model_for(n, U, cfg.model_values(y))
                u = _propose(model, cfg, np.random.default_rng([seed, n]))
                ev(lo + width * u)
                if ev.new_since_checkpoint >= cfg.checkpoint_every:
                    save(snapshot(False))
            if cfg.local_evals:
                _local_search(ev, cfg, lo, width, save, snapshot)
            X, y = ev.arrays()
            U = (X - lo) / width
            model = surrogate.final_model(U, cfg.model_values(y))
            mu = model.mean_at_observed()
            k = int(np.argmin(mu))
            theta = model.theta
            hyper = {
                "lengthscales_unit_cube": np.exp(theta[:d]).tolist(),
                "signal_variance": float(math.exp(theta[d])) * model.y_std**2,
                "noise_variance": float(math.exp(theta[d + 1])) * model.y_std**2,
                "noise_std": float(math.sqrt(math.exp(theta[d + 1]))) * model.y_std,
                "n_refits": len(surrogate.history),
                "output_transform": cfg.output_transform,
            }
            result = snapshot(
                True,
                best_x_posterior=X[k].copy(),
                best_mean_posterior=cfg.objective_value(float(mu[k])),
                hyperparameters=hyper,
            )
            finished = True
            save(result)
            return result
    finally:
        if not finished and checkpoint is not None and ev.n > 0:
            save(snapshot(False))
