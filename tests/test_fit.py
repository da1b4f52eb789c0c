"""The fitting layer on real synthetic observations (real generator, renderer, histograms, GP)."""

import json
import shutil
from dataclasses import replace

import numpy as np
import pytest

from cropcraft_core.config import default_layout
from cropcraft_core.config.params import ParamBox, bounds, param_space, resolve_params
from cropcraft_core.errors import ConfigError, InputError
from cropcraft_core.fit import (
    FitConfig,
    ForwardModel,
    combine,
    fit_observation,
    fit_seed,
    observe_canopy,
)
from cropcraft_core.fit.mlp import (
    MLPConfig,
    observation_features,
    predict_params,
    training_pairs,
)
from cropcraft_core.metrics import canopy_metrics
from cropcraft_core.observe import preset
from cropcraft_core.optimize import SeedResult
from cropcraft_core.procedural import generate_canopy

# a quarter of the paper's 994 x 738 keeps the tests fast; the statistics are resolution-free
SMALL = {"image_width": 248, "image_height": 184}


#: A mid-sized soybean canopy that the loss tests observe.
SOY_TRUTH = {
    "leaf_length": 1.2,
    "petiole_length": 1.0,
    "petiole_angle": 2.0,
    "internode_length": 1.2,
    "num_nodes": 8.0,
}


def observation(crop, params, seed=11):
    canopy = generate_canopy(crop, params, default_layout(crop), seed=seed)
    return observe_canopy(canopy, preset(crop, **SMALL)), canopy


def test_true_parameters_beat_a_far_off_point():
    """The loss tells the truth from a far-off point (fewer nodes, smaller leaves)."""
    truth = SOY_TRUTH
    obs, _ = observation("soybean", truth)
    fm = ForwardModel(obs)
    at_truth = np.mean([fm.loss(truth, s) for s in range(3)])
    far = {**truth, "leaf_length": 0.5, "num_nodes": 3.0}
    assert at_truth < np.mean([fm.loss(far, s) for s in range(3)])
    assert fm.timings["calls"] == 6


def test_an_observation_pools_row_cameras_along_the_row_and_over_neighbouring_rows(tmp_path):
    """``views_along``/``views_across``: the observation's statistics are the bin-by-bin mean
    of the row cameras along its row and over the rows beside it; its depth map, mask and camera
    stay the row camera's, and the pooled statistics survive a save and a load."""
    from cropcraft_core.observe import Observation, loss, mean_stats

    layout = default_layout("soybean")
    canopy = generate_canopy("soybean", SOY_TRUTH, layout, seed=11)
    single = preset("soybean", **SMALL)
    pooled_preset = preset("soybean", **SMALL, views_along=3, views_across=1)
    obs = observe_canopy(canopy, pooled_preset)
    offsets = pooled_preset.view_offsets(layout.row_spacing)
    assert len(offsets) == 9 and obs.meta["views"] == [list(o) for o in offsets]
    views = [
        observe_canopy(canopy, single, camera=single.row_camera().shifted(dx, dy))
        for dx, dy in offsets
    ]
    assert obs.stats.equals(mean_stats([v.stats for v in views]))
    assert len({round(v.stats.mask_area, 6) for v in views}) > 1  # nine different draws
    np.testing.assert_array_equal(obs.depth, views[0].depth)
    np.testing.assert_array_equal(obs.mask, views[0].mask)
    assert obs.camera.to_dict() == views[0].camera.to_dict()
    # one camera (the default) is the paper's observation, bit for bit
    assert observe_canopy(canopy, single).stats.equals(views[0].stats)
    obs.save(tmp_path / "o")
    assert Observation.load(tmp_path / "o").equals(obs)
    # the prediction side is unchanged: the row camera's own canopy, predicted, scores its
    # distance from the pool
    assert ForwardModel(obs).loss(SOY_TRUTH, 11) == pytest.approx(
        loss(obs.stats, views[0].stats, obs.preset).total, rel=1e-9
    )
    # maize: every view is binned over the row camera's own canopy (its resolved depth range)
    maize = generate_canopy("maize", {"num_nodes": 9.0}, default_layout("maize"), seed=11)
    m1 = observe_canopy(maize, preset("maize", **SMALL))
    m3 = observe_canopy(maize, preset("maize", **SMALL, views_along=3, view_step=1.0))
    assert m3.preset.depth_range == m1.preset.depth_range and m3.stats.spec == m1.stats.spec
    assert len(m3.meta["views"]) == 3


def test_surfaces_in_their_own_units_pool_the_same_views():
    """``Observation.from_surfaces`` moves the scene-frame camera by the metric offsets over
    the scale, so surfaces in their own units (here 2 per metre) give each pooled view exactly
    what a metric render of it gives."""
    from cropcraft_core.observe import Observation, mean_stats
    from cropcraft_core.render.raster import render_depth

    canopy = generate_canopy("soybean", SOY_TRUTH, default_layout("soybean"), seed=11)
    v, f = canopy.mesh.vertices, canopy.mesh.faces
    p = preset("soybean", **SMALL, views_along=3, view_step=0.3, views_across=1)
    cam = p.row_camera()
    scene = cam.cam_to_world.copy()
    scene[:3, 3] *= 2.0
    cam_scene = type(cam)(cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy, scene)

    def render(c):
        return render_depth(v * 2.0, f, c).depth, None

    obs = Observation.from_surfaces(
        "soybean",
        render,
        cam,
        cam_scene,
        0.5,
        1.0,
        preset_overrides={**SMALL, "views_along": 3, "view_step": 0.3, "views_across": 1},
        row_spacing=0.76,
    )
    one = preset("soybean", **SMALL)
    views = []
    for dx, dy in p.view_offsets(0.76):
        c = cam.shifted(dx, dy)
        views.append(Observation.from_depth("soybean", render_depth(v, f, c).depth, c, preset=one))
    expected = mean_stats([o.stats for o in views])
    for k in ("depth", "lateral", "sobel"):
        np.testing.assert_allclose(getattr(obs.stats, k), getattr(expected, k), atol=1e-12)
    assert obs.stats.mask_area == pytest.approx(expected.mask_area, abs=1e-12)
    assert obs.box_mask and len(obs.meta["views"]) == 9


def test_a_pooled_view_outside_the_reconstruction_is_left_out():
    """With ``no_surface``/``max_no_surface``, ``Observation.from_surfaces`` measures each pooled
    view's share without a reconstructed surface and leaves out those over the limit: here the
    reconstruction holds the row camera's strip only (a ground strip 1 m wide, in scene units
    of 2 per metre), so the neighbouring rows' six views are left out and the pool is the mean
    of the three along the row."""
    from cropcraft_core.observe import Observation, mean_stats, no_surface_fraction
    from cropcraft_core.render.raster import render_depth

    canopy = generate_canopy("soybean", SOY_TRUTH, default_layout("soybean"), seed=11)
    v, f = canopy.mesh.vertices, canopy.mesh.faces
    strip = np.array([[-4.0, -0.5, 0.0], [4.0, -0.5, 0.0], [4.0, 0.5, 0.0], [-4.0, 0.5, 0.0]])
    strip_f = np.array([[0, 1, 2], [0, 2, 3]], np.int32)
    overrides = {**SMALL, "views_along": 3, "view_step": 0.3, "views_across": 1}
    cam = preset("soybean", **overrides, render_height=1.0).row_camera()
    scene = cam.cam_to_world.copy()
    scene[:3, 3] *= 2.0
    cam_scene = type(cam)(cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy, scene)

    def build(**check):
        return Observation.from_surfaces(
            "soybean",
            lambda c: (render_depth(v * 2.0, f, c).depth, None),
            cam,
            cam_scene,
            0.5,
            1.0,
            preset_overrides=overrides,
            row_spacing=0.76,
            **check,
        )

    obs = build(
        no_surface=lambda c: no_surface_fraction(render_depth(strip * 2.0, strip_f, c).depth),
        max_no_surface=0.18,
    )
    assert obs.meta["views"] == [[0.0, 0.0], [-0.3, 0.0], [0.3, 0.0]]
    assert obs.meta["views_outside"] == [0.0, 0.0]
    left = obs.meta["views_left_out"]
    assert [(dx, dy) for dx, dy, _ in left] == [
        (a, c) for c in (-0.76, 0.76) for a in (0.0, -0.3, 0.3)
    ]
    assert all(0.5 < share < 1.0 for *_, share in left)
    one = preset("soybean", **SMALL)
    along = [
        Observation.from_depth("soybean", render_depth(v, f, c).depth, c, preset=one).stats
        for c in (cam, cam.shifted(-0.3, 0.0), cam.shifted(0.3, 0.0))
    ]
    expected = mean_stats(along)
    for k in ("depth", "lateral", "sobel"):
        np.testing.assert_allclose(getattr(obs.stats, k), getattr(expected, k), atol=1e-12)
    # without the check every view is pooled, as before
    full = build()
    assert len(full.meta["views"]) == 9 and "views_left_out" not in full.meta
    with pytest.raises(ConfigError, match="both the measure and its limit"):
        build(max_no_surface=0.18)


