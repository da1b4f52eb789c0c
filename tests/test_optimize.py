"""Bayesian optimisation, baselines, checkpoint/resume and validation (cropcraft_core.optimize)."""

from __future__ import annotations

import math
import os

import numpy as np
import pytest
from scipy.linalg import cho_solve

from cropcraft_core.config.params import bounds as crop_bounds
from cropcraft_core.errors import ConfigError, InputError
from cropcraft_core.optimize import (
    METHODS,
    BOConfig,
    SeedResult,
    aggregate,
    check_bounds,
    check_in_bounds,
    evaluation_rng,
    run_method,
    run_seed,
)
from cropcraft_core.optimize.baselines import run_random, run_trust_region
from cropcraft_core.optimize.gp import MaternGP, fit_hyperparameters

FAST = {"candidates": 512, "local_candidates": 256, "n_polish": 3}


def quadratic(centre: np.ndarray, scale: np.ndarray):
    """Noise-free bowl with minimum 0 at ``centre``; objective(x, i) signature."""

    def f(x: np.ndarray, eval_index: int) -> float:
        return float((((x - centre) / scale) ** 2).sum())

    return f


class Noisy:
    """Quadratic + independent noise from evaluation_rng(seed, i, common=False)."""

    def __init__(self, seed: int, raise_at: int | None = None):
        self.seed, self.raise_at, self.calls = seed, raise_at, []

    def __call__(self, x: np.ndarray, eval_index: int) -> float:
        if eval_index == self.raise_at:
            raise KeyboardInterrupt(f"simulated kill at {eval_index}")
        self.calls.append(eval_index)
        rng = evaluation_rng(self.seed, eval_index, common=False)
        return float(((x - 0.3) ** 2).sum() + 0.01 * rng.standard_normal())


@pytest.mark.parametrize("d,n,n0,tol", [(2, 30, 10, 0.05), (5, 60, 20, 0.15)])
def test_bo_finds_quadratic_minimum(d, n, n0, tol):
    rng = np.random.default_rng(d)
    b = np.column_stack([-rng.uniform(1, 3, d), rng.uniform(1, 3, d)])
    centre = b[:, 0] + (b[:, 1] - b[:, 0]) * rng.uniform(0.2, 0.8, d)
    scale = b[:, 1] - b[:, 0]
    r = run_seed(quadratic(centre, scale), b, BOConfig(n_evals=n, n_initial=n0, **FAST), seed=1)
    assert r.X.shape == (n, d) and r.y.shape == (n,)
    assert r.complete and r.best_y == r.y.min()
    assert np.all(r.X >= b[:, 0]) and np.all(r.X <= b[:, 1])
    err = np.abs(r.reported_x - centre) / scale
    assert err.max() < tol, (err, r.best_y)
    # BO beats its own random initial design by a wide margin.
    assert r.best_y < 0.1 * r.y[:n0].min()
    assert r.seconds_optimizer > 0 and r.seconds_per_eval.shape == (n,)


def test_seed_is_deterministic_and_initial_design_from_default_rng():
    b = np.array([[0.0, 2.0], [-1.0, 1.0]])
    cfg = BOConfig(n_evals=16, n_initial=8, **FAST)
    r1 = run_seed(Noisy(3), b, cfg, seed=3)
    r2 = run_seed(Noisy(3), b, cfg, seed=3)
    np.testing.assert_array_equal(r1.X, r2.X)
    np.testing.assert_array_equal(r1.y, r2.y)
    expected = b[:, 0] + (b[:, 1] - b[:, 0]) * np.random.default_rng(3).random((8, 2))
    np.testing.assert_array_equal(r1.X[:8], expected)
    r3 = run_seed(Noisy(3), b, cfg, seed=4)
    assert not np.array_equal(r1.X, r3.X)


