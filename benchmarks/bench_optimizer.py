"""Optimiser benchmark: our GP-BO vs scikit-optimize gp_minimize vs the paper's baselines.

    .venv/bin/python -m benchmarks.bench_optimizer [--quick] [--seeds 5] [--first-seed 0]
        [--n 500] [--n-initial 200] [--noise-sd 0.1] [--skopt-seeds 1] [--skopt-n 500]
        [--methods bo,bo-iid,skopt,random,trust-region] [--json out.json] [--progress skopt.log]
        [--load earlier.json ...]

scikit-optimize costs ~20-25 CPU-minutes per seed at n = 500 (more wall time on a loaded
machine), so the default runs one skopt seed; ``--skopt-n 300`` with ``--progress`` gives its
per-iteration CPU curve, from which n = 500 is extrapolated (cost ~ n^1.7 per iteration here).
``--load a.json b.json --methods ""`` prints one table from earlier ``--json`` runs.

Objective: Hartmann-6 restricted to 5-D (x6 fixed at its optimum coordinate 0.6573, so the
minimum is still -3.32237 at (0.20169, 0.15001, 0.47687, 0.27533, 0.31165)) on [0, 1]^5, plus
a noise term that mimics the crop model's random leaf angles: for a random draw w the loss is
``f(x) + e_w(x)`` with ``e_w`` a random smooth field (64 random Fourier features, length-scale
0.15, standard deviation ``--noise-sd`` = 0.1 at every x). ``bo`` uses common random numbers
(one draw per seed: ``evaluation_rng(seed, i, common=True)``); every other method (``bo-iid``,
``skopt``, ``random``, ``trust-region``) gets an independent draw per evaluation, which is what
a model that resamples leaf angles at each call gives. Quality is the *noise-free* f at the
reported point (BO, skopt: the observed point with the lowest GP posterior mean; random,
trust-region: the lowest observation) and at the mean of the seeds' points (the paper's answer).

Optimiser seconds exclude the objective (the objective here costs microseconds; the real one
~100 ms); CPU seconds are the process CPU time (robust on a shared, loaded machine), wall
seconds what a user waits. "s/it @ n" is the mean optimiser CPU time of the 10 iterations
before evaluation n.
BLAS is limited to one thread (seeds run one per process in production).
"""

from __future__ import annotations

import os

for _v in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
import warnings  # noqa: E402

import numpy as np  # noqa: E402

from benchmarks.options import (  # noqa: E402
    at_least,
    json_file,
    non_negative,
    output_file,
    write_json,
)
from cropcraft_core.optimize import BOConfig, SeedResult, aggregate, evaluation_rng, run_seed  # noqa: E402
from cropcraft_core.optimize.baselines import run_random, run_trust_region  # noqa: E402

#: The methods compared (``--methods``).
METHODS = ("bo", "bo-iid", "skopt", "random", "trust-region")
OPTIMUM = -3.32237
X6 = 0.6573
_A = np.array(
    [
        [10, 3, 17, 3.5, 1.7, 8],
        [0.05, 10, 17, 0.1, 8, 14],
        [3, 3.5, 1.7, 10, 17, 8],
        [17, 8, 0.05, 10, 0.1, 14],
    ]
)
_P = 1e-4 * np.array(
    [
        [1312, 1696, 5569, 124, 8283, 5886],
        [2329, 4135, 8307, 3736, 1004, 9991],
        [2348, 1451, 3522, 2883, 3047, 6650],
        [4047, 8828, 8732, 5743, 1091, 381],
    ]
)
_ALPHA = np.array([1.0, 1.2, 3.0, 3.2])
BOUNDS = np.array([[0.0, 1.0]] * 5)


def hartmann5(x: np.ndarray) -> np.ndarray:
    """Noise-free Hartmann-6 with x6 = 0.6573: (m, 5) -> (m,) (or (5,) -> scalar)."""
    x = np.asarray(x, dtype=np.float64)
    X = np.atleast_2d(x)
    X6_ = np.hstack([X, np.full((X.shape[0], 1), X6)])
    inner = ((X6_[:, None, :] - _P[None]) ** 2 * _A[None]).sum(-1)
    out = -(np.exp(-inner) @ _ALPHA)
    return out if x.ndim == 2 else float(out[0])