def test_the_unbiased_estimator_is_the_mean_cross_term_of_the_canopies():
    """``loss_estimator="unbiased"``: over K canopies the loss's U-statistic, the mean over
    pairs j != k of the bilinear form of (s_j - o) and (s_k - o), computed here by hand; one
    canopy is the loss itself, and the checks compare the U-statistic's jackknife
    pseudo-values over all the canopies (every pair counted), whose mean is the U-statistic."""
    from cropcraft_core.fit.select import _per_canopy

    obs, _ = observation("soybean", SOY_TRUTH)
    pooled, unbiased = ForwardModel(obs), ForwardModel(obs, estimator="unbiased")
    p, o, w = SOY_TRUTH, obs.stats, obs.preset.loss
    seeds = [3, 4, 5]
    s = [pooled.stats(p, k) for k in seeds]

    def form(a, b):
        return (
            (a.depth - o.depth) @ (b.depth - o.depth)
            + w.lambda_lateral * (a.lateral - o.lateral) @ (b.lateral - o.lateral)
            + w.lambda_sobel * (a.sobel - o.sobel) @ (b.sobel - o.sobel)
            + w.lambda_mask * (a.mask_area - o.mask_area) * (b.mask_area - o.mask_area)
        )

    pairs = [form(s[j], s[k]) for j in range(3) for k in range(3) if j != k]
    assert unbiased.loss(p, seeds) == pytest.approx(np.mean(pairs), rel=1e-9)
    assert form(s[0], s[0]) == pytest.approx(pooled.loss(p, 3), rel=1e-9)
    assert unbiased.loss(p, 3) == pooled.loss(p, 3)
    # the pooled loss carries the draw variance the unbiased one leaves out
    assert pooled.loss(p, seeds) > unbiased.loss(p, seeds)
    four = s + [pooled.stats(p, 6)]

    def u(keep):
        return np.mean([form(four[j], four[k]) for j in keep for k in keep if j != k])

    every = u(range(4))
    by_hand = [4 * every - 3 * u([i for i in range(4) if i != j]) for j in range(4)]
    values = _per_canopy(unbiased, p, [3, 4, 5, 6])
    np.testing.assert_allclose(values, by_hand, rtol=1e-9, atol=1e-12)
    assert values.mean() == pytest.approx(unbiased.loss(p, [3, 4, 5, 6]), rel=1e-9)
    assert len(_per_canopy(pooled, p, [3, 4, 5, 6])) == 4
    with pytest.raises(ConfigError, match="at least 3 canopies"):
        _per_canopy(unbiased, p, [3, 4])
    with pytest.raises(ConfigError, match="loss estimator"):
        ForwardModel(obs, estimator="median")
    with pytest.raises(ConfigError, match="loss_estimator"):
        FitConfig(loss_estimator="median").validate()
    with pytest.raises(ConfigError, match="can be negative"):
        FitConfig(loss_estimator="unbiased", gp_output="log").validate()


def test_pipeline_bench_says_whose_miss_an_answer_is():
    """``bench pipeline --fit`` scores the answer and the truth, and their basins' floors under
    each side's loss, on the same fresh canopies against the observation and against the true
    mesh; a canopy's own render is its perfect reconstruction. The truth as the answer ties
    exactly; a far-off answer on a perfect reconstruction is the optimiser's miss; an answer
    that fits a wrong reconstruction (another canopy's render) better than the truth does is
    the reconstruction's."""
    from functools import partial

    from benchmarks.bench_pipeline import loss_attribution

    # the bench's own canopies (16 to polish on, 6 x 16 to score on) cut to a test's size
    loss_attribution = partial(
        loss_attribution,
        floor_evals=12,
        polish_seeds=tuple(range(900, 908)),
        score_groups=tuple(tuple(range(910 + 8 * g, 918 + 8 * g)) for g in range(4)),
    )
    truth = SOY_TRUTH
    obs, _ = observation("soybean", truth)
    same = loss_attribution(obs, obs.depth, truth, truth)
    assert same["observation"]["answer"] == same["observation"]["truth"] > 0
    assert same["true_mesh"] == pytest.approx(same["observation"], rel=1e-9)
    for side in ("observation", "true_mesh"):
        assert same["floor_params"][side]["answer"] == same["floor_params"][side]["truth"]
    assert same["floor_difference"]["observation"] == {"mean": 0.0, "se": 0.0}
    # one floor: each polish ends at the other's, so neither side's flags decide the verdict
    assert all(f["answer"] == f["truth"] for f in same["floor_left_basin"].values())
    assert same["whose"] == "loss"

    far = {**truth, "leaf_length": 0.5, "num_nodes": 3.0}
    miss = loss_attribution(obs, obs.depth, far, truth)
    for against in ("observation", "true_mesh"):
        assert miss[against]["answer"] > 2 * miss[against]["truth"]
        assert miss[against]["truth"] == same[against]["truth"]
        assert miss[against]["answer_floor"] <= miss[against]["answer"]
    assert miss["whose"] == "optimiser"
    # a perfect reconstruction's own fit: the true mesh asked alone, the same figures
    alone = loss_attribution(obs, obs.depth, far, truth, observation_side=False)
    assert set(alone["floor_difference"]) == {"true_mesh"} and "observation" not in alone
    assert alone["true_mesh"] == pytest.approx(miss["true_mesh"], rel=1e-9)
    assert alone["whose"] == "optimiser"
    assert loss_attribution(obs, obs.depth, truth, truth, observation_side=False)["whose"] == "loss"

    other = {**truth, "leaf_length": 0.8, "num_nodes": 5.0}
    wrong, _ = observation("soybean", other)
    moved = loss_attribution(wrong, obs.depth, other, truth)
    assert moved["floor_difference"]["observation"]["mean"] < 0
    assert moved["floor_difference"]["true_mesh"]["mean"] > 0
    assert moved["whose"] == "reconstruction"


def test_whose_miss_trusts_a_side_only_where_each_floor_stayed_in_its_basin():
    """A side prefers the truth's basin where the truth's floor is significantly the deeper,
    or where the answer's polish left its basin for the truth's (a slope, no valley, there),
    and never where the truth's polish slid into the answer's; the verdicts follow."""
    from benchmarks.bench_pipeline import whose_miss

    def diff(obs: float, mesh: float, se: float = 0.001) -> dict:
        return {"observation": {"mean": obs, "se": se}, "true_mesh": {"mean": mesh, "se": se}}

    def left(**sides: str) -> dict:
        return {s: {"answer": "answer" in w, "truth": "truth" in w} for s, w in sides.items()}

    assert whose_miss(diff(0.004, 0.02)) == "optimiser"
    mesh_only = {"true_mesh": {"mean": 0.02, "se": 0.001}}
    assert whose_miss(mesh_only) == "optimiser"
    assert whose_miss({"true_mesh": {"mean": -0.02, "se": 0.001}}) == "loss"
    # the answer's polish left for the truth's basin: the true mesh prefers the truth's
    flags = {"true_mesh": {"answer": True, "truth": False}}
    assert whose_miss({"true_mesh": {"mean": -0.001, "se": 0.001}}, flags) == "optimiser"
    assert whose_miss(diff(-0.006, 0.02)) == "reconstruction"
    assert whose_miss(diff(-0.006, -0.005)) == "loss"
    assert whose_miss(diff(0.001, 0.001)) == "loss"  # within two standard errors
    # a 1.1 m canopy: on the true mesh the answer's polish went to the truth's leaf size and
    # ended a little below the truth's floor; on the observation the truth's slid to the answer
    c = left(observation="truth", true_mesh="answer")
    assert whose_miss(diff(-0.0065, -0.005), c) == "reconstruction"
    assert whose_miss(diff(0.004, 0.02), left(observation="truth")) == "reconstruction"
    assert whose_miss(diff(-0.006, -0.005), left(observation="answer")) == "optimiser"
    # both or neither left: the floors' losses decide
    assert whose_miss(diff(0.004, 0.02), left(observation="answer truth")) == "optimiser"
    assert whose_miss(diff(-0.006, -0.005), left(true_mesh="")) == "loss"