def test_concurrent_seeds_in_threads_match_sequential_seeds():
    """Seeds on threads of one process (Prefect's thread pool) give the sequential results even
    when BLAS has more threads: the 1-thread limit holds until the last seed is done (OpenBLAS
    with 2 threads rounds differently, and a BO trajectory amplifies the last bit)."""
    import threading

    from threadpoolctl import threadpool_limits

    def wavy(x: np.ndarray, eval_index: int) -> float:
        return float(np.sin(3 * x).sum() + 0.01 * (x**2).sum())

    b = np.array([[0.0, 2.0]] * 5)
    short, long = BOConfig(n_evals=12, n_initial=10), BOConfig(n_evals=40, n_initial=10)
    with threadpool_limits(limits=2):
        alone = run_seed(wavy, b, long, seed=0)
        out: dict[str, object] = {}
        go = threading.Barrier(2)

        def run(name, cfg, seed):
            go.wait()
            out[name] = run_seed(wavy, b, cfg, seed=seed)

        ts = [
            threading.Thread(target=run, args=("short", short, 1)),
            threading.Thread(target=run, args=("long", long, 0)),
        ]
        for t in ts:
            t.start()
        for t in ts:
            t.join()
    np.testing.assert_array_equal(out["long"].X, alone.X)


@pytest.mark.parametrize("kill_at", [5, 23, 30])
def test_resume_after_interrupt_equals_uninterrupted(tmp_path, kill_at):
    b = np.array([[0.0, 1.0], [0.0, 2.0], [-1.0, 1.0]])
    cfg = BOConfig(n_evals=36, n_initial=12, refit_every=4, checkpoint_every=3, **FAST)
    full = run_seed(Noisy(7), b, cfg, seed=7)

    ck = tmp_path / "seed7.json"
    snapshots: list[bytes] = []

    def grab(i, x, y):  # what a hard kill (no clean exit) would leave: the last periodic save
        if ck.exists():
            snapshots.append(ck.read_bytes())

    with pytest.raises(KeyboardInterrupt):
        run_seed(Noisy(7, raise_at=kill_at), b, cfg, seed=7, checkpoint=ck, callback=grab)
    partial = SeedResult.load(ck)
    assert not partial.complete and partial.n_evals == kill_at  # saved on exit
    np.testing.assert_array_equal(partial.X, full.X[:kill_at])

    resumed_obj = Noisy(7)
    resumed = run_seed(resumed_obj, b, cfg, seed=7, checkpoint=ck)
    assert resumed_obj.calls == list(range(kill_at, 36))  # stored evaluations are not redone
    for r in (resumed, SeedResult.load(ck)):
        assert r.complete
        np.testing.assert_array_equal(r.X, full.X)
        np.testing.assert_array_equal(r.y, full.y)
        np.testing.assert_array_equal(r.best_x, full.best_x)
        np.testing.assert_array_equal(r.best_x_posterior, full.best_x_posterior)
        assert r.best_y == full.best_y and r.best_mean_posterior == full.best_mean_posterior

    # Hard kill: only an earlier periodic checkpoint survives.
    assert snapshots
    ck2 = tmp_path / "hard.json"
    ck2.write_bytes(snapshots[0])
    assert SeedResult.load(ck2).n_evals < kill_at
    again = run_seed(Noisy(7), b, cfg, seed=7, checkpoint=ck2)
    np.testing.assert_array_equal(again.X, full.X)
    np.testing.assert_array_equal(again.y, full.y)

    # A finished checkpoint is returned without calling the objective.
    def boom(x, i):
        raise AssertionError("objective called for a finished run")

    done = run_seed(boom, b, cfg, seed=7, checkpoint=ck)
    np.testing.assert_array_equal(done.X, full.X)


def test_checkpoint_of_another_run_is_refused(tmp_path):
    b = np.array([[0.0, 1.0], [0.0, 1.0]])
    ck = tmp_path / "c.json"
    run_seed(Noisy(1), b, BOConfig(n_evals=10, n_initial=5, **FAST), seed=1, checkpoint=ck)
    # the refusal says what differs, so that a user extending a run knows which setting it was
    with pytest.raises(ConfigError, match=r"another run \(n_evals 10, now 12\)"):
        run_seed(Noisy(1), b, BOConfig(n_evals=12, n_initial=5, **FAST), seed=1, checkpoint=ck)
    with pytest.raises(ConfigError, match=r"another run \(seed 1, now 2\)"):
        run_seed(Noisy(2), b, BOConfig(n_evals=10, n_initial=5, **FAST), seed=2, checkpoint=ck)
    cfg = BOConfig(n_evals=10, n_initial=5, **FAST)
    with pytest.raises(ConfigError, match=r"the objective \(observation or fit settings\)"):
        run_seed(Noisy(1), b, cfg, seed=1, checkpoint=ck, run_id="another observation")


