"""Choosing the fit's answer from its seeds (``cropcraft_core/fit/select.py``): the pooled GP's
minimum and the re-scoring of candidates on fresh canopies, on real fits."""

from dataclasses import replace

import numpy as np
import pytest

from cropcraft_core.config import default_layout
from cropcraft_core.config.params import bounds as param_bounds
from cropcraft_core.config.params import params_from_vector
from cropcraft_core.errors import ConfigError
from cropcraft_core.fit import FitConfig, ForwardModel, combine, fit_seed, observe_canopy
from cropcraft_core.fit.select import (
    averaged_minimum,
    candidates,
    polish,
    reevaluation_seeds,
    unpolished,
)
from cropcraft_core.observe import preset
from cropcraft_core.optimize import SeedResult, aggregate
from cropcraft_core.procedural import generate_canopy

SMALL = {"image_width": 248, "image_height": 184}


def _seed(seed: int, X: np.ndarray, y: np.ndarray, bounds: np.ndarray) -> SeedResult:
    i = int(np.argmin(y))
    return SeedResult(
        method="bo",
        seed=seed,
        bounds=bounds,
        X=X,
        y=y,
        best_x=X[i],
        best_y=float(y[i]),
        seconds_optimizer=0.0,
        seconds_objective=0.0,
        seconds_per_eval=np.zeros(len(y)),
    )


def test_averaged_minimum_is_the_minimum_of_the_seed_averaged_loss():
    """Each seed sees the bowl shifted by its own canopy offset; the pooled GP's minimum is the
    minimum of the average bowl (the offsets' mean), not any one seed's."""
    rng = np.random.default_rng(3)
    bounds = np.array([[0.0, 2.0], [1.0, 14.0], [0.5, 1.5]])
    lo, span = bounds[:, 0], bounds[:, 1] - bounds[:, 0]
    centre = np.array([0.4, 0.6, 0.5])
    offsets = rng.normal(0.0, 0.06, (10, 3))
    results = []
    for s, off in enumerate(offsets):
        # random exploration plus points clustered where a seed's optimiser would end up
        U = np.clip(
            np.vstack([rng.random((150, 3)), centre + off + rng.normal(0, 0.05, (150, 3))]), 0, 1
        )
        y = 0.002 + 0.4 * ((U - centre - off) ** 2).sum(1)
        results.append(_seed(s, lo + span * U, y, bounds))
    got = (averaged_minimum(results) - lo) / span
    target = centre + offsets.mean(0)
    assert np.abs(got - target).max() < 0.04
    # and it lies nearer that minimum than a typical single seed's best point
    single = [np.abs((r.best_x - lo) / span - target).max() for r in results]
    assert np.abs(got - target).max() < np.median(single)


def test_averaged_minimum_refuses_seeds_from_different_boxes():
    X = np.random.default_rng(0).random((20, 2))
    a = _seed(0, X, X.sum(1) + 0.1, np.array([[0.0, 1.0], [0.0, 1.0]]))
    b = _seed(1, X, X.sum(1) + 0.1, np.array([[0.0, 2.0], [0.0, 1.0]]))
    with pytest.raises(ConfigError, match="different parameter box"):
        averaged_minimum([a, b])


@pytest.fixture(scope="module")
def soybean_seeds():
    truth = {"leaf_length": 1.0, "petiole_length": 1.1, "petiole_angle": 1.5, "num_nodes": 7.0}
    canopy = generate_canopy("soybean", truth, default_layout("soybean"), seed=5)
    obs = observe_canopy(canopy, preset("soybean", **SMALL))
    cfg = FitConfig(
        n_seeds=3,
        n_evals=30,
        n_initial=12,
        combine="reevaluate",
        reevaluate_canopies=4,
        polish_evals=0,  # the plain re-scoring; the polish has its own test
    )
    return obs, cfg, [fit_seed(obs, s, cfg) for s in range(3)]