def test_bo_fit_recovers_maize_parameters():
    """A quick-budget BO fit recovers a maize canopy's LAI and node count."""
    truth = {
        "leaf_length": 1.1,
        "leaf_order_shift": 1.0,
        "internode_length": 0.9,
        "num_nodes": 12.0,
    }
    obs, canopy = observation("maize", truth)
    cfg = FitConfig(n_seeds=2, n_evals=60, n_initial=25)
    res = fit_observation(obs, cfg)
    assert set(res.params) == set(truth) and len(res.seed_params) == 2
    fitted = generate_canopy("maize", res.params, default_layout("maize"), seed=11)
    m_true = canopy_metrics(canopy, gap_fraction=False)
    m_fit = canopy_metrics(fitted, gap_fraction=False)
    assert abs(m_fit["lai"] - m_true["lai"]) / m_true["lai"] < 0.35
    assert abs(m_fit["node_count"] - m_true["node_count"]) <= 3


def test_closing_local_search_refines_a_soybean_seed_from_its_lowest_point():
    """With ``local_share`` the last evaluations of a seed are a simplex search started at the
    GP phase's lowest point on the seed's own objective, and go further down from there."""
    truth = {
        "leaf_length": 1.0,
        "petiole_length": 1.2,
        "petiole_angle": 2.0,
        "internode_length": 1.0,
        "num_nodes": 6.5,
    }
    obs, _ = observation("soybean", truth)
    base = {"n_evals": 50, "n_initial": 20}
    plain = fit_seed(obs, 3, FitConfig(**base))
    local = fit_seed(obs, 3, FitConfig(**base, local_share=0.3))
    assert local.n_evals <= 50 and local.config["local_evals"] == 15
    np.testing.assert_array_equal(local.X[:35], plain.X[:35])  # the same design and GP steps
    assert local.y[35:].min() < local.y[:35].min()  # it went further down
    # the search stays around the point it started from (5 % simplex in the unit cube)
    start = local.X[:35][np.argmin(local.y[:35])]
    span = np.ptp(bounds("soybean"), axis=1)
    assert np.all(np.abs(local.X[35:] - start) / span < 0.5)


def test_resume_after_interrupt_equals_uninterrupted(tmp_path):
    obs, _ = observation("soybean", {"num_nodes": 6.0})
    cfg = FitConfig(n_seeds=1, n_evals=30, n_initial=12)
    clean = fit_seed(obs, 3, cfg)

    class Killed(Exception):
        pass

    def kill_at_20(i, x, y):
        if i == 20:
            raise Killed

    ck = tmp_path / "seed-3.json"
    with pytest.raises(Killed):
        fit_seed(obs, 3, cfg, checkpoint=ck, callback=kill_at_20)
    assert ck.exists()
    # the kill came after evaluation 20 was stored: the checkpoint holds 21 evaluations
    assert SeedResult.load(ck).n_evals == 21
    seen = []
    resumed = fit_seed(obs, 3, cfg, checkpoint=ck, callback=lambda i, x, y: seen.append(i))
    assert seen == list(range(21, 30))  # only the missing evaluations were run again
    assert np.array_equal(resumed.X, clean.X) and np.array_equal(resumed.y, clean.y)
    assert np.array_equal(resumed.reported_x, clean.reported_x)


@pytest.mark.parametrize("method", ["bo", "random"])
def test_a_checkpoint_of_another_objective_is_refused(tmp_path, method):
    """A seed's checkpoint records the identity of its objective (observation, fit settings,
    box with its fixed values): resumed against another observation it mixed two fits' losses,
    and a finished one came back for changed settings; now it is refused by name."""
    obs, _ = observation("soybean", {"num_nodes": 6.0})
    other, _ = observation("soybean", {"num_nodes": 9.0})
    cfg = FitConfig(method=method, n_seeds=1, n_evals=8, n_initial=4)
    ck = tmp_path / "seed-0.json"
    done = fit_seed(obs, 0, cfg, checkpoint=ck)
    assert np.array_equal(fit_seed(obs, 0, cfg, checkpoint=ck).y, done.y)  # its own: served
    for o, c in (
        (other, cfg),
        (obs, replace(cfg, canopies_per_eval=3)),
        (obs, replace(cfg, common_random_numbers=False)),
        (obs, replace(cfg, box={"num_nodes": 9.0})),
        (obs, replace(cfg, box={"num_nodes": 14.0})),
    ):
        with pytest.raises(ConfigError, match="belongs to another run"):
            fit_seed(o, 0, c, checkpoint=ck)


def test_seeds_of_another_box_or_with_non_finite_answers_are_not_combined():
    """Seeds fitted in a box of the same size but other bounds were clipped into the new one
    and misreported; a seed whose loss is NaN (a damaged stored result) was picked as the
    trust-region's best."""
    obs, _ = observation("maize", {"num_nodes": 9.0})
    cfg = FitConfig(n_seeds=2, n_evals=8, n_initial=4, combine="median")
    seeds = [fit_seed(obs, s, cfg) for s in range(2)]
    narrow = replace(cfg, box={"leaf_length": [1.0, 1.15]})
    with pytest.raises(ConfigError, match="fitted under another parameter box"):
        combine("maize", seeds, narrow, 1.0)
    seeds[0] = replace(seeds[0], best_y=float("nan"))
    with pytest.raises(InputError, match=r"seed result\(s\) \[0\] hold a non-finite loss"):
        combine("maize", seeds, replace(cfg, method="trust-region"), 1.0)


def test_trust_regions_answer_reports_the_seeds_spread_not_zero():
    """Trust-region answers its lowest-loss seed, and its ``params_std`` read 0 whatever the
    seeds' spread: the report's "SD over seeds" said 0 beside a range of 0.14."""
    obs, _ = observation("maize", {"num_nodes": 9.0})
    cfg = FitConfig(n_seeds=3, n_evals=8, n_initial=4, method="random")
    seeds = [fit_seed(obs, s, cfg) for s in range(3)]
    fit = combine("maize", seeds, replace(cfg, method="trust-region"), 1.0)
    best = seeds[int(np.argmin([r.best_y for r in seeds]))]
    assert list(fit.params.values()) == pytest.approx(list(best.reported_x))
    spread = np.std([r.reported_x for r in seeds], axis=0, ddof=1)
    assert list(fit.params_std.values()) == pytest.approx(list(spread))
    assert spread.max() > 0


@pytest.mark.parametrize("method", ["random", "trust-region"])
def test_baselines_run_end_to_end(method):
    obs, _ = observation("maize", {"num_nodes": 9.0})
    res = fit_observation(obs, FitConfig(method=method, n_seeds=2, n_evals=12, n_initial=4))
    assert res.method == method and len(res.seed_losses) == 2
    for name, value in res.params.items():
        assert np.isfinite(value), name