class NoisyHartmann:
    """``objective(x, eval_index)`` = hartmann5(x) + a random smooth field drawn from
    ``evaluation_rng(seed, eval_index, common=common)``: (5,) -> float."""

    def __init__(
        self, seed: int, common: bool, noise_sd: float = 0.1, lengthscale: float = 0.15, k: int = 64
    ):
        self.seed, self.common, self.noise_sd, self.lengthscale, self.k = (
            seed,
            common,
            noise_sd,
            lengthscale,
            k,
        )
        self._field = None

    def _draw(self, eval_index: int):
        rng = evaluation_rng(self.seed, eval_index, common=self.common)
        W = rng.standard_normal((self.k, 5)) / self.lengthscale
        b = rng.uniform(0, 2 * math.pi, self.k)
        return W, b

    def __call__(self, x: np.ndarray, eval_index: int) -> float:
        if self.common:
            if self._field is None:
                self._field = self._draw(0)
            W, b = self._field
        else:
            W, b = self._draw(eval_index)
        noise = self.noise_sd * math.sqrt(2.0 / self.k) * float(np.cos(W @ x + b).sum())
        return hartmann5(x) + noise


def run_method(
    method: str,
    seed: int,
    n: int,
    n_init: int,
    skopt_n: int,
    progress: str | None = None,
    noise_sd: float = 0.1,
) -> SeedResult:
    if method == "bo":
        return run_seed(
            NoisyHartmann(seed, True, noise_sd), BOUNDS, BOConfig(n_evals=n, n_initial=n_init), seed
        )
    if method == "bo-iid":
        return run_seed(
            NoisyHartmann(seed, False, noise_sd),
            BOUNDS,
            BOConfig(n_evals=n, n_initial=n_init),
            seed,
        )
    if method == "skopt":
        from cropcraft_core.optimize.skopt_reference import run_skopt

        log = open(progress, "a") if progress else None  # noqa: SIM115

        def cb(i: int, x: np.ndarray, y: float) -> None:
            if log is not None:  # per-evaluation CPU/wall clock, readable while it runs
                log.write(f"{seed} {i} {time.process_time():.3f} {time.perf_counter():.3f}\n")
                log.flush()

        return run_skopt(
            NoisyHartmann(seed, False, noise_sd),
            BOUNDS,
            seed=seed,
            n_evals=skopt_n,
            n_initial=min(n_init, skopt_n),
            callback=cb,
        )
    if method == "random":
        return run_random(NoisyHartmann(seed, False, noise_sd), BOUNDS, n_evals=n, seed=seed)
    if method == "trust-region":  # at the others' budget, as the fit runs it (fit_seed)
        return run_trust_region(
            NoisyHartmann(seed, False, noise_sd), BOUNDS, seed=seed, n_starts=1, maxiter=n,
            max_evals=n,
        )  # fmt: skip
    raise SystemExit(f"unknown method {method!r}")


def per_iter(r: SeedResult, n: int) -> float:
    t = r.cpu_per_eval if r.cpu_per_eval is not None else r.seconds_per_eval
    if t.shape[0] < n:
        return float("nan")
    return float(np.mean(t[max(0, n - 10) : n]))


def summarise(method: str, results: list[SeedResult], checkpoints: tuple[int, ...]) -> dict:
    rep = np.array([hartmann5(r.reported_x) for r in results])
    obs = np.array([hartmann5(r.best_x) for r in results])
    agg = aggregate(results)
    return {
        "method": method,
        "seeds": [r.seed for r in results],
        "n_evals": int(np.mean([r.n_evals for r in results])),
        "opt_s": float(np.mean([r.seconds_optimizer for r in results])),
        "opt_cpu": float(np.mean([r.cpu_seconds_optimizer for r in results])),
        "per_iter": {n: float(np.nanmean([per_iter(r, n) for r in results])) for n in checkpoints},
        "true_reported_mean": float(rep.mean()),
        "true_reported_sd": float(rep.std(ddof=1)) if rep.size > 1 else 0.0,
        "true_observed_mean": float(obs.mean()),
        "true_at_seed_mean": float(hartmann5(agg.mean_x)),
        "spread_x": float(np.linalg.norm(agg.std_x)),
    }