def test_reevaluate_keeps_the_candidate_with_the_lowest_fresh_canopy_loss(soybean_seeds):
    obs, cfg, seeds = soybean_seeds
    fit = combine("soybean", seeds, cfg, 1.0, obs)
    sel = fit.extra["selection"]
    assert set(sel["candidates"]) == {"seed-0", "seed-1", "seed-2", "mean", "averaged"}
    losses = {k: c["loss"] for k, c in sel["candidates"].items()}
    assert sel["chosen"] == min(losses, key=losses.get)
    assert fit.params == sel["candidates"][sel["chosen"]]["params"]
    # the recorded losses are reproducible: the same fresh canopies, none a seed fitted to
    assert sel["canopy_seeds"] == reevaluation_seeds(4)
    fm = ForwardModel(obs)
    for k in ("mean", sel["chosen"]):
        assert fm.loss(sel["candidates"][k]["params"], sel["canopy_seeds"]) == pytest.approx(
            losses[k], rel=1e-12
        )
    # the spread reported is still the seeds' spread, and the mean candidate is the paper's
    paper = combine("soybean", seeds, FitConfig(**{**cfg.to_dict(), "combine": "mean"}), 1.0)
    assert fit.params_std == paper.params_std
    assert sel["candidates"]["mean"]["params"] == pytest.approx(paper.params)
    assert paper.extra == {} and fit.seconds > 1.0
    # candidates are inside the box
    b = param_bounds("soybean")
    for x in candidates(seeds).values():
        assert np.all(x >= b[:, 0] - 1e-12) and np.all(x <= b[:, 1] + 1e-12)
    assert np.allclose(aggregate(seeds).mean_x, candidates(seeds)["mean"])
    params_from_vector("soybean", candidates(seeds)["averaged"])  # a valid parameter set


def test_polish_refines_the_lowest_rescored_candidate_on_the_same_canopies(soybean_seeds):
    """Nelder-Mead from the lowest re-scored candidate(s) on the re-scoring canopies: never
    worse than its start, reproducible, inside the box; polish_evals=0 is the plain re-scoring."""
    obs, cfg, seeds = soybean_seeds
    plain = combine("soybean", seeds, cfg, 1.0, obs)
    assert not any(k.startswith("polished") for k in plain.extra["selection"]["candidates"])
    fit = combine("soybean", seeds, replace(cfg, polish_starts=2, polish_evals=25), 1.0, obs)
    sel = fit.extra["selection"]
    losses = {k: c["loss"] for k, c in sel["candidates"].items()}
    rescored = sorted((k for k in losses if not k.startswith("polished")), key=losses.get)
    assert [k for k in losses if k.startswith("polished")] == [
        f"polished-{k}" for k in rescored[:2]
    ]
    for k in rescored[:2]:
        assert losses[f"polished-{k}"] <= losses[k]
    assert sel["chosen"] == min(losses, key=losses.get)
    assert sel["chosen"].startswith("polished-")  # 25 steps from a 30-evaluation fit do improve
    assert losses[sel["chosen"]] < plain.extra["selection"]["candidates"][rescored[0]]["loss"]
    fm = ForwardModel(obs)
    assert fm.loss(fit.params, sel["canopy_seeds"]) == pytest.approx(
        losses[sel["chosen"]], rel=1e-12
    )
    b = param_bounds("soybean")
    x = np.array(list(fit.params.values()))
    assert np.all(x >= b[:, 0]) and np.all(x <= b[:, 1])
    x0 = candidates(seeds)[rescored[0]]
    got, v, n = polish(fm, x0, sel["canopy_seeds"], 25)
    assert n <= 26 and v == pytest.approx(losses[f"polished-{rescored[0]}"], rel=1e-12)
    assert np.allclose(got, list(sel["candidates"][f"polished-{rescored[0]}"]["params"].values()))
    # the unpolished answer read back from the polished record is the plain re-scoring's
    name, params, rescore = unpolished(sel)
    assert name == plain.extra["selection"]["chosen"] and params == plain.params
    assert 0 < rescore < sel["seconds"]


def test_reevaluate_needs_the_observation_and_valid_settings(soybean_seeds):
    obs, cfg, seeds = soybean_seeds
    with pytest.raises(ConfigError, match="pass it"):
        combine("soybean", seeds, cfg, 0.0)
    with pytest.raises(ConfigError, match="observation is of soybean"):
        combine("maize", seeds, cfg, 0.0, obs)
    # the crop's default rule: maize re-scores, soybean takes the seeds' guarded median
    assert FitConfig().combine_rule("maize") == "reevaluate"
    assert FitConfig().combine_rule("soybean") == "guarded"
    assert FitConfig(combine="mean").combine_rule("maize") == "mean"
    with pytest.raises(ConfigError, match="unknown combine rule"):
        FitConfig(combine="mode").validate()
    with pytest.raises(ConfigError, match="reevaluate_canopies"):
        FitConfig(reevaluate_canopies=0).validate()
    for bad in ({"polish_starts": 0}, {"polish_evals": -1}):
        with pytest.raises(ConfigError, match="polish_starts >= 1"):
            FitConfig(**bad).validate()