def test_fit_seeds_in_worker_processes_give_the_in_process_fit():
    """``cropcraft fit --workers``: the seeds spread over spawned single-threaded processes
    give the fit that running them here does, seed by seed."""
    from cropcraft_core.parallel import processes

    obs, _ = observation("maize", {"num_nodes": 9.0})
    cfg = FitConfig(n_seeds=3, n_evals=16, n_initial=8, combine="median")
    here = fit_observation(obs, cfg)
    with processes(2) as ex:
        there = fit_observation(obs, cfg, executor=ex)
    assert there.seed_losses == here.seed_losses and len(set(here.seed_losses)) == 3
    assert there.seed_params == here.seed_params
    assert there.params == here.params


def test_rows_fitted_together_give_each_rows_own_fit():
    """``cropcraft fit --neighbour-rows``: every row's seeds in one map over the processes and
    every row's re-scoring in another give each row the answer its own fit gives, in order."""
    from cropcraft_core.fit import fit_observations
    from cropcraft_core.parallel import processes

    rows = [observation("maize", {"num_nodes": n}, seed=s)[0] for n, s in ((9.0, 11), (12.0, 5))]
    cfg = FitConfig(
        n_seeds=2,
        n_evals=14,
        n_initial=8,
        combine="reevaluate",
        reevaluate_canopies=2,
        polish_evals=4,
    )
    alone = [fit_observation(o, cfg) for o in rows]
    with processes(2) as ex:
        together = fit_observations(rows, cfg, executor=ex)
    assert [r.params for r in together] == [r.params for r in alone]
    assert [r.seed_losses for r in together] == [r.seed_losses for r in alone]
    assert together[0].params != together[1].params
    for a, b in zip(alone, together, strict=True):
        sa, sb = a.extra["selection"], b.extra["selection"]
        assert (sa["chosen"], sa["candidates"]) == (sb["chosen"], sb["candidates"])


def test_mlp_baseline_trains_caches_and_predicts(tmp_path, monkeypatch):
    monkeypatch.setenv("CROPCRAFT_CACHE", str(tmp_path))
    obs, _ = observation("maize", {"num_nodes": 9.0})
    cfg = MLPConfig(n_pairs=24, epochs=3, batch_size=8)
    monkeypatch.setattr(
        "cropcraft_core.fit.mlp.preset", lambda crop, **kw: preset(crop, **{**SMALL, **kw})
    )
    p1 = predict_params(obs, cfg)
    cached = list((tmp_path / "mlp").glob("maize-*.pt"))
    assert len(cached) == 1
    p2 = predict_params(obs, cfg)  # from the cache: same network, same answer
    assert p1 == p2
    cached[0].write_bytes(cached[0].read_bytes()[:100])  # truncated: trained again, named
    with pytest.warns(UserWarning, match=r"cached MLP .*maize-.*\.pt cannot be read"):
        assert predict_params(obs, cfg) == p1
    assert [p.name for p in (tmp_path / "mlp").iterdir()] == [cached[0].name]  # no temporaries
    assert predict_params(obs, cfg) == p1
    # the network reads an observation as its training pairs were made: the paper's bins,
    # whatever the observation's own (maize's default fits its depth bins to the canopy), and
    # for maize no derivative histogram (zeros in training; an observation computes one for
    # its reports)
    paper = observe_canopy(
        generate_canopy("maize", {"num_nodes": 9.0}, default_layout("maize"), seed=11),
        preset("maize", **{**SMALL, "depth_top_margin": None}),
    )
    assert paper.stats.spec != obs.stats.spec and obs.stats.sobel.any()
    x = observation_features(obs)
    np.testing.assert_array_equal(x, observation_features(paper))
    assert not x[20:30].any()  # 10 depth, 10 lateral, then the 10 derivative bins
    np.testing.assert_allclose(x[:20], np.r_[paper.stats.depth, paper.stats.lateral], rtol=1e-6)
    assert predict_params(paper, cfg) == p1
    # maize's pairs are all rendered at 5 m: a camera raised over a tall canopy (5.1 m) is an
    # input the network never saw vary, read as its training value, not as 0.1 / 1e-6 spreads
    # that put every parameter on a bound of the box
    _, canopy = observation("maize", {"num_nodes": 9.0})
    raised = observe_canopy(canopy, preset("maize", **{**SMALL, "render_height": 5.1}))
    p3 = np.array(list(predict_params(raised, cfg).values()))
    b = bounds("maize")
    assert np.all((p3 > b[:, 0]) & (p3 < b[:, 1])), p3


def test_mlp_baseline_reads_the_node_count_of_canopies_it_never_saw(tmp_path, monkeypatch):
    """Trained on 120 pairs for 40 epochs (5 s), the network tells a 4-node maize canopy from
    a 15-node one, each within a node and a half (it read 4.5-4.6 and 15.1 when written) on two
    draws of each: the prediction is the network's, not just inside the box its sigmoid maps
    into (which every output is)."""
    monkeypatch.setenv("CROPCRAFT_CACHE", str(tmp_path))
    monkeypatch.setattr(
        "cropcraft_core.fit.mlp.preset", lambda crop, **kw: preset(crop, **{**SMALL, **kw})
    )
    cfg = MLPConfig(n_pairs=120, epochs=40, batch_size=16)
    for nodes in (4.0, 15.0):
        for seed in (11, 12):
            obs, _ = observation("maize", {"num_nodes": nodes}, seed=seed)
            assert predict_params(obs, cfg)["num_nodes"] == pytest.approx(nodes, abs=1.5)


def test_mlp_training_pairs_are_the_same_made_in_worker_processes(monkeypatch):
    """The pairs are drawn first and made in jobs, so a process pool (spawned workers, as the
    benchmarks' ``--workers``) gives exactly the in-process pairs, in order."""
    from cropcraft_core.parallel import processes

    monkeypatch.setattr("cropcraft_core.fit.mlp.PAIRS_PER_JOB", 2)
    cfg = MLPConfig(n_pairs=7)  # soybean: 4 at each render height (1.0, 1.25 m), 7 kept
    x, y = training_pairs("soybean", cfg)
    made = []
    with processes(2) as ex:
        xp, yp = training_pairs("soybean", cfg, executor=ex, progress=made.append)
    np.testing.assert_array_equal(xp, x)
    np.testing.assert_array_equal(yp, y)
    assert x.shape == (7, 42) and y.shape == (7, 5) and made == [2, 4, 6, 8]
    # the render height is the feature before the mask area: four pairs at 1 m, three higher
    assert x[:, -2].tolist() == [1.0] * 4 + [1.25] * 3
    assert len({row.tobytes() for row in x}) == 7


def test_bad_fit_config():
    with pytest.raises(ConfigError, match="unknown method"):
        FitConfig(method="adam").validate()
    with pytest.raises(ConfigError, match="n_initial"):
        FitConfig(n_evals=10, n_initial=20).validate()
    # BO's initial design is no bound on the baselines, which never read it
    FitConfig(method="random", n_evals=100).validate()
    FitConfig(method="trust-region", n_evals=50).validate()
    with pytest.raises(ConfigError, match="n_evals"):
        FitConfig(method="random", n_evals=1).validate()
    with pytest.raises(ConfigError, match="local_share"):
        FitConfig(local_share=1.5).validate()
    with pytest.raises(ConfigError, match="gp_output"):
        FitConfig(gp_output="sqrt").validate()


def test_local_share_is_a_share_of_the_seed_budget_capped_after_the_design():
    """The closing local search scales with the budget, so a reduced budget stays valid."""
    assert FitConfig(local_share=0.2).local_evals("soybean") == 100
    assert FitConfig(local_share=0.2, n_evals=60, n_initial=25).local_evals("soybean") == 12
    assert FitConfig(local_share=1.0, n_evals=60, n_initial=25).local_evals("maize") == 35
    cfg = FitConfig(local_share=0.2, gp_output="log").bo_config("soybean").validate()
    assert (cfg.local_evals, cfg.output_transform) == (100, "log")