def test_numpy_integer_budgets_are_stored_as_numbers(tmp_path):
    """A budget from a numpy sweep passes validation, so the stored config must take it too."""
    b = np.array([[0.0, 1.0], [0.0, 1.0]])
    n = np.arange(6, 30, 6)[1]
    r = run_seed(Noisy(1), b, BOConfig(n_evals=n, n_initial=np.int64(5), **FAST), seed=1)
    for name in ("r.json", "r.npz"):
        assert SeedResult.load(r.save(tmp_path / name)).config["n_evals"] == 12


def test_a_damaged_checkpoint_is_named_not_resumed(tmp_path):
    """A checkpoint that parses but holds NaN losses, points outside the box, another format
    version, or a finished run short of its budget is refused naming the file; a truncated
    .npz (the stored seed results) too, not a raw BadZipFile."""
    import json

    b = np.array([[0.0, 1.0], [0.0, 1.0]])
    cfg = BOConfig(n_evals=10, n_initial=5, **FAST)
    ck = tmp_path / "c.json"
    run_seed(Noisy(1), b, cfg, seed=1, checkpoint=ck)
    good = json.loads(ck.read_text())
    for change, match in (
        ({"y": [float("nan")] + good["y"][1:]}, "is damaged"),
        ({"X": [[5.0, 0.5]] + good["X"][1:]}, "is damaged"),
        ({"X": good["X"][:7], "y": good["y"][:7]}, "is damaged"),  # "complete" yet short
        ({"version": 99}, "cannot read seed result .*c.json: a SeedResult of format 99"),
    ):
        ck.write_text(json.dumps({**good, **change}))
        with pytest.raises(InputError, match=match):
            run_seed(Noisy(1), b, cfg, seed=1, checkpoint=ck)
    npz = SeedResult.from_dict(good).save(tmp_path / "r.npz")
    npz.write_bytes(npz.read_bytes()[: npz.stat().st_size // 2])
    with pytest.raises(InputError, match="cannot read seed result .*r.npz"):
        SeedResult.load(npz)


def test_result_serialisation_round_trip(tmp_path):
    b = crop_bounds("maize")
    centre = b.mean(1)
    r = run_seed(
        quadratic(centre, b[:, 1] - b[:, 0]), b, BOConfig(n_evals=14, n_initial=10, **FAST)
    )
    for name in ("r.json", "r.npz"):
        back = SeedResult.load(r.save(tmp_path / name))
        np.testing.assert_array_equal(back.X, r.X)
        np.testing.assert_array_equal(back.y, r.y)
        np.testing.assert_array_equal(back.best_x_posterior, r.best_x_posterior)
        assert back.config == r.config and back.hyperparameters == r.hyperparameters
    assert sorted(q.name for q in tmp_path.iterdir()) == ["r.json", "r.npz"]  # no temporaries
    umask = os.umask(0)
    os.umask(umask)
    assert {q.stat().st_mode & 0o777 for q in tmp_path.iterdir()} == {0o666 & ~umask}


def test_aggregate_mean_and_spread():
    b = np.array([[0.0, 1.0], [0.0, 1.0]])
    cfg = BOConfig(n_evals=12, n_initial=8, **FAST)
    rs = [run_seed(Noisy(s), b, cfg, seed=s) for s in range(3)]
    mean_x, std_x, per_seed = aggregate(rs)
    P = np.vstack([r.best_x_posterior for r in rs])
    np.testing.assert_allclose(per_seed, P)
    np.testing.assert_allclose(mean_x, P.mean(0))
    np.testing.assert_allclose(std_x, P.std(0, ddof=1))
    np.testing.assert_allclose(aggregate(rs, use="observed").per_seed, [r.best_x for r in rs])
    with pytest.raises(ConfigError):
        aggregate([])
    other = run_seed(Noisy(9), np.array([[0.0, 1.0]] * 3), cfg, seed=9)
    with pytest.raises(ConfigError, match="seed 9 has 3 parameters, seed 0 2"):
        aggregate([*rs, other])


@pytest.mark.parametrize("crop", ["soybean", "maize"])
def test_random_baseline_end_to_end(crop, tmp_path):
    b = crop_bounds(crop)
    r = run_random(quadratic(b.mean(1), b[:, 1] - b[:, 0]), b, n_evals=500, seed=2)
    assert r.method == "random" and r.X.shape == (500, b.shape[0])
    assert np.all(r.X >= b[:, 0]) and np.all(r.X <= b[:, 1])
    assert r.best_y == r.y.min() and r.best_x_posterior is None
    np.testing.assert_array_equal(r.reported_x, r.best_x)
    # Resumable like BO.
    ck = tmp_path / "rand.json"
    obj = Noisy(2, raise_at=123)
    with pytest.raises(KeyboardInterrupt):
        run_random(obj, b, n_evals=200, seed=2, checkpoint=ck)
    again = Noisy(2)
    resumed = run_random(again, b, n_evals=200, seed=2, checkpoint=ck)
    assert again.calls == list(range(123, 200))  # evaluations 0-122 came from the checkpoint
    full = run_random(Noisy(2), b, n_evals=200, seed=2)
    np.testing.assert_array_equal(resumed.y, full.y)


def test_trust_region_baseline_end_to_end(tmp_path):
    b = crop_bounds("soybean")
    centre = b[:, 0] + 0.3 * (b[:, 1] - b[:, 0])
    f = quadratic(centre, b[:, 1] - b[:, 0])
    r = run_trust_region(f, b, seed=0, n_starts=10, maxiter=500)
    assert r.method == "trust-region" and r.n_evals > 10
    assert np.all(r.X >= b[:, 0]) and np.all(r.X <= b[:, 1])
    assert r.best_y < 1e-6 and r.best_y == r.y.min()
    # Interrupted and resumed (deterministic replay) = uninterrupted, on a noisy objective.
    noisy = lambda x, i: Noisy(0)(x, i)  # noqa: E731
    full = run_trust_region(noisy, b, seed=0, n_starts=3, maxiter=30)
    ck = tmp_path / "tr.json"

    def killer(x, i):
        if i == full.n_evals // 2:
            raise KeyboardInterrupt
        return noisy(x, i)

    with pytest.raises(KeyboardInterrupt):
        run_trust_region(killer, b, seed=0, n_starts=3, maxiter=30, checkpoint=ck)
    called = []

    def counting(x, i):
        called.append(i)
        return noisy(x, i)

    resumed = run_trust_region(counting, b, seed=0, n_starts=3, maxiter=30, checkpoint=ck)
    # the stored evaluations are replayed, not recomputed: the objective sees only the rest
    assert called == list(range(full.n_evals // 2, full.n_evals))
    np.testing.assert_array_equal(resumed.X, full.X)
    np.testing.assert_array_equal(resumed.y, full.y)
    capped = run_trust_region(noisy, b, seed=0, max_evals=40)
    assert capped.n_evals == 40


@pytest.mark.parametrize(
    "bad",
    [
        [[0.0, 1.0], [2.0, 1.0]],  # low > high
        [[0.0, 0.0]],  # empty side
        [[0.0, 1.0, 2.0]],  # wrong shape
        [[0.0, math.nan]],
        [[-1e308, 1e308]],  # finite ends, a width that overflows
        [0.0, 1.0],
        "box",
    ],
)
def test_bad_bounds_raise_config_error(bad):
    with pytest.raises(ConfigError):
        check_bounds(bad)
    with pytest.raises(ConfigError):
        run_seed(quadratic(np.zeros(1), np.ones(1)), bad, BOConfig(n_evals=4, n_initial=2))


@pytest.mark.parametrize(
    "kw",
    [
        {"n_initial": 600},
        {"n_initial": 1, "n_evals": 10},
        {"refit_every": 0},
        {"candidates": 0},
        {"xi": -1.0},
        {"n_evals": 2.5},
        {"noise_variance": -1.0},
        {"blas_threads": 0},
        {"output_transform": "sqrt"},
        {"output_transform": "log", "log_offset": 0.0},
        # a misparsed setting (YAML's yes, a flag): True is not the number 1
        {"noise_variance": True},
        {"xi": True},
        {"blas_threads": True},
        {"local_scale": 1e300},
    ],
)
def test_bad_config_raises_config_error(kw):
    with pytest.raises(ConfigError):
        run_seed(quadratic(np.zeros(2), np.ones(2)), [[0, 1], [0, 1]], BOConfig(**kw))


def test_box_violations_raise_config_error():
    b = crop_bounds("soybean")
    check_in_bounds(b.mean(1), b)
    x = b.mean(1)
    x[4] = 15.0  # num_nodes in [1, 14]
    with pytest.raises(ConfigError, match="num_nodes|outside the parameter box"):
        check_in_bounds(x, b)
    with pytest.raises(ConfigError):
        check_in_bounds(b.mean(1)[:3], b)
    with pytest.raises(ConfigError):
        run_seed(quadratic(np.zeros(2), np.ones(2)), [[0, 1], [0, 1]], seed=-1)
    with pytest.raises(ConfigError):
        run_random(quadratic(np.zeros(2), np.ones(2)), [[0, 1], [0, 1]], n_evals=0)


def test_bad_objective_value_raises_input_error():
    with pytest.raises(InputError, match="evaluation 0"):
        run_seed(lambda x, i: math.nan, [[0, 1]], BOConfig(n_evals=4, n_initial=2))


def test_gp_incremental_update_matches_full_factorisation():
    rng = np.random.default_rng(0)
    X = rng.random((60, 3))
    y = np.sin(4 * X).sum(1)
    theta = fit_hyperparameters(X[:40], y[:40])
    inc = MaternGP(X[:40], y[:40], theta)
    for i in range(40, 60):
        inc.append(X[i], y[i])
    full = MaternGP(X, y, theta)
    full.y_mean, full.y_std = inc.y_mean, inc.y_std
    full.ys = (y - inc.y_mean) / inc.y_std
    np.testing.assert_allclose(inc.L, full.L, atol=1e-9)
    # kept column-major, as LAPACK's triangular solves take it (a row-major factor is copied
    # whole on every solve: most of BO's overhead at n = 500, benchmarks/RESULTS.md #gp-layout)
    assert inc.L.flags.f_contiguous and full.L.flags.f_contiguous
    Xs = rng.random((5, 3))
    m1, s1 = inc.predict(Xs)
    full.alpha = cho_solve((full.L, True), full.ys)
    m2, s2 = full.predict(Xs)
    np.testing.assert_allclose(m1, m2, atol=1e-8)
    np.testing.assert_allclose(s1, s2, atol=1e-8)


def test_run_method_dispatch():
    b = np.array([[0.0, 1.0], [0.0, 1.0]])
    cfg = BOConfig(n_evals=12, n_initial=8, **FAST)
    f = quadratic(np.full(2, 0.4), np.ones(2))
    for m in METHODS:
        r = run_method(m, f, b, seed=0, config=cfg)
        assert r.method == m and np.all((r.X >= 0) & (r.X <= 1))
    with pytest.raises(ConfigError, match="unknown optimisation method"):
        run_method("nelder-mead", Noisy(0), b)


def test_log_output_transform_models_log_loss_and_refuses_negative_values(tmp_path):
    """The GP sees log(y + offset); the objective's values, the best point and the reported
    posterior mean stay in the objective's units; a negative value is a named error."""
    b = np.array([[0.0, 1.0], [0.0, 1.0]])
    centre = np.array([0.37, 0.61])

    def steep(x, i):  # a loss spanning five orders of magnitude over the box
        return float(1e-4 + 10.0 * ((x - centre) ** 2).sum() ** 2)

    cfg = BOConfig(n_evals=40, n_initial=12, output_transform="log", **FAST)
    r = run_seed(steep, b, cfg, seed=3, checkpoint=tmp_path / "log.json")
    assert r.complete and r.best_y == r.y.min() and r.best_y < 1e-3
    assert np.abs(r.best_x - centre).max() < 0.08
    # The posterior mean is reported back in the objective's units, next to the observed values.
    k = int(np.argmin(np.abs(r.X - r.best_x_posterior).sum(1)))
    assert 0.2 * r.y[k] < r.best_mean_posterior < 5.0 * r.y[k]
    assert r.hyperparameters["output_transform"] == "log"
    assert r.config["output_transform"] == "log"
    # A run without the transform records the configuration as runs before it did.
    plain = run_seed(steep, b, BOConfig(n_evals=14, n_initial=12, **FAST), seed=3)
    assert "output_transform" not in plain.config and "log_offset" not in plain.config
    # and a checkpoint of the other transform is another run's.
    with pytest.raises(ConfigError, match="another run"):
        run_seed(
            steep,
            b,
            BOConfig(n_evals=40, n_initial=12, **FAST),
            seed=3,
            checkpoint=tmp_path / "log.json",
        )
    with pytest.raises(InputError, match="output_transform='log'"):
        run_seed(
            lambda x, i: -1.0,
            b,
            BOConfig(n_evals=14, n_initial=12, output_transform="log", **FAST),
            seed=0,
        )


VALLEY_CENTRE = np.array([0.41, 0.63, 0.29])
VALLEY_AXIS = np.array([1.0, -1.0, 0.5]) / 1.5


def valley(x: np.ndarray, eval_index: int) -> float:
    """A narrow tilted valley (condition number ~300): a stationary GP over the whole box
    resolves its floor poorly, a simplex follows it."""
    z = x - VALLEY_CENTRE
    return float(1e3 * (z @ VALLEY_AXIS) ** 2 + 3.0 * (z @ z) + 1e-3)


def test_local_search_spends_the_last_evaluations_and_goes_down_the_valley():
    b = np.array([[0.0, 1.0]] * 3)
    base = BOConfig(n_evals=60, n_initial=20, **FAST)
    gp_only = run_seed(valley, b, base, seed=4)
    local = run_seed(valley, b, BOConfig(n_evals=60, n_initial=20, local_evals=25, **FAST), seed=4)
    assert local.n_evals <= 60
    # the design and the first GP steps are the same run's
    np.testing.assert_array_equal(local.X[:35], gp_only.X[:35])
    before = float(local.y[:35].min())
    assert local.best_y < 0.3 * before, (before, local.best_y)
    assert local.best_y < gp_only.best_y  # at the same budget
    # the search starts at the lowest point of the GP phase: every later point is near it
    start = local.X[:35][int(np.argmin(local.y[:35]))]
    assert np.abs(local.X[35:] - start).max() < 0.5
    assert local.config["local_evals"] == 25 and "local_evals" not in gp_only.config


def test_a_local_search_that_stopped_early_is_a_finished_checkpoint(tmp_path):
    """Nelder-Mead may end before the budget (its simplex shrunk on a flat loss): the finished
    checkpoint is returned as it is, not refused as "short of its budget"."""

    def plateaus(x, i):  # flat steps, as a histogram loss under common random numbers
        return float(np.floor(((x - 0.3) ** 2).sum() * 50) / 50)

    b = np.array([[0.0, 1.0]] * 2)
    cfg = BOConfig(n_evals=60, n_initial=10, local_evals=40, **FAST)
    ck = tmp_path / "c.json"
    first = run_seed(plateaus, b, cfg, seed=0, checkpoint=ck)
    assert first.complete and first.n_evals < 60

    def boom(x, i):
        raise AssertionError("objective called for a finished run")

    again = run_seed(boom, b, cfg, seed=0, checkpoint=ck)
    np.testing.assert_array_equal(again.X, first.X)


@pytest.mark.parametrize("kill_at", [36, 47])
def test_resume_inside_the_local_search_equals_uninterrupted(tmp_path, kill_at):
    b = np.array([[0.0, 1.0]] * 3)
    cfg = BOConfig(
        n_evals=50, n_initial=12, refit_every=5, local_evals=20, checkpoint_every=4, **FAST
    )

    class Killed:
        def __init__(self, at=None):
            self.at, self.calls = at, []

        def __call__(self, x, i):
            if i == self.at:
                raise KeyboardInterrupt
            self.calls.append(i)
            return valley(x, i)

    full = run_seed(Killed(), b, cfg, seed=2)
    ck = tmp_path / "c.json"
    with pytest.raises(KeyboardInterrupt):
        run_seed(Killed(kill_at), b, cfg, seed=2, checkpoint=ck)
    again = Killed()
    resumed = run_seed(again, b, cfg, seed=2, checkpoint=ck)
    assert again.calls and again.calls[0] == kill_at  # stored evaluations are replayed, not redone
    np.testing.assert_array_equal(resumed.X, full.X)
    np.testing.assert_array_equal(resumed.y, full.y)
    assert resumed.best_y == full.best_y


@pytest.mark.parametrize("kw", [{"local_evals": 41}, {"local_evals": 5, "local_step": 0.0}])
def test_bad_local_search_settings_are_named(kw):
    with pytest.raises(ConfigError, match="local_"):
        BOConfig(n_evals=50, n_initial=10, **kw).validate()