def test_median_rule_ignores_a_stranded_seed():
    """``combine="median"`` (soybean's default answer, unless guarded re-scoring finds a deeper
    basin) is the per-parameter median of the seeds' best points: one seed stranded at the box's
    far corner moves the mean, not the median."""
    b = param_bounds("soybean")
    lo, span = b[:, 0], b[:, 1] - b[:, 0]
    rng = np.random.default_rng(3)
    centre = lo + 0.4 * span
    pts = [centre + 0.01 * span * rng.standard_normal(len(lo)) for _ in range(4)] + [b[:, 1]]
    seeds = []
    for s, x in enumerate(pts):
        X = np.vstack([lo + rng.random((5, len(lo))) * span, x])
        seeds.append(_seed(s, X, np.r_[np.ones(5), 0.1], b))
    med = combine("soybean", seeds, FitConfig(n_seeds=5, combine="median"), 0.0)
    mean = combine("soybean", seeds, FitConfig(n_seeds=5, combine="mean"), 0.0)
    expect = params_from_vector("soybean", np.median(np.vstack(pts), axis=0))
    assert med.params == pytest.approx(expect)
    assert med.params_std == mean.params_std  # the spread reported is the seeds' spread
    far = params_from_vector("soybean", b[:, 1])
    for k, v in med.params.items():
        assert abs(v - expect[k]) < 1e-12
        assert abs(mean.params[k] - far[k]) < abs(v - far[k])  # the mean is pulled to the corner


def test_a_point_an_ulp_outside_the_box_is_set_on_its_bound():
    """Arithmetic on points of the box can land an ulp outside it (the mean of seeds at a
    bound, ``low + range * u``); such a vector still makes a valid canopy, a real excursion
    is still a named error."""
    from cropcraft_core.config.params import resolve_params

    b = param_bounds("maize")  # leaf_length, leaf_order_shift, internode_length, num_nodes
    x = np.array(
        [np.nextafter(b[0, 0], -np.inf), 0.0, np.nextafter(b[2, 1], np.inf), b[3, 1] + 1e-12]
    )
    p = params_from_vector("maize", x)
    assert resolve_params("maize", p) == p
    assert [p["leaf_length"], p["internode_length"], p["num_nodes"]] == [b[0, 0], *b[2:, 1]]
    far = b[:, 0] - 1e-6 * (b[:, 1] - b[:, 0])
    with pytest.raises(ConfigError, match="outside its range"):
        resolve_params("maize", params_from_vector("maize", far))


@pytest.fixture(scope="module")
def truth_scene():
    """A soybean observation of known parameters at a test's size: (observation, the crop's
    box, the true point, a point far off in every parameter)."""
    from cropcraft_core.config.params import ParamBox

    truth = {
        "leaf_length": 1.0,
        "petiole_length": 1.1,
        "petiole_angle": 1.5,
        "internode_length": 1.25,
        "num_nodes": 7.0,
    }
    obs = observe_canopy(
        generate_canopy("soybean", truth, default_layout("soybean"), seed=5),
        preset("soybean", **SMALL),
    )
    box = ParamBox.of("soybean")
    t = np.array([truth[n] for n in box.names])
    return obs, box, t, np.array([0.55, 1.9, 3.8, 0.6, 3.0])