def test_resolved_writes_out_the_crop_defaults_and_keeps_what_was_given():
    """One place reads the crop defaults; what a user set is never replaced."""
    from cropcraft_core.fit.fitting import (
        DEFAULT_CANOPIES,
        DEFAULT_COMBINE,
        DEFAULT_GP_OUTPUT,
        DEFAULT_LOCAL_SHARE,
    )

    for crop in ("soybean", "maize"):
        r = FitConfig().resolved(crop)
        assert (r.combine, r.canopies_per_eval, r.local_share, r.gp_output) == (
            DEFAULT_COMBINE[crop],
            DEFAULT_CANOPIES[crop],
            DEFAULT_LOCAL_SHARE[crop],
            DEFAULT_GP_OUTPUT[crop],
        )
        mine = {"combine": "mean", "canopies_per_eval": 3, "local_share": 0.0, "n_evals": 80}
        for gp in ("none", "log"):
            assert FitConfig(**mine, gp_output=gp).resolved(crop) == FitConfig(**mine, gp_output=gp)
        # the unbiased estimator can go negative: its default GP models the loss itself
        unbiased = FitConfig(loss_estimator="unbiased", canopies_per_eval=2)
        assert unbiased.resolved(crop).gp_output == "none"
        assert unbiased.validate().bo_config(crop).validate().output_transform == "none"
        assert FitConfig().bo_config(crop).output_transform == DEFAULT_GP_OUTPUT[crop]
        # the baselines have no GP: their fits are the paper's whatever the GP settings say
        assert FitConfig(method="random", gp_output="log").papers_optimiser(crop)
        assert not FitConfig(gp_output="log").papers_optimiser(crop)
    assert FitConfig().resolved("soybean").resolved("soybean") == FitConfig().resolved("soybean")


def test_soybean_with_its_node_count_given_takes_the_mean_of_the_seeds():
    """A counted node number (a value, not a range) switches soybean's default answer rule to
    the mean; a range, maize, or a rule the user set do not."""
    assert FitConfig(box={"num_nodes": 9}).combine_rule("soybean") == "mean"
    assert FitConfig(box={"num_nodes": [6, 9]}).combine_rule("soybean") == "guarded"
    assert FitConfig(box={"leaf_length": 1.0}).combine_rule("soybean") == "guarded"
    assert FitConfig(box={"num_nodes": 12}).combine_rule("maize") == "reevaluate"
    assert FitConfig(box={"num_nodes": 9}, combine="median").combine_rule("soybean") == "median"


def test_accuracy_bench_with_changed_loss_weights_keeps_its_own_checkpoints(tmp_path):
    """``bench accuracy --preset lambda_lateral=...`` fits observations with those weights,
    records them, and keeps its seeds apart from the default weights' checkpoints."""
    import json

    from benchmarks.bench_accuracy import _parse_preset, run

    budget = {"n_seeds": 1, "n_evals": 6, "n_initial": 3, "reevaluate_canopies": 2}
    kw = {"overrides": {**budget, "polish_evals": 4}, "checkpoint_dir": tmp_path, "log": print}
    a = run("maize", ["bo"], True, 1, **kw)
    weights = _parse_preset("maize", ["lambda_lateral=0.25"])
    b = run("maize", ["bo"], True, 1, preset_overrides=weights, **kw)
    names = sorted(p.name for p in tmp_path.glob("*-seed*.json"))
    assert len(names) == 2 and sum("-p" in n for n in names) == 1
    # the same optimiser seed draws the same first points; the loss on them is another one
    plain, weighted = (json.loads((tmp_path / n).read_text()) for n in sorted(names, key=len))
    assert np.allclose(plain["X"][:3], weighted["X"][:3])
    assert not np.allclose(plain["y"][:3], weighted["y"][:3])
    assert a["preset_overrides"] == {} and b["preset_overrides"] == {"lambda_lateral": 0.25}
    assert a["truths"] == b["truths"]
    with pytest.raises(SystemExit, match="unknown maize preset setting 'lambda_lateal'"):
        _parse_preset("maize", ["lambda_lateal=0.25"])
    with pytest.raises(SystemExit, match="KEY=VALUE"):
        _parse_preset("maize", ["lambda_lateral"])


def test_accuracy_bench_gives_known_parameters_their_true_value_in_checkpoints_of_their_own(
    tmp_path,
):
    """``bench accuracy --known num_nodes``: every row's answer carries the scene's true node
    count and the seeds search the other parameters, apart from the plain run's checkpoints."""
    import json

    from benchmarks.bench_accuracy import run

    budget = {"n_seeds": 1, "n_evals": 6, "n_initial": 3, "reevaluate_canopies": 2}
    kw = {"overrides": {**budget, "polish_evals": 4}, "checkpoint_dir": tmp_path, "log": print}
    plain = run("maize", ["bo"], True, 1, **kw)
    known = run("maize", ["bo"], True, 1, known=("num_nodes",), **kw)
    names = sorted(p.name for p in tmp_path.glob("*-seed*.json"))
    assert len(names) == 2 and sum("-known-num_nodes-" in n for n in names) == 1
    true_nodes = known["truths"][0]["params"]["num_nodes"]
    for row, r in known["methods"].items():
        assert r["predictions"][0]["params"]["num_nodes"] == true_nodes, row
    assert plain["truths"] == known["truths"] and known["known"] == ["num_nodes"]
    ck = json.loads((tmp_path / next(n for n in names if "-known-" in n)).read_text())
    assert np.asarray(ck["X"]).shape == (6, 3)


def test_accuracy_bench_redraws_the_true_canopies_at_the_same_parameters(tmp_path):
    """``bench accuracy --draw 1``: every scene keeps its true parameters, its true canopy is
    another random draw (another LAI, another observation), the fitted canopies are measured on
    that draw's seed, and its seeds checkpoint apart from the table's."""
    from benchmarks.bench_accuracy import DRAW_STRIDE, canopy_seed, run

    budget = {"n_seeds": 1, "n_evals": 6, "n_initial": 3, "reevaluate_canopies": 2}
    kw = {"overrides": {**budget, "polish_evals": 4}, "checkpoint_dir": tmp_path, "log": print}
    table = run("soybean", ["bo"], True, 1, **kw)
    drawn = run("soybean", ["bo"], True, 1, draw=1, **kw)
    names = sorted(p.name for p in tmp_path.glob("*-seed*.json"))
    assert len(names) == 2 and sum("-draw1-" in n for n in names) == 1
    t0, t1 = table["truths"][0], drawn["truths"][0]
    assert t0["params"] == t1["params"] and t0["lai"] != t1["lai"]
    assert (table["draw"], drawn["draw"]) == (0, 1)
    assert canopy_seed(3, 2) == canopy_seed(3) + 2 * DRAW_STRIDE
    with pytest.raises(ConfigError, match="draw -1"):
        canopy_seed(3, -1)


def test_accuracy_bench_combines_scenes_in_its_worker_processes_as_it_would_in_process(tmp_path):
    """With ``--workers`` each scene's answers (re-scoring and polish included) are combined in
    the worker processes as soon as its seeds are in; the answers are the ones the in-process
    run gives from the same seeds (here resumed from the workers' finished checkpoints)."""
    from benchmarks.bench_accuracy import run

    budget = {"n_seeds": 2, "n_evals": 6, "n_initial": 3, "reevaluate_canopies": 2}
    kw = {"overrides": {**budget, "polish_evals": 4}, "checkpoint_dir": tmp_path, "log": print}
    pooled = run("maize", ["bo"], True, 2, workers=2, **kw)
    shutil.rmtree(tmp_path / "answers")  # combine in this process, not read the pool's answers
    local = run("maize", ["bo"], True, 2, workers=1, **kw)
    assert len(list(tmp_path.glob("*-seed*.json"))) == 4
    rows = ["bo", "bo-median", "bo-mean", "bo-guarded", "bo-unpolished"]
    assert list(pooled["methods"]) == list(local["methods"]) == rows
    for row in rows:
        got = [p["params"] for p in pooled["methods"][row]["predictions"]]
        assert got == [p["params"] for p in local["methods"][row]["predictions"]], row
        assert pooled["methods"][row]["errors"] == local["methods"][row]["errors"], row
    # the unpolished row is read from the polished selection (tests/test_select.py checks it is
    # the plain re-scoring's answer): its time is the seeds' plus the re-scoring, not the polish
    sec = {row: pooled["methods"][row]["seconds_per_scene"] for row in rows}
    assert sec["bo-median"] < sec["bo-unpolished"] < sec["bo"]