def print_table(rows: list[dict], checkpoints: tuple[int, ...]) -> None:
    head = (
        f"{'method':<14}{'noise':>6}{'seeds':>6}{'n':>7}{'opt CPU s':>11}{'opt wall s':>12}"
        + "".join(f"{'s/it@' + str(n):>10}" for n in checkpoints)
        + f"{'true f @ reported':>22}{'f @ lowest obs':>16}{'f @ seed-mean x':>17}{'|sd x|':>8}"
    )
    print(head)
    print("-" * len(head))
    for r in rows:
        pi = "".join(
            f"{(r['per_iter'].get(n) or r['per_iter'].get(str(n)) or float('nan')):>10.3f}"
            for n in checkpoints
        )
        print(
            f"{r['method']:<14}{r.get('noise_sd', 0.1):>6.2f}{len(r['seeds']):>6}{r['n_evals']:>7}"
            f"{r.get('opt_cpu', float('nan')):>11.1f}{r['opt_s']:>12.1f}{pi}"
            f"{r['true_reported_mean']:>13.3f} ± {r['true_reported_sd']:<6.3f}"
            f"{r['true_observed_mean']:>16.3f}{r['true_at_seed_mean']:>17.3f}{r['spread_x']:>8.3f}"
        )
    print(f"(optimum {OPTIMUM})")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="cropcraft bench optimizer", description=__doc__.split("\n")[0]
    )
    p.add_argument(
        "--quick",
        action="store_true",
        help="defaults n=120/40 initial, 2 seeds, skopt n=120 (flags given still win)",
    )
    p.add_argument("--seeds", type=at_least(1), help="seeds per method (5)")
    p.add_argument("--first-seed", type=at_least(0), default=0)
    p.add_argument("--n", type=at_least(2), help="evaluations per seed (ours, baselines; 500)")
    p.add_argument("--n-initial", type=at_least(2), help="random initial evaluations (200)")
    p.add_argument("--noise-sd", type=non_negative, default=0.1)
    p.add_argument("--skopt-seeds", type=at_least(0), help="skopt's seeds (1)")
    p.add_argument("--skopt-n", type=at_least(2), help="skopt's evaluations (500)")
    p.add_argument("--methods", default=",".join(METHODS))
    p.add_argument("--json", type=output_file, help="write the summaries (and seed results) here")
    p.add_argument("--progress", help="skopt: append 'seed eval cpu wall' lines here as it runs")
    p.add_argument(
        "--load",
        nargs="*",
        type=json_file,
        default=[],
        help="add summaries from earlier --json runs",
    )
    a = p.parse_args(argv)
    base = (120, 40, 2, 120, 1) if a.quick else (500, 200, 5, 500, 1)
    given = (a.n, a.n_initial, a.seeds, a.skopt_n, a.skopt_seeds)
    n, n_init, seeds, skopt_n, skopt_seeds = (
        d if v is None else v for v, d in zip(given, base, strict=True)
    )
    if n_init > n:
        p.error(f"--n-initial {n_init} exceeds --n {n}")
    methods = [m for m in a.methods.split(",") if m]
    bad = [m for m in methods if m not in METHODS]
    if bad:
        p.error(f"unknown method(s) {', '.join(bad)}: choose from {', '.join(METHODS)}")
    if skopt_seeds == 0:  # none of skopt's: it ran the others, then failed with no table
        methods = [m for m in methods if m != "skopt"]
    if not methods and not a.load:
        p.error("no method to run (--methods, --skopt-seeds 0) and no --load")
    checkpoints = (250, 300, 400, 500) if not a.quick else (60, 100, 120)
    warnings.filterwarnings("ignore")
    rows: list[dict] = []
    for path in a.load:
        loaded = json.loads(open(path).read())
        if not isinstance(loaded, dict) or not isinstance(loaded.get("rows"), list):
            p.error(f"--load {path}: not a bench optimizer --json file (no rows)")
        rows.extend(loaded["rows"])
    dump: dict = {"rows": [], "results": {}}
    for method in methods:
        k = skopt_seeds if method == "skopt" else seeds
        results = []
        for s in range(a.first_seed, a.first_seed + k):
            t = time.perf_counter()
            r = run_method(method, s, n, n_init, skopt_n, a.progress, a.noise_sd)
            print(
                f"  {method} seed {s}: {time.perf_counter() - t:.1f} s wall, optimiser "
                f"{r.seconds_optimizer:.1f} s wall / {r.cpu_seconds_optimizer:.1f} s CPU, "
                f"true f {hartmann5(r.reported_x):.4f}",
                file=sys.stderr,
                flush=True,
            )
            results.append(r)
        row = summarise(method, results, checkpoints)
        row["noise_sd"] = a.noise_sd
        rows.append(row)
        dump["rows"].append(row)
        dump["results"][method] = [r.to_dict() for r in results]
        if a.json:  # after each method: a long run's finished methods are kept
            write_json(a.json, dump)
    print_table(rows, checkpoints)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