def test_guarded_keeps_the_median_unless_the_winner_is_significantly_deeper(truth_scene):
    """``combine="guarded"``: the seeds' median, unless re-scoring's winner beats the median's
    own floor on fresh canopies by more than two standard errors. A winner at the true
    parameters against seeds stranded far off: the winner. A winner that is the median itself:
    a tie, the median. A far-off winner against seeds around the truth: the median."""
    from cropcraft_core.fit.select import Selection, guard

    obs, box, t, far = truth_scene

    def seeds(centre: np.ndarray) -> list[SeedResult]:
        pts = [centre + d for d in (np.zeros(5), 0.02 * np.ones(5), -0.02 * np.ones(5))]
        return [
            _seed(
                s, np.clip(p, box.bounds[:, 0], box.bounds[:, 1])[None], np.array([0.1]), box.bounds
            )
            for s, p in enumerate(pts)
        ]

    def selection(x: np.ndarray) -> Selection:
        return Selection(
            "seed-0", x, {"seed-0": x}, {"seed-0": 0.0}, reevaluation_seeds(4), 0.0, 0.0
        )

    fm = ForwardModel(obs)
    stranded = seeds(far)
    g = guard(fm, stranded, selection(t), polish_evals=6, box=box, check=8)
    assert g.chosen == "seed-0" and np.array_equal(g.x, t)
    assert g.difference[0] < -2 * g.difference[1]
    assert np.allclose(g.median, np.median([r.best_x for r in stranded], axis=0))
    assert g.canopy_seeds == reevaluation_seeds(12)[4:]  # none the re-scoring used
    rec = g.to_dict(box)
    assert rec["chosen"] == "seed-0" and set(rec["median_floor"]) == set(box.names)

    tie = guard(fm, stranded, selection(g.median), polish_evals=0, box=box, check=8)
    assert tie.chosen == "median" and tie.difference == (0.0, 0.0)

    near = seeds(t)
    kept = guard(fm, near, selection(far), polish_evals=6, box=box, check=8)
    assert kept.chosen == "median" and np.allclose(kept.x, np.median([r.best_x for r in near], 0))
    assert kept.difference[0] > 0


def test_guarded_through_combine_records_its_verdict(soybean_seeds):
    """The rule re-scores like ``reevaluate`` (it needs the observation), keeps that record and
    adds its own; its answer is the re-scored winner or the seeds' median, as it says."""
    obs, cfg, seeds = soybean_seeds
    cfg = replace(cfg, combine="guarded", polish_evals=4)
    assert cfg.reevaluates("soybean")
    fit = combine("soybean", seeds, cfg, 0.0, obs)
    g, sel = fit.extra["guard"], fit.extra["selection"]
    assert g["rule"] == "guarded" and g["canopy_seeds"] == reevaluation_seeds(4 + 32)[4:]
    if g["chosen"] == "median":
        assert np.allclose(list(fit.params.values()), np.median(aggregate(seeds).per_seed, 0))
        assert g["difference"]["mean"] >= -2 * g["difference"]["se"]
    else:
        assert g["chosen"] == sel["chosen"]
        assert fit.params == sel["candidates"][sel["chosen"]]["params"]
    with pytest.raises(ConfigError, match="pass it"):
        combine("soybean", seeds, cfg, 0.0)

    # combine makes the median's floor beside the selection, and the guard scores the two
    # floors side by side (threads): the same bits as the selection, then the guard, alone
    from cropcraft_core.fit.select import guard, select

    box, fm = cfg.param_box("soybean"), ForwardModel(obs, None, cfg.loss_estimator)
    alone = select(fm, seeds, cfg.reevaluate_canopies, cfg.polish_starts, 4, box=box)
    g_alone = guard(fm, seeds, alone, 4, box).to_dict(box)
    assert alone.to_dict(box)["candidates"] == sel["candidates"]
    assert {k: v for k, v in g_alone.items() if k != "seconds"} == {
        k: v for k, v in g.items() if k != "seconds"
    }


def test_beside_runs_both_and_ends_the_other_at_once_where_the_main_fails():
    """``beside`` runs ``other`` in a second thread on a copy of the forward model whose
    timings are added to the model's; where ``main`` fails its error comes at once, and the
    other thread's work stops at its next canopy instead of running to its end."""
    import threading
    import time

    from cropcraft_core.fit.forward import Stopped
    from cropcraft_core.fit.select import beside

    truth = {"leaf_length": 1.0, "petiole_length": 1.0, "petiole_angle": 2.0}
    truth |= {"internode_length": 1.0, "num_nodes": 5.0}
    canopy = generate_canopy("soybean", truth, default_layout("soybean"), seed=3)
    forward = ForwardModel(observe_canopy(canopy, preset("soybean", **SMALL)))
    names: list[str] = []

    def other(fm: ForwardModel) -> float:
        names.append(threading.current_thread().name)
        assert fm is not forward and fm.stop is not None
        return fm.loss(truth, 1)

    first, second = beside(forward, lambda fm: fm.loss(truth, 0), other)
    assert first == forward.loss(truth, 0) and second == forward.loss(truth, 1)
    assert names and names[0] != threading.current_thread().name
    # the copy's canopy was counted in the model's timings (the two made here, then two more)
    assert forward.timings["calls"] == 4

    done: list[BaseException] = []

    def endless(fm: ForwardModel) -> None:
        try:
            while True:
                fm.loss(truth, 1)
        except BaseException as e:  # what ended it
            done.append(e)
            raise

    def failing(fm: ForwardModel) -> None:
        time.sleep(0.5)  # the other thread is among its canopies by now
        raise ValueError("main failed")

    with pytest.raises(ValueError, match="main failed"):  # returns at all: ``endless`` never
        beside(forward, failing, endless)  # ends on its own, so it was not waited for

    def beside_threads() -> list[threading.Thread]:
        return [th for th in threading.enumerate() if th.name.startswith("cropcraft-beside")]

    deadline = time.perf_counter() + 10
    while (not done or beside_threads()) and time.perf_counter() < deadline:
        time.sleep(0.05)
    assert done and isinstance(done[0], Stopped)
    assert not beside_threads()  # the thread itself has ended, so nothing holds the exit