def test_accuracy_bench_diagnoses_a_miss_by_scoring_the_answer_against_the_truth():
    """``--diagnose K``: a scene whose LAI misses by more than 15 % is scored at its answer and
    at its truth on the same K fresh canopies; an answer far from a truth that scores lower is
    the optimiser's miss, the truth itself as the answer ties (the loss's, exactly zero apart);
    a scene within 15 % is scored only where it is among the misses that carry most of LAIE,
    each verdict's share of the squared LAI error is its scenes' part, and the bench's worker
    processes score alike."""
    from benchmarks.bench_accuracy import diagnose, diagnose_misses, run, scene_observation
    from cropcraft_core.parallel import processes

    truth, obs = scene_observation("maize", 0, 0.25)
    same = diagnose(obs, truth["params"], truth["params"], 3)
    assert same["difference"] == {"mean": 0.0, "se": 0.0} and same["whose"] == "loss"
    assert same["answer_loss"] == same["truth_loss"] > 0
    far = {**truth["params"], "leaf_length": 0.8, "num_nodes": 2.0}
    miss = diagnose(obs, far, truth["params"], 3)
    assert miss["truth_loss"] == same["truth_loss"]  # the same fresh canopies
    assert miss["answer_loss"] > 5 * miss["truth_loss"] and miss["whose"] == "optimiser"

    # scene 7 misses by 50 %; scene 8, ten times denser, by only 10 % but carries 79 % of the
    # squared LAI error (scored too); scene 9's 10 % of a sparse canopy is left alone
    lai = truth["lai"]
    truths = [truth, {**truth, "lai": 10 * lai}, truth]
    predictions = [
        {"params": far, "lai": 0.5 * lai},
        {"params": truth["params"], "lai": 11 * lai},
        {"params": far, "lai": 1.1 * lai},
    ]
    obs3 = [obs, obs, obs]
    got = diagnose_misses(obs3, predictions, truths, [7, 8, 9], 3, log=print)
    assert list(got["scenes"]) == [7, 8] and got["canopies"] == 3
    assert got["scenes"][7] == miss and got["scenes"][8] == same
    share = got["share_of_lai_sq_error"]
    assert share == pytest.approx({"optimiser": 0.25 / 1.26, "loss": 1 / 1.26})
    with processes(2, {"observations": obs3}) as ex:  # as the bench's workers score them
        assert diagnose_misses(obs3, predictions, truths, [7, 8, 9], 3, ex) == got
    with pytest.raises(ConfigError, match="--diagnose takes 2 canopies or more, got 1"):
        run("maize", ["bo"], True, 1, diagnose=1)


def test_accuracy_bench_keeps_each_scenes_answers_and_scores_the_finished_scenes_alone(tmp_path):
    """With ``--checkpoint-dir`` a scene's answers under every row are kept beside its seeds, so
    a resumed run reads them instead of combining again (the same table); ``--first`` runs the
    later scenes alone; ``--finished-only``
    fits nothing and scores just the scenes whose seeds are all finished, by their own numbers
    (their canopy seeds), as the whole run scored them."""
    from benchmarks.bench_accuracy import run

    budget = {"n_seeds": 2, "n_evals": 6, "n_initial": 3, "reevaluate_canopies": 2}
    kw = {"overrides": {**budget, "polish_evals": 4}, "checkpoint_dir": tmp_path}
    logs: list[str] = []
    first = run("maize", ["bo"], True, 2, log=logs.append, **kw)
    kept = sorted((tmp_path / "answers").glob("*.json"))
    assert [p.name.split("-scene")[1].split("-")[0] for p in kept] == ["0", "1"]
    assert not any("answers read" in line for line in logs)

    logs.clear()
    again = run("maize", ["bo"], True, 2, log=logs.append, **kw)
    assert sum("answers read" in line for line in logs) == 2
    assert again["methods"] == first["methods"]
    assert first["scene_indices"] == again["scene_indices"] == [0, 1]

    # --first 1: scene 1 alone, by its own number (its truth, its kept seeds and answers), as
    # the whole run scored it, so the parts of a run split over sessions join
    logs.clear()
    tail = run("maize", ["bo"], True, 2, log=logs.append, first=1, **kw)
    assert tail["scene_indices"] == [1] and tail["truths"] == first["truths"][1:]
    assert sum("answers read" in line for line in logs) == 1
    for row, r in tail["methods"].items():
        assert r["predictions"] == first["methods"][row]["predictions"][1:], row
    with pytest.raises(ConfigError, match="--first 2 is not one of the 2 scenes"):
        run("maize", ["bo"], True, 2, first=2, **kw)
    # --only 1: the same scene by its number, as --first 1 gave it; a number past the run's
    # scenes is named
    only = run("maize", ["bo"], True, 2, only=(1,), **kw)
    assert only["scene_indices"] == [1] and only["methods"] == tail["methods"]
    with pytest.raises(ConfigError, match="--only 5 is not one of scenes 0..1"):
        run("maize", ["bo"], True, 2, only=(1, 5), **kw)

    # the kept answers are named by the seeds too: seeds that came out otherwise are not theirs
    from dataclasses import replace

    from benchmarks.bench_accuracy import _answers_path, _Scenes, rules, scene_observation

    scenes = _Scenes([scene_observation("maize", 0, 0.25)[1]], [{}], checkpoint_dir=tmp_path)
    seeds = [SeedResult.load(p) for p in sorted(tmp_path.glob("*-scene0-seed*.json"))]
    cfg = FitConfig(**{**FitConfig().to_dict(), **budget, "polish_evals": 4})
    rows = rules("maize", "bo", cfg)
    stem = kept[0].name.rsplit("-", 1)[0]
    assert _answers_path(scenes, stem, "maize", rows, seeds) == kept[0]
    other = [seeds[0], replace(seeds[1], best_y=seeds[1].best_y * 2)]
    assert _answers_path(scenes, stem, "maize", rows, other) != kept[0]

    # scene 0 loses a seed: only scene 1 is finished, and nothing is fitted to finish scene 0
    next(tmp_path.glob("*-scene0-seed1.json")).unlink()
    part = run("maize", ["bo"], True, 2, log=print, finished_only=True, **kw)
    assert part["scene_indices"] == [1] and part["scenes"] == 1
    assert not list(tmp_path.glob("*-scene0-seed1.json"))
    for row, r in part["methods"].items():
        assert r["predictions"] == first["methods"][row]["predictions"][1:], row
    assert part["truths"] == first["truths"][1:]

    next(tmp_path.glob("*-scene1-seed0.json")).write_text('{"complete": false}')
    with pytest.raises(ConfigError, match="no scene has all its seeds finished in"):
        run("maize", ["bo"], True, 2, log=print, finished_only=True, **kw)
    with pytest.raises(ConfigError, match="--finished-only reads the seeds in --checkpoint-dir"):
        run("maize", ["bo"], True, 2, finished_only=True, overrides=kw["overrides"])


def test_known_parameters_are_fixed_and_the_rest_searched_inside_their_box():
    """``FitConfig.box``: a known value is not fitted (every evaluation and the answer carry
    it, its spread is 0); a narrowed range bounds every evaluation; the re-scored answer
    (maize's default) and its polish stay in the box."""
    truth = {"leaf_length": 1.1, "leaf_order_shift": 1.0, "internode_length": 0.9, "num_nodes": 12}
    obs, _ = observation("maize", truth)
    box = {"num_nodes": 12, "leaf_length": [1.0, 1.15]}
    cfg = FitConfig(n_seeds=2, n_evals=24, n_initial=10, box=box, reevaluate_canopies=2)
    cfg = FitConfig(**{**cfg.to_dict(), "polish_evals": 8})
    seed = fit_seed(obs, 0, cfg)
    assert seed.X.shape == (24, 3)  # leaf_length, leaf_order_shift, internode_length
    assert np.all((seed.X[:, 0] >= 1.0) & (seed.X[:, 0] <= 1.15))
    res = fit_observation(obs, cfg)
    assert res.params["num_nodes"] == 12.0 and res.params_std["num_nodes"] == 0.0
    assert all(p["num_nodes"] == 12.0 for p in res.seed_params)
    assert 1.0 <= res.params["leaf_length"] <= 1.15
    cands = res.extra["selection"]["candidates"]
    assert any(k.startswith("polished-") for k in cands)
    assert all(c["params"]["num_nodes"] == 12.0 for c in cands.values())
    # seeds fitted under another box are not combined with this one's
    whole = fit_seed(obs, 1, FitConfig(n_evals=12, n_initial=6))
    with pytest.raises(ConfigError, match="another parameter box"):
        combine("maize", [seed, whole], cfg, 0.0, obs)


@pytest.mark.parametrize("method", ["random", "trust-region"])
def test_baselines_keep_known_parameters(method):
    obs, _ = observation("soybean", SOY_TRUTH)
    cfg = FitConfig(method=method, n_seeds=1, n_evals=8, n_initial=4, box={"num_nodes": 8})
    res = fit_observation(obs, cfg)
    assert res.params["num_nodes"] == 8.0 and len(res.params) == 5


def test_bad_parameter_box_is_named():
    with pytest.raises(ConfigError, match="unknown soybean parameter 'nodes'"):
        FitConfig(box={"nodes": 9}).param_box("soybean")
    with pytest.raises(ConfigError, match=r"outside the model's range \[1, 14\]"):
        FitConfig(box={"num_nodes": 20}).param_box("soybean")
    with pytest.raises(ConfigError, match="low 1.2 is above high 0.9"):
        ParamBox.of("maize", {"leaf_length": [1.2, 0.9]})
    with pytest.raises(ConfigError, match="not a number"):
        ParamBox.of("maize", {"leaf_length": "long"})
    with pytest.raises(ConfigError, match="not a finite number"):
        ParamBox.of("maize", {"leaf_length": True})
    with pytest.raises(ConfigError, match="nothing is left to fit"):
        ParamBox.of(
            "maize",
            {n: 1.0 for n in ("leaf_length", "internode_length")}
            | {"leaf_order_shift": 0.0, "num_nodes": 9},
        )
    with pytest.raises(ConfigError, match="box must map"):
        FitConfig(box=[("num_nodes", 9)]).validate()
    whole = ParamBox.of("soybean")
    assert whole.is_full and whole.names == tuple(s.name for s in param_space("soybean"))
    assert not ParamBox.of("soybean", {"num_nodes": [2, 14]}).is_full


def test_pipeline_bench_combines_one_fits_seeds_by_every_rule(tmp_path):
    """``bench pipeline --fit`` answers by every combination rule from the same seeds: the
    crop's default (soybean: the guarded median) as ``bo``, the median, the mean, the
    re-scoring with and without its polish; a rerun resumes every seed from its checkpoint and
    answers the same."""
    from benchmarks.bench_pipeline import fit_rules

    obs, _ = observation("soybean", SOY_TRUTH)
    small = {"reevaluate_canopies": 2, "polish_evals": 4}  # the re-scoring at a test's size
    answers, spread = fit_rules(obs, "3x10", tmp_path / "seeds", **small)
    assert set(answers) == {
        "bo",
        "bo-median",
        "bo-mean",
        "bo-reevaluate",
        "bo-reevaluate-unpolished",
    }
    # the guard answers the median or re-scoring's polished winner
    assert answers["bo"] in (answers["bo-median"], answers["bo-reevaluate"])
    seeds = [s["params"] for s in spread["seeds"]]
    assert [s["seed"] for s in spread["seeds"]] == [0, 1, 2]
    for k in SOY_TRUTH:
        vals = [p[k] for p in seeds]
        assert answers["bo-median"][k] == pytest.approx(np.median(vals))
        assert answers["bo-mean"][k] == pytest.approx(np.mean(vals))
        assert spread["params_std"][k] == pytest.approx(np.std(vals, ddof=1))
    assert sorted(p.name for p in (tmp_path / "seeds").iterdir()) == [
        f"seed-{s}.json" for s in range(3)
    ]
    again, spread_again = fit_rules(obs, "3x10", tmp_path / "seeds", **small)
    assert again == answers and spread_again == spread


@pytest.mark.parametrize("crop", ["soybean", "maize"])
def test_true_mesh_observation_is_the_attributions_perfect_reconstruction(crop):
    """``bench pipeline --fit-true-mesh`` fits the true mesh's depth seen by the observation's
    camera: the same camera, preset and depth bins (maize's resolved over the observation's
    canopy), the mask rules of the observation's box, and statistics identical to the ones the
    whose-miss attribution scores as the true mesh (``truth_stats``)."""
    from benchmarks.bench_pipeline import true_mesh_observation, truth_stats
    from cropcraft_core.observe import Observation, loss
    from cropcraft_core.observe.observation import predicted_mask

    truth = resolve_params(crop)  # the middle of every range
    seen, _ = observation(crop, truth)
    other = {**truth, "leaf_length": 0.8 * truth["leaf_length"]}
    wrong, _ = observation(crop, other, seed=5)  # a reconstruction of some other canopy
    boxed = Observation(
        crop,
        wrong.camera,
        wrong.depth,
        predicted_mask(wrong.depth, wrong.camera, wrong.preset),
        preset=wrong.preset,
        box_mask=True,
    )
    for obs in (wrong, boxed):
        perfect = true_mesh_observation(obs, seen.depth)
        assert perfect.camera is obs.camera and perfect.preset == obs.preset
        assert perfect.box_mask == obs.box_mask
        scored = truth_stats(obs, seen.depth)  # without the Sobel histogram where λ is 0
        for k in ("depth", "lateral", "mask_area") + (("sobel",) if scored.has_sobel else ()):
            np.testing.assert_array_equal(getattr(perfect.stats, k), getattr(scored, k))
        assert loss(perfect.stats, scored, obs.preset).total == 0.0
    # without a box the true mesh's render is its own observation
    np.testing.assert_array_equal(true_mesh_observation(wrong, seen.depth).mask, seen.mask)


def test_pipeline_bench_fits_the_true_mesh_beside_the_observation(tmp_path, capsys):
    """The perfect reconstruction's fit is an ordinary fit of the bench (its own checkpoints,
    every rule, the truth's traits) without the whose-miss attribution, and the bench asks
    for a budget before fitting it."""
    from benchmarks.bench_pipeline import fit_and_compare, main, true_mesh_observation

    obs, canopy = observation("soybean", SOY_TRUTH)
    other = {**SOY_TRUTH, "leaf_length": 0.9}
    recon, _ = observation("soybean", other, seed=5)
    root = tmp_path / "scene"
    (root / "truth").mkdir(parents=True)
    (root / "truth" / "params.json").write_text(json.dumps({"params": SOY_TRUTH}))
    metrics = canopy_metrics(canopy, gap_fraction=False)
    (root / "truth" / "metrics.json").write_text(json.dumps(metrics, default=float))
    small = {"reevaluate_canopies": 2, "polish_evals": 4}
    perfect = true_mesh_observation(recon, obs.depth)
    fit = fit_and_compare(perfect, root, "2x8", obs.depth, tmp_path / "tm", None, **small)
    assert "loss" not in fit  # the attribution asked of no side
    assert sorted(p.name for p in (tmp_path / "tm").iterdir()) == ["seed-0.json", "seed-1.json"]
    assert set(fit["rules"]) == {
        "bo-median",
        "bo-mean",
        "bo-reevaluate",
        "bo-reevaluate-unpolished",
    }
    lai = fit["traits"]["lai"]
    assert lai["true"] == pytest.approx(metrics["lai"])
    assert fit["lai_rel_err"] == pytest.approx(lai["estimated"] / lai["true"] - 1)
    with pytest.raises(SystemExit) as err:
        main(["--fit-true-mesh", "--scene-dir", str(root)])
    assert err.value.code == 2
    assert "--fit-true-mesh needs --fit" in capsys.readouterr().err