def test_benchmark_rows_share_one_rescoring_and_answer_as_separate_combines(soybean_seeds):
    """``combine_scene`` re-scores once for the guarded and the re-scored rows (and reads the
    unpolished row from it): every row answers what its own ``combine`` call answers."""
    from benchmarks.bench_accuracy import combine_scene, rules

    obs, cfg, seeds = soybean_seeds
    cfg = replace(cfg, combine=None, polish_evals=4)
    rows = rules("soybean", "bo", cfg)
    assert {r for r, _ in rows} >= {"bo", "bo-reevaluate", "bo-reevaluate-unpolished"}
    answers = combine_scene("soybean", rows, seeds, 2.0, obs)
    for row, c in rows:
        f = combine("soybean", seeds, c, 2.0, obs if c.reevaluates("soybean") else None)
        assert answers[row][0] == f.params, row
    with pytest.raises(ConfigError, match="pass it"):
        combine_scene("soybean", rows, seeds, 2.0)


def test_floors_ranks_every_floor_on_fresh_canopies_and_guards_the_lowest(soybean_seeds):
    """``combine="floors"``: every candidate polished on the re-scoring canopies, ranked on
    fresh ones, the lowest taken only where it beats the median's floor on further canopies;
    seeds that bring their floor (their own task polished it) are not polished again, and the
    answer is the same."""
    from benchmarks.bench_accuracy import combine_scene, rules
    from cropcraft_core.fit.select import seed_floor

    obs, cfg, seeds = soybean_seeds
    cfg = replace(cfg, combine="floors", polish_evals=4)
    assert cfg.reevaluates("soybean")
    fit = combine("soybean", seeds, cfg, 0.0, obs)
    f = fit.extra["floors"]
    assert f["rule"] == "floors" and "selection" not in fit.extra
    assert set(f["floors"]) == {"seed-0", "seed-1", "seed-2", "mean", "averaged"}
    assert f["from_seeds"] == [] and all(r.floor is None for r in seeds)  # inputs untouched
    assert f["pick_canopy_seeds"] == reevaluation_seeds(4 + 32)[4:20]
    assert f["check_canopy_seeds"] == reevaluation_seeds(4 + 32)[20:]
    pick = {k: v["pick_loss"] for k, v in f["floors"].items()}
    best = min(pick, key=pick.get)
    fm = ForwardModel(obs)
    got = np.mean([fm.loss(f["floors"][best]["params"], [c]) for c in f["pick_canopy_seeds"]])
    assert got == pytest.approx(pick[best], rel=1e-12)
    # each floor is its polish from the candidate, never worse there than the candidate
    x, v, _ = polish(fm, candidates(seeds)["mean"], reevaluation_seeds(4), 4)
    assert list(f["floors"]["mean"]["params"].values()) == pytest.approx(list(x), rel=1e-12)
    assert f["floors"]["mean"]["polish_loss"] == pytest.approx(v, rel=1e-12)
    if f["chosen"] == "median":
        assert np.allclose(list(fit.params.values()), np.median(aggregate(seeds).per_seed, 0))
        assert f["difference"]["mean"] >= -2 * f["difference"]["se"]
    else:
        assert f["chosen"] == best and fit.params == f["floors"][best]["params"]
        assert f["difference"]["mean"] < -2 * f["difference"]["se"]
    # the seeds' own floors (as fit_seed makes them under this rule) give the same answer
    floored = [seed_floor(fm, r, 4, 4) for r in seeds]
    again = combine("soybean", floored, cfg, 0.0, obs)
    assert again.extra["floors"]["from_seeds"] == ["seed-0", "seed-1", "seed-2"]
    assert again.params == fit.params
    # the benchmark's floors row: the same answer, its seconds counting the seeds' polishes
    ((params, seconds),) = combine_scene("soybean", [("bo", cfg)], floored, 2.0, obs).values()
    assert params == fit.params
    assert seconds > 2.0 + sum(r.floor["seconds"] for r in floored)
    # opt-in: the benchmark's automatic comparison rows leave it out
    assert not any("floors" in r for r, _ in rules("soybean", "bo", replace(cfg, combine=None)))
    with pytest.raises(ConfigError, match="pass it"):
        combine("soybean", seeds, cfg, 0.0)


def test_floors_takes_a_seed_at_the_truth_over_a_median_stranded_far_off(truth_scene):
    from cropcraft_core.fit.select import floors

    obs, box, t, far = truth_scene
    lo, hi = box.bounds[:, 0], box.bounds[:, 1]

    def seed(s: int, p: np.ndarray) -> SeedResult:  # three evaluations around p, best at p
        X = np.clip(np.vstack([p, p + 0.03 * (hi - lo), p - 0.03 * (hi - lo)]), lo, hi)
        return _seed(s, X, np.array([0.1, 0.2, 0.2]), box.bounds)

    results = [seed(0, t), seed(1, far), seed(2, far + 0.01 * (hi - lo))]
    got = floors(ForwardModel(obs), results, canopies=4, polish_evals=0, box=box, pick=8, check=8)
    assert got.chosen == "seed-0" and np.allclose(got.x, t)
    assert got.difference[0] < -2 * got.difference[1]
    assert np.allclose(got.median, np.median([r.best_x for r in results], axis=0))
    assert got.pick_seeds == reevaluation_seeds(20)[4:12]
    assert got.check_seeds == reevaluation_seeds(20)[12:]


def test_a_floors_seed_polishes_its_point_once_and_a_resumed_one_keeps_it(tmp_path, monkeypatch):
    """Under ``combine="floors"`` ``fit_seed`` polishes the seed's point on the re-scoring
    canopies and checkpoints it with the search; a run resumed from that checkpoint returns the
    same floor without polishing (the polish would fail here); other rules polish nothing."""
    from cropcraft_core.fit import select as select_mod

    truth = {"leaf_length": 1.0, "petiole_length": 1.1, "petiole_angle": 1.5, "num_nodes": 7.0}
    obs = observe_canopy(
        generate_canopy("soybean", truth, default_layout("soybean"), seed=5),
        preset("soybean", **SMALL),
    )
    cfg = FitConfig(
        n_seeds=1, n_evals=14, n_initial=8, combine="floors", reevaluate_canopies=3, polish_evals=5
    )
    ckpt = tmp_path / "seed-0.json"
    r = fit_seed(obs, 0, cfg, checkpoint=ckpt)
    assert r.floor["canopy_seeds"] == reevaluation_seeds(3) and r.floor["polish_evals"] == 5
    assert 1 <= r.floor["evals"] <= 6
    fm = ForwardModel(obs)
    assert fm.loss(params_from_vector("soybean", r.floor["x"]), reevaluation_seeds(3)) == (
        pytest.approx(r.floor["loss"], rel=1e-12)
    )
    assert r.floor["loss"] <= fm.loss(
        params_from_vector("soybean", r.reported_x), reevaluation_seeds(3)
    )
    assert SeedResult.load(ckpt).floor == r.floor
    assert SeedResult.load(r.save(tmp_path / "seed.npz")).floor == r.floor  # the flow's store

    def no_polish(*a, **k):
        raise AssertionError("a resumed seed polished its point again")

    monkeypatch.setattr(select_mod, "polish", no_polish)
    again = fit_seed(obs, 0, cfg, checkpoint=ckpt)
    assert again.floor == r.floor and np.array_equal(again.X, r.X)
    assert fit_seed(obs, 0, replace(cfg, combine="guarded")).floor is None
    # a different polish is another floor: the search is resumed, the point polished anew
    monkeypatch.undo()
    other = fit_seed(obs, 0, replace(cfg, polish_evals=3), checkpoint=ckpt)
    assert other.floor["polish_evals"] == 3 and np.array_equal(other.X, r.X)