def test_rows_bench_compares_the_centre_row_with_the_rows_mean_and_resumes(tmp_path, monkeypatch):
    """bench rows: each scene fitted over its centre row and the rows either side of it; the
    rows' mean answer is the canopy of every parameter's mean over the rows' answers; a rerun
    over the same checkpoints reads each row's kept answers instead of fitting again."""
    import benchmarks.bench_pipeline as bp
    from benchmarks.bench_rows import ANSWERS, row_observation, run
    from cropcraft_core.config import default_layout
    from cropcraft_core.metrics import canopy_metrics
    from cropcraft_core.procedural import generate_canopy

    kw = dict(scenes=1, neighbours=1, scale=0.25, budget="2x8", workers=1, log=lambda *_: None)
    kw["fit_options"] = {"reevaluate_canopies": 2, "polish_evals": 4}
    res = run("soybean", first=3, checkpoint_dir=str(tmp_path), **kw)
    assert res["scenes"] == [3] and res["rows"] == [-1, 0, 1]
    assert set(res["table"]["bo"]) == set(ANSWERS)
    # the moved cameras look at other plants of the same canopy
    centre = row_observation("soybean", 3, 0, 0.25)[1]
    side = row_observation("soybean", 3, 1, 0.25)[1]
    shift = side.camera.cam_to_world[:3, 3] - centre.camera.cam_to_world[:3, 3]
    assert shift == pytest.approx([0.0, default_layout("soybean").row_spacing, 0.0])
    assert not np.array_equal(np.nan_to_num(side.depth), np.nan_to_num(centre.depth))
    answers = {
        k: json.loads(
            next(
                (tmp_path / "soybean-scale0.25" / f"scene3-row{k:+d}").glob("answers-2x8-*.json")
            ).read_text()
        )["bo"]
        for k in (-1, 0, 1)
    }
    mean = {n: float(np.mean([a[n] for a in answers.values()])) for n in answers[0]}
    lai = canopy_metrics(
        generate_canopy("soybean", mean, default_layout("soybean"), seed=100_003),
        gap_fraction=False,
    )["lai"]
    t = res["truth_lai"][0]
    assert res["table"]["bo"]["rows' mean"]["LAIPE"] == pytest.approx(abs(lai / t - 1))
    by_row = next(s for s in res["per_scene"] if s["rule"] == "bo")["lai_by_row"]
    assert res["table"]["bo"]["mean of rows' LAI"]["LAIPE"] == pytest.approx(
        abs(np.mean(list(by_row.values())) / t - 1)
    )

    def refit(*_a, **_k):
        raise AssertionError("a kept row was fitted again")

    monkeypatch.setattr(bp, "fit_rules", refit)
    again = run("soybean", first=3, checkpoint_dir=str(tmp_path), **kw)
    assert again["table"] == res["table"]
    # another image scale is another observation: fitted, not served the kept answers
    with pytest.raises(AssertionError, match="fitted again"):
        run("soybean", first=3, checkpoint_dir=str(tmp_path), **{**kw, "scale": 0.3})


def test_pipeline_bench_names_the_leaves_an_observation_lost_without_a_hole():
    """bench pipeline's cover errors: an observation the same as its truth misses nothing;
    leaf pixels that show the soil behind them count as missed deeper (no hole), empty ones as
    missed empty, and foreground where the truth has none as extra, all as shares of the
    truth's leaf pixels; one printed line."""
    from benchmarks.bench_pipeline import cover_errors, cover_line
    from cropcraft_core.observe import Observation

    sharp, _ = observation("soybean", SOY_TRUTH)
    d_true = np.where(sharp.mask, sharp.depth, np.nan)

    def observed(depth, mask):
        return Observation(
            "soybean", sharp.camera, depth, mask, preset=sharp.preset, box_mask=False
        )

    same = cover_errors(observed(d_true, sharp.mask), d_true)
    assert same["missed"] == same["extra"] == 0 and same["truth"] == same["observation"] > 0
    rows = np.zeros_like(sharp.mask)
    rows[: rows.shape[0] // 4] = True
    soil = rows & sharp.mask  # the leaves of the top quarter lost over the soil
    depth = np.where(soil, d_true + 0.3, d_true)
    empty = np.zeros_like(rows)
    empty[-rows.shape[0] // 8 :] = True
    empty &= sharp.mask  # the bottom eighth's leaves lost with nothing behind them
    depth = np.where(empty, np.nan, depth)
    ground = ~sharp.mask & np.roll(sharp.mask, 3, axis=1)  # a fattened edge beside each leaf
    depth = np.where(ground, float(np.nanmax(d_true)), depth)
    c = cover_errors(observed(depth, (sharp.mask & ~soil & ~empty) | ground), d_true)
    n = sharp.mask.sum()
    assert c["missed_deeper"] == pytest.approx(soil.sum() / n)
    assert c["missed_empty"] == pytest.approx(empty.sum() / n)
    assert c["missed"] == pytest.approx(c["missed_deeper"] + c["missed_empty"])
    assert c["extra"] == pytest.approx(ground.sum() / n) and c["extra"] > 0
    line = cover_line(c)
    assert line.startswith("  row-view cover: the observation's mask")
    assert f"{100 * c['missed_deeper']:.1f} % show a surface behind the leaf" in line


def test_pipeline_bench_measures_which_blur_of_the_truth_matches_the_observation():
    """bench pipeline's blur match: the true mesh blurred by each width against the
    observation; an observation the same as its truth matches it unblurred (0, at loss 0), one
    whose leaves were softened by 6 mm the truth blurred alike; one printed line."""
    from benchmarks.bench_pipeline import blur_match, blur_match_line
    from cropcraft_core.observe import Observation
    from cropcraft_core.observe.histograms import blur_depth

    sharp, _ = observation("soybean", SOY_TRUTH)
    d_true = np.where(sharp.mask, sharp.depth, np.nan)
    z = float(np.median(sharp.depth[sharp.mask]))
    soft = Observation(
        "soybean",
        sharp.camera,
        blur_depth(d_true, 0.006 * sharp.camera.fy / z),
        sharp.mask,
        preset=sharp.preset,
        box_mask=False,
    )
    s0 = blur_match(sharp, d_true)
    assert s0["best_m"] == 0.0 and s0["losses"][0] == 0.0
    assert s0["losses"] == sorted(s0["losses"])
    s6 = blur_match(soft, d_true)
    assert 0.0045 <= s6["best_m"] <= 0.009
    assert s6["losses"][0] > 10 * min(s6["losses"])
    line = blur_match_line(s6)
    assert line.startswith("  blur match: loss against the true mesh blurred by 0/1.5/3/4.5/6/9/12")
    assert f"closest at {1e3 * s6['best_m']:g} mm" in line


def test_an_answer_pressing_the_box_on_two_parameters_is_named():
    """A maize canopy fitted as soybean pressed three of the box's ends at once (LAI +26 %,
    leaf angles 30° off) with nothing said. Two fitted parameters within 1 % of their ends
    give a warning naming them; one does not (a true value can lie there); a given value is
    not fitted, and a narrowed range's own ends count."""
    from cropcraft_core.config import param_space
    from cropcraft_core.fit.fitting import edge_warning

    middle = {s.name: s.middle for s in param_space("soybean")}
    one = {**middle, "leaf_length": 1.4995}
    assert edge_warning("soybean", one) is None
    two = {**one, "petiole_angle": 0.5}
    msg = edge_warning("soybean", two)
    assert msg and "leaf_length 1.5 (searched 0.5 to 1.5)" in msg and "petiole_angle 0.5" in msg
    assert "is the crop right" in msg
    # num_nodes given (fixed at 14, its end): not fitted, not counted
    assert edge_warning("soybean", {**one, "num_nodes": 14.0}, {"num_nodes": 14}) is None
    # a narrowed range's end is the box's
    narrowed = {**one, "internode_length": 1.2}
    assert edge_warning("soybean", narrowed, {"internode_length": [0.8, 1.2]})
    assert edge_warning("soybean", narrowed) is None
