"""Synthetic accuracy benchmark (the paper's Table "Synthetic data evaluation").

    cropcraft bench accuracy --crop soybean [--scenes 30] [--methods bo,trust-region,random,mlp]
                             [--quick] [--crn-ablation] [--json FILE]

For each scene: true parameters drawn uniformly (seeded), the true canopy built with its own
seed, its depth rendered from the row camera as the observation (no background), a fit per
method, and the fitted canopy measured like the truth. Prints LAIE, LAIPE (and its median), AME,
ASDE, NDPE, NCPE per method beside the paper's synthetic numbers. ``--quick`` is a reduced
budget (quarter resolution, 2 seeds × 60 evaluations, 6 scenes) for smoke runs and tests.
``--crn-ablation`` adds a BO row without common random numbers; ``--preset KEY=VALUE``
changes every scene's observation preset (loss weights such as ``lambda_lateral``, bins),
with checkpoints of its own. BO's row uses the crop's
default rule for its answer (soybean: the per-parameter median of the seeds' best points;
maize: candidates re-scored on fresh canopies and the best polished, ``fit/select.py``);
``bo-mean``, ``bo-median``, ``bo-reevaluate`` are the other rules on the same seeds, and
``...-unpolished`` the re-scoring without its polish. ``--known NAME`` (repeatable) gives every
fit the scene's true value of that parameter (``FitConfig.box``), as a user who counted it in
the field would: what knowing it buys.

Every (scene, optimiser seed) pair is one job, and so is each scene's combining of its seeds
once they are in (the re-scoring rows are the costly part): ``--workers N`` runs them in N
single-threaded processes (default: one per core), and ``--checkpoint-dir DIR`` keeps each
seed's resumable checkpoint there, so a killed run (hours at the default budget) continues
where it stopped. Each scene's answers under every row are kept there too (``answers/``, named by
the scene's seeds and the rows' settings), so a resumed run does not combine a finished scene
again (about two minutes a soybean scene at the full-resolution row camera); delete that folder,
or bump ``ANSWERS_VERSION`` with a change to a combining rule's code, to recompute them.
``--finished-only`` fits nothing: it scores the scenes whose seeds are all finished in
``--checkpoint-dir`` (a long run's table so far, read while it runs). ``--first K`` fits and
scores only scenes K onwards of ``--scenes`` (each by its own number, truth and seeds): the
part of a run that one machine or session could not finish, whose per-scene results
(``--json``) join those of the earlier part; ``--only I,J,...`` fits and scores just those
scenes (a probe of the scenes a change is about; their numbers, truths and seeds are the full
run's). ``--diagnose K`` asks of every scene whose answer (the method's default rule) misses
the true LAI by more than 15 %, and of the largest misses that carry 80 % of LAIE's square,
whose miss it is: the answer's and the truth's parameters scored
on K fresh canopies each, paired (:func:`diagnose`): where the truth scores lower, the
optimiser's; where it does not, the loss's (this observation's statistics do not prefer it).
``--draw K`` (K ≥ 1) builds every scene's true canopy anew with another random seed at the same
true parameters (checkpoints of its own; draw 0 is the table's): how much of a scene's miss
belongs to its one observed draw rather than to its parameters.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from concurrent.futures import FIRST_COMPLETED, wait
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from benchmarks.options import at_least, folder, output_file, positive, write_json
from cropcraft_core.config import ParamBox, default_layout, param_space
from cropcraft_core.errors import ConfigError
from cropcraft_core.export.atomic import atomic_write_text
from cropcraft_core.fit import FitConfig, fit_seed, observe_canopy
from cropcraft_core.fit.fitting import COMBINE_RULES, OPT_IN_RULES, combine, initial_evals
from cropcraft_core.fit.forward import ForwardModel
from cropcraft_core.fit.select import select, unpolished
from cropcraft_core.metrics import canopy_metrics, evaluate
from cropcraft_core.observe import clear_render_height, preset
from cropcraft_core.parallel import SHARED, processes
from cropcraft_core.procedural import generate_canopy
from cropcraft_core.store import config_hash

PAPER = {  # Table "Synthetic data evaluation": LAIE, NDPE, NCPE
    ("soybean", "bo"): {"LAIE": 0.97, "NDPE": 0.21, "NCPE": 0.23},
    ("maize", "bo"): {"LAIE": 0.13, "NDPE": 0.05, "NCPE": 0.08},
    ("soybean", "trust-region"): {"LAIE": 2.49, "NDPE": 0.48, "NCPE": 0.91},
    ("maize", "trust-region"): {"LAIE": 1.46, "NDPE": 0.13, "NCPE": 0.70},
}
# LAI_within_15: the share of scenes whose LAI is within 15 % of the truth (the photo
# pipeline's target, ``bench_pipeline.TARGETS``, and the paper's figure on real soybean)
COLUMNS = ("LAIE", "LAIPE", "LAIPE_median", "LAI_within_15", "AME", "ASDE", "NDPE", "NCPE")
#: Part of every kept scene answer's name (``--checkpoint-dir``'s ``answers/``): bump it when a
#: combining rule's code changes (``fit/select.py``, ``fit/fitting.combine``), so that resumed
#: runs combine their scenes again instead of reading answers the old code gave.
ANSWERS_VERSION = 1


@dataclass(frozen=True)
class Budget:
    scenes: int
    fit: FitConfig
    scale: float  # image resolution relative to the paper's 994 × 738


def budget(
    quick: bool,
    scenes: int | None,
    method: str,
    crn: bool = True,
    overrides: dict | None = None,
    scale: float | None = None,
) -> Budget:
    """The quick or default budget, with optional FitConfig overrides (n_seeds, n_evals, ...)."""
    o = {k: v for k, v in (overrides or {}).items() if v is not None}
    if "n_evals" in o and "n_initial" not in o and isinstance(o["n_evals"], int):
        o["n_initial"] = initial_evals(o["n_evals"])  # as `cropcraft fit --evals N` reads N
    if scenes is not None and (
        isinstance(scenes, bool) or not isinstance(scenes, int) or scenes < 1
    ):
        raise ConfigError(f"scenes must be a whole number >= 1, got {scenes!r}")
    if scale is not None and not (isinstance(scale, int | float) and 0 < scale < float("inf")):
        raise ConfigError(f"image scale must be a finite number > 0, got {scale!r}")
    if quick:
        fit = {"n_seeds": 2, "n_evals": 60, "n_initial": 25, **o}
        cfg = FitConfig(method=method, common_random_numbers=crn, **fit)
        return Budget(6 if scenes is None else scenes, cfg, 0.25 if scale is None else scale)
    cfg = FitConfig(method=method, common_random_numbers=crn, **o)
    return Budget(30 if scenes is None else scenes, cfg, 1.0 if scale is None else scale)


#: Canopy seeds of one draw apart: more than any scene number.
DRAW_STRIDE = 1_000_000


def canopy_seed(index: int, draw: int = 0) -> int:
    """The random seed of scene ``index``'s true canopy in observation draw ``draw`` (0: the
    table's); a fitted canopy is measured on the same seed, so a scene's LAI error is its
    parameters', not two canopies' draws."""
    if not 0 <= index < DRAW_STRIDE or draw < 0:
        raise ConfigError(f"scene {index}, draw {draw}: out of range")
    return 100_000 + index + DRAW_STRIDE * draw


def scene_truth(crop: str, index: int, seed: int = 2024, draw: int = 0):
    """Scene ``index``'s true parameters (by ``seed`` and the index: the same in every draw)
    and its true canopy (draw ``draw``'s random seed, :func:`canopy_seed`)."""
    rng = np.random.default_rng([seed, index])
    params = {s.name: float(rng.uniform(s.low, s.high)) for s in param_space(crop)}
    canopy = generate_canopy(crop, params, default_layout(crop), seed=canopy_seed(index, draw))
    return params, canopy


def truth_record(crop: str, index: int, draw: int = 0) -> dict:
    """Scene ``index``'s true parameters and canopy metrics (in draw ``draw``)."""
    return _record(*scene_truth(crop, index, draw=draw))


def _record(params: dict, canopy) -> dict:
    return {"params": params, **canopy_metrics(canopy, gap_fraction=False)}


def scene_observation(
    crop: str, index: int, scale: float, preset_overrides: dict | None = None, draw: int = 0
) -> tuple[dict, object]:
    """Scene ``index``'s truth record (:func:`truth_record`) and its observation: the true
    canopy's depth from the row camera at ``scale`` × 994×738, at the crop's render height
    raised over a tall canopy as the row fit raises it (``observe.clear_render_height`` of the
    mesh's 99.5th height percentile), with the crop's observation preset changed by
    ``preset_overrides`` (e.g. ``{"lambda_lateral": 0.25}``), the true canopy of draw ``draw``.
    Deterministic, so a worker anywhere can rebuild it from these values."""
    params, canopy = scene_truth(crop, index, draw=draw)
    size = {"image_width": round(994 * scale), "image_height": round(738 * scale)}
    size.update(preset_overrides or {})
    base = preset(crop, **size)
    top = float(np.percentile(canopy.mesh.vertices[:, 2], 99.5))
    h = clear_render_height(crop, base.render_height, top)
    p = base if h == base.render_height else preset(crop, **{**size, "render_height": h})
    obs = observe_canopy(canopy, p, meta={"scene": index, "draw": draw})
    return _record(params, canopy), obs


def combine_scene(crop: str, rows, results, seconds: float, observation=None, layout=None) -> dict:
    """One scene's answer under each of ``rows`` ((row name, FitConfig)) from its seeds'
    ``results`` (combined in seed order, as ``fit_observation`` would), ``seconds`` the seeds'
    summed compute: ``{row: (params, seconds of fitting incl. any re-scoring)}``. Re-scoring
    rows need the scene's ``observation``; rows with the same re-scoring options share one
    re-scoring (it is deterministic), and each row still counts its seconds. A ``floors`` row
    also counts the seeds' own polishes (``SeedResult.floor``), which the other rows do not
    use. ``layout``: the planting layout the seeds were fitted with (None: the crop's)."""
    results = sorted(results, key=lambda r: r.seed)
    out, made, polished_by = {}, {}, {}
    for row, cfg in rows:
        if not cfg.reevaluates(crop):
            f = combine(crop, results, cfg, seconds)
            out[row] = (f.params, f.seconds)
            continue
        if cfg.combine_rule(crop) == "floors":  # no re-scoring; the seeds' polishes count here
            polishes = sum(float(r.floor["seconds"]) for r in results if r.floor is not None)
            f = combine(crop, results, cfg, seconds + polishes, observation, layout)
            out[row] = (f.params, f.seconds)
            continue
        box = cfg.param_box(crop)
        polished = polished_by.get((cfg.reevaluate_canopies, cfg.polish_starts, box.names))
        if cfg.combine_rule(crop) == "reevaluate" and cfg.polish_evals == 0 and polished:
            # the same re-scoring without its polish: read from a polished re-scoring
            _, params, rescore = unpolished(polished.to_dict(box))
            out[row] = (params, seconds + rescore)
            continue
        key = (cfg.reevaluate_canopies, cfg.polish_starts, cfg.polish_evals, box.names)
        if key not in made and observation is not None:  # (without one, combine names the error)
            made[key] = select(
                ForwardModel(observation, layout),
                results,
                cfg.reevaluate_canopies,
                cfg.polish_starts,
                cfg.polish_evals,
                box=box,
            )
            if cfg.polish_evals > 0:
                polished_by[(*key[:2], box.names)] = made[key]
        f = combine(crop, results, cfg, seconds, observation, layout, selection=made.get(key))
        out[row] = (f.params, f.seconds)
    return out


def score(
    crop: str,
    params: list[dict],
    truths: list[dict],
    seconds: list[float],
    log=print,
    indices: list[int] | None = None,
    draw: int = 0,
):
    """One method's row of the table: each scene's fitted canopy (built with the truth's canopy
    seed, :func:`canopy_seed` of its number and ``draw``) measured like the truth; LAIE, LAIPE
    (and its median), AME, ASDE, NDPE, NCPE. ``indices``: the scenes' numbers where they are
    not 0, 1, 2, ... (``--finished-only``)."""
    indices = list(range(len(params))) if indices is None else list(indices)
    preds = []
    for k, p_ in enumerate(params):
        i = indices[k]
        fitted = generate_canopy(crop, p_, default_layout(crop), seed=canopy_seed(i, draw))
        preds.append({"params": p_, **canopy_metrics(fitted, gap_fraction=False)})
        log(
            f"  {crop} scene {i}: LAI {preds[-1]['lai']:.2f} (true {truths[k]['lai']:.2f}), "
            f"{seconds[k]:.0f} s of fitting"
        )
    errs = evaluate(preds, truths)
    lai_pe = [abs(p_["lai"] - t_["lai"]) / t_["lai"] for p_, t_ in zip(preds, truths, strict=True)]
    errs["LAIPE_median"] = float(np.median(lai_pe))
    from benchmarks.bench_pipeline import TARGETS

    errs["LAI_within_15"] = float(np.mean(np.asarray(lai_pe) <= TARGETS["lai_rel_err"]))
    return {
        "errors": errs,
        "seconds_per_scene": float(np.mean(seconds)),
        "predictions": preds,
    }


def seed_coverage(
    crop: str,
    seed_params: list[list[dict]],
    truths: list[dict],
    indices: list[int],
    draw: int = 0,
) -> dict | None:
    """How the seeds' own answers spread around the truth, scene by scene: each seed's
    parameters built on the scene's truth layout and canopy seed and measured
    (:func:`cropcraft_core.metrics.seeds.seed_traits`, as the flow's ``metrics.json`` has
    them); ``truth_in_lai_range``: the share of scenes whose true LAI lies within its seeds'
    lowest and highest, ``lai_relative_range_median``: the median over scenes of (max − min) /
    mean, and per scene its range. None where the method has fewer than two seeds."""
    from cropcraft_core.metrics.seeds import seed_traits

    if not seed_params or min(len(p) for p in seed_params) < 2:
        return None
    per = []
    for i, params, truth in zip(indices, seed_params, truths, strict=True):
        seed = canopy_seed(i, draw)
        lai = seed_traits(crop, params, default_layout(crop), seed=seed)["traits"]["lai"]
        per.append(
            {
                "scene": int(i),
                "lai_min": lai["min"],
                "lai_max": lai["max"],
                "true_lai": truth["lai"],
                "inside": bool(lai["min"] <= truth["lai"] <= lai["max"]),
                "relative_range": lai["relative_range"],
            }
        )
    return {
        "truth_in_lai_range": float(np.mean([p["inside"] for p in per])),
        "lai_relative_range_median": float(np.median([p["relative_range"] for p in per])),
        "scenes": per,
    }


def run(
    crop: str,
    methods: list[str],
    quick: bool,
    scenes: int | None,
    crn_ablation: bool = False,
    log=print,
    overrides: dict | None = None,
    scale: float | None = None,
    workers: int = 1,
    checkpoint_dir: str | Path | None = None,
    preset_overrides: dict | None = None,
    known: tuple[str, ...] = (),
    finished_only: bool = False,
    first: int = 0,
    only: tuple[int, ...] = (),
    diagnose: int = 0,
    draw: int = 0,
) -> dict:
    """The benchmark's result: per method its errors, seconds of fitting per scene (summed over
    seeds, so independent of ``workers``) and the per-scene predictions; and the truths.
    ``preset_overrides``: observation preset changes (loss weights, bins) for every scene;
    ``known``: parameters every fit is given at the scene's true value; ``finished_only``: fit
    nothing, score only the scenes whose seeds are all finished in ``checkpoint_dir`` for every
    method (``scene_indices`` in the result says which); ``first``: fit and score only scenes
    ``first`` onwards of the ``scenes`` (a run split over machines; every scene keeps its own
    truth, so the parts' per-scene results join); ``only``: fit and score just these scene
    numbers of the ``scenes`` (a probe of the scenes a change is about); ``diagnose``: canopies
    on which each optimiser's LAI misses are scored against the truth (:func:`diagnose_misses`,
    under the method's ``diagnosis``); ``draw``: the true canopies' draw (:func:`canopy_seed`;
    0 is the table's)."""
    if diagnose == 1 or diagnose < 0:
        raise ConfigError(f"bench accuracy: --diagnose takes 2 canopies or more, got {diagnose}")
    runs = [(m, m, True) for m in methods]
    if crn_ablation and "bo" in methods:
        runs.append(("bo-no-crn", "bo", False))
    b0 = budget(quick, scenes, "bo", overrides=overrides, scale=scale)
    if not 0 <= first < b0.scenes:
        raise ConfigError(f"bench accuracy: --first {first} is not one of the {b0.scenes} scenes")
    numbers = tuple(range(first, b0.scenes))  # the scenes fitted, by their own numbers
    if only:
        bad = sorted(set(only) - set(numbers))
        if bad:
            raise ConfigError(
                f"bench accuracy: --only {bad[0]} is not one of scenes {first}..{b0.scenes - 1}"
            )
        numbers = tuple(sorted(set(only)))
    truths, observations = [], []
    for i in numbers:
        truth, obs = scene_observation(crop, i, b0.scale, preset_overrides, draw)
        truths.append(truth)
        observations.append(obs)
    out = {
        "crop": crop,
        "quick": quick,
        "scenes": b0.scenes,
        "methods": {},
        "budget": {**b0.fit.to_dict(), "image_scale": b0.scale},
        "preset_overrides": dict(preset_overrides or {}),
        "known": list(known),
        "draw": draw,
    }
    scene_set = _Scenes(
        observations,
        boxes=[{n: t["params"][n] for n in known} for t in truths],
        checkpoint_dir=Path(checkpoint_dir) if checkpoint_dir else None,
        preset_overrides=preset_overrides,
        indices=numbers,
        draw=draw,
    )
    if finished_only:
        if scene_set.checkpoint_dir is None:
            raise ConfigError("bench accuracy: --finished-only reads the seeds in --checkpoint-dir")
        keep = finished_scenes(
            scene_set,
            [
                (label, budget(quick, scenes, m, crn, overrides, scale))
                for label, m, crn in runs
                if m != "mlp"
            ],
        )
        if not keep:
            raise ConfigError(
                f"bench accuracy: no scene has all its seeds finished in {checkpoint_dir}"
            )
        log(f"  finished in {checkpoint_dir}: {len(keep)} of {len(observations)} scenes {keep}")
        scene_set = scene_set.subset(keep)
        observations = scene_set.observations
        truths = [truths[numbers.index(i)] for i in keep]
        out["scenes"] = len(keep)
    out["scene_indices"] = list(scene_set.indices)
    boxes = scene_set.boxes
    with processes(workers, {"observations": observations}) as ex:
        for label, method, crn in runs:
            b = budget(quick, scenes, method, crn, overrides, scale)
            if method == "mlp":
                params, seconds = _predict_mlp(observations, quick, ex)
                params = [
                    ParamBox.of(crop, bx).clip(p) for p, bx in zip(params, boxes, strict=True)
                ]
                out["methods"][label] = score(
                    crop, params, truths, seconds, log=log, indices=scene_set.indices, draw=draw
                )
                continue
            rows = rules(crop, label, b.fit)
            answers, seeds = _fit_and_combine(scene_set, b, label, rows, ex, workers, log)
            for row, _ in rows:
                params = [answers[i][row][0] for i in range(len(observations))]
                seconds = [answers[i][row][1] for i in range(len(observations))]
                log(f"  {row}:")
                out["methods"][row] = score(
                    crop, params, truths, seconds, log=log, indices=scene_set.indices, draw=draw
                )
            out["methods"][label]["seed_spread"] = seed_coverage(
                crop,
                [
                    [
                        ParamBox.of(crop, bx).params(r.reported_x)
                        for r in sorted(seeds[i], key=lambda r: r.seed)
                    ]
                    for i, bx in enumerate(boxes)
                ],
                truths,
                scene_set.indices,
                draw,
            )
            if diagnose:
                r = out["methods"][label]
                r["diagnosis"] = diagnose_misses(
                    observations, r["predictions"], truths, scene_set.indices, diagnose, ex, log
                )
    out["truths"] = truths
    return out


#: A paired difference beyond this many standard errors decides (as ``loss_attribution``'s).
DIAGNOSIS_SE = 2.0
#: :func:`diagnose_misses` also scores the largest LAI misses that together carry this share of
#: the summed squared LAI error.
DIAGNOSE_LAIE_SHARE = 0.8


def diagnose(observation, answer: dict, truth: dict, canopies: int) -> dict:
    """Whose miss an answer is, by its points: ``answer`` and ``truth`` (parameter dicts) scored
    on the same ``canopies`` fresh canopies (paired: each canopy seed builds both), the loss's
    mean at each and the paired difference (answer − truth) with its standard error.

    ``whose``: ``optimiser`` where the truth scores lower by more than :data:`DIAGNOSIS_SE`
    standard errors: a better point existed and the fit did not return it (a seed that missed,
    or a combined answer off its basin's floor); ``loss`` otherwise: the answer scores as well
    as the truth or better, so the statistics of this observation do not prefer the truth's
    parameters (the observed canopy is one draw, and its loss's minimum lies elsewhere). By
    points, not floors: a point near the truth might still beat the answer, so ``loss`` says
    only that the truth itself would not have been the better answer
    (``bench_pipeline.loss_attribution`` polishes both to their floors, at a hundred times the
    cost)."""
    from benchmarks.bench_pipeline import ATTRIBUTION_FROM, POLISH_SEEDS
    from cropcraft_core.fit.select import reevaluation_seeds

    if canopies < 2:
        raise ConfigError(f"diagnose needs 2 canopies or more, got {canopies}")
    fm = ForwardModel(observation)
    # the canopies on which loss_attribution scores its points (after its polish canopies),
    # so no optimiser seed, re-scoring or polish drew them
    first = ATTRIBUTION_FROM + len(POLISH_SEEDS)
    seeds = reevaluation_seeds(first + canopies)[first:]
    la = np.asarray([fm.loss(answer, s) for s in seeds])
    lt = np.asarray([fm.loss(truth, s) for s in seeds])
    d = la - lt
    se = float(d.std(ddof=1) / np.sqrt(d.size))
    return {
        "canopies": canopies,
        "answer_loss": float(la.mean()),
        "truth_loss": float(lt.mean()),
        "difference": {"mean": float(d.mean()), "se": se},
        "whose": "optimiser" if d.mean() > DIAGNOSIS_SE * se else "loss",
    }


def _diagnose_job(args) -> dict:
    i, answer, truth, canopies = args
    return diagnose(SHARED["observations"][i], answer, truth, canopies)


def diagnose_misses(
    observations: list,
    predictions: list[dict],
    truths: list[dict],
    indices,
    canopies: int,
    ex=None,
    log=print,
) -> dict:
    """:func:`diagnose` for every scene whose predicted LAI misses the truth by more than the
    pipeline's 15 % (``bench_pipeline.TARGETS``) and for the fewest, largest misses that carry
    :data:`DIAGNOSE_LAIE_SHARE` of the summed squared LAI error (LAIE's: a dense canopy 10 %
    off weighs more than a sparse one 30 % off), in ``ex``'s processes where given (whose
    :data:`SHARED` observations are ``observations``), and what the misses carry:
    ``{"canopies", "scenes": {number: diagnosis}, "share_of_lai_sq_error": {whose: share}}``
    (each verdict's part of the summed squared LAI error of all scenes, the LAIE's square
    times their count)."""
    from benchmarks.bench_pipeline import TARGETS

    err = np.asarray([p["lai"] - t["lai"] for p, t in zip(predictions, truths, strict=True)])
    sq = err**2
    # the scenes that carry LAIE: the largest squared errors, up to DIAGNOSE_LAIE_SHARE of it
    order = np.argsort(-sq, kind="stable")
    carried = np.cumsum(sq[order]) - sq[order] < DIAGNOSE_LAIE_SHARE * sq.sum()
    carry = {int(k) for k in order[carried & (sq[order] > 0)]}
    misses = [
        k
        for k, t in enumerate(truths)
        if abs(err[k]) > TARGETS["lai_rel_err"] * t["lai"] or k in carry
    ]
    jobs = [(k, predictions[k]["params"], truths[k]["params"], canopies) for k in misses]
    if ex is None:
        got = [diagnose(observations[k], *rest) for k, *rest in jobs]
    else:
        got = list(ex.map(_diagnose_job, jobs))
    found = dict(zip(misses, got, strict=True))
    total = float(sq.sum()) or 1.0
    share = {"optimiser": 0.0, "loss": 0.0}
    for k, d in found.items():
        share[d["whose"]] += float(sq[k]) / total
        diff = d["difference"]
        log(
            f"  scene {indices[k]}: LAI {err[k]:+.2f}, answer − truth loss "
            f"{diff['mean']:+.2e} ± {diff['se']:.1e}: {d['whose']}"
        )
    return {
        "canopies": canopies,
        "scenes": {int(indices[k]): d for k, d in found.items()},
        "share_of_lai_sq_error": share,
    }


def rules(crop: str, label: str, cfg: FitConfig) -> list[tuple[str, FitConfig]]:
    """The table rows one method's seeds give: BO's seeds are also combined by the other rules
    (``{label}-mean``, ``{label}-median``, ``{label}-reevaluate``), at no extra fitting cost,
    so every run compares them on the same seeds. The opt-in rules (``OPT_IN_RULES``:
    ``floors`` polishes every seed's point) are a row only where ``--combine`` names them."""
    if cfg.method != "bo":
        return [(label, cfg)]
    own = cfg.combine_rule(crop)
    others = [r for r in COMBINE_RULES if r != own and r not in OPT_IN_RULES]
    rows = [(label, cfg), *((f"{label}-{r}", replace(cfg, combine=r)) for r in others)]
    # the re-scoring's own answer without its Nelder-Mead polish, on the same seeds
    return rows + [
        (f"{row}-unpolished", replace(c, polish_evals=0))
        for row, c in rows
        if c.combine_rule(crop) == "reevaluate" and c.polish_evals > 0
    ]


def seed_seconds(r) -> float:
    """A seed's own compute seconds (objective + optimiser) as its result records them, so a
    seed resumed from a finished checkpoint still counts what it cost."""
    return float(r.seconds_objective + r.seconds_optimizer)


def _seed_job(args) -> tuple[int, object, float]:
    """One optimiser seed of one scene (in a worker process or in-process)."""
    i, seed, cfg, checkpoint = args
    r = fit_seed(SHARED["observations"][i], seed, cfg, checkpoint=checkpoint)
    return i, r, seed_seconds(r)


@dataclass(frozen=True)
class _Scenes:
    """What every method's fits in one benchmark run share: the scenes' observations, the
    parameters given in each (``boxes[k]``, ``{}`` where none), the observation preset's
    changes (part of a checkpoint's name), where the seeds checkpoint (``None``: nowhere), the
    scenes' numbers (``indices[k]``; 0, 1, 2, ... unless a subset was taken) and the true
    canopies' draw (:func:`canopy_seed`; part of a checkpoint's name where not 0)."""

    observations: list
    boxes: list[dict]
    checkpoint_dir: Path | None = None
    preset_overrides: dict | None = None
    indices: tuple[int, ...] | None = None
    draw: int = 0

    def __post_init__(self) -> None:
        if self.indices is None:
            object.__setattr__(self, "indices", tuple(range(len(self.observations))))

    def subset(self, keep: list[int]) -> _Scenes:
        """The scenes numbered ``keep`` (numbers, not positions)."""
        pos = [self.indices.index(i) for i in keep]
        return replace(
            self,
            observations=[self.observations[k] for k in pos],
            boxes=[self.boxes[k] for k in pos],
            indices=tuple(keep),
        )

    def stems(self, b: Budget, label: str) -> list[str]:
        """Per scene, the name its kept files start with: the crop, the method and what makes
        its fit another one (resolution, budget, optimiser, preset changes, known parameters,
        a raised camera), and the scene's number."""
        cfg = b.fit
        crop = self.observations[0].crop
        tag = f"{label}-x{b.scale:g}-e{cfg.n_evals}-i{cfg.n_initial}-k{cfg.canopies_per_eval or 0}"
        if not cfg.papers_optimiser(crop):  # another optimiser: its own checkpoints
            tag += f"-g{cfg.resolved(crop).gp_output}-l{cfg.local_evals(crop)}"
        if cfg.loss_estimator != "pooled":  # another objective: its own checkpoints
            tag += f"-{cfg.loss_estimator}"
        # another loss or other statistics: another fit, its own checkpoints
        if self.preset_overrides:
            tag += "-p" + config_hash(self.preset_overrides)[:8]
        # depth bins over each canopy (maize's default since session 40): not the paper's bins
        top = preset(crop, **(self.preset_overrides or {})).loss.depth_top_margin
        if top is not None:
            tag += f"-top{top:g}"
        if any(self.boxes):  # parameters given: another fit, its own checkpoints
            tag += "-known-" + "-".join(sorted(self.boxes[0]))
        if self.draw:  # another observed canopy: another fit, its own checkpoints
            tag += f"-draw{self.draw}"
        default_h = preset(crop).render_height
        out = []
        for i, obs in zip(self.indices, self.observations, strict=True):
            # a scene observed from a raised camera is another fit: its own checkpoints
            h = obs.preset.render_height
            raised = f"-h{h:g}" if abs(h - default_h) > 1e-9 else ""
            out.append(f"{crop}-{tag}-scene{i}{raised}")
        return out


def _seed_jobs(scenes: _Scenes, b: Budget, label: str):
    """The (position, seed, config, checkpoint path) jobs that fit every scene with ``b.fit``
    (given the parameters known in that scene), in scene order."""
    cfg, ck = b.fit, scenes.checkpoint_dir
    if ck is not None:
        ck.mkdir(parents=True, exist_ok=True)
    return [
        (k, s, replace(cfg, box=scenes.boxes[k]), ck / f"{stem}-seed{s}.json" if ck else None)
        for k, stem in enumerate(scenes.stems(b, label))
        for s in range(cfg.n_seeds)
    ]


def finished_scenes(scenes: _Scenes, methods: list[tuple[str, Budget]]) -> list[int]:
    """The numbers of the scenes whose seed checkpoints (:func:`_seed_jobs`) are all finished
    in ``scenes.checkpoint_dir`` under every one of ``methods`` ((label, budget) pairs)."""
    done = set(scenes.indices)
    for label, b in methods:
        for k, _, _, path in _seed_jobs(scenes, b, label):
            n = scenes.indices[k]
            if n in done and not (path.is_file() and _finished(path)):
                done.discard(n)
    return sorted(done)


def _finished(path: Path) -> bool:
    try:
        return bool(json.loads(path.read_text()).get("complete", True))
    except (OSError, ValueError):
        return False  # being written, or cut short: not finished


def _answers_path(scenes: _Scenes, stem: str, crop: str, rows, results) -> Path | None:
    """Where a scene's answers under ``rows`` ((row, FitConfig) pairs) from its seeds'
    ``results`` are kept, or None without a checkpoint folder. Named by the scene's seeds
    (``stem``) and a hash of every row's resolved settings, each seed's reported point and loss
    (seeds fitted again differently, e.g. by changed code, are another key), the package version
    and ``ANSWERS_VERSION``."""
    if scenes.checkpoint_dir is None:
        return None
    from cropcraft_core import __version__

    key = {
        "rows": [[row, c.resolved(crop).to_dict()] for row, c in rows],
        "seeds": [
            [r.seed, np.asarray(r.reported_x).tolist(), repr(float(r.best_y))]
            for r in sorted(results, key=lambda r: r.seed)
        ],
        "version": [__version__, ANSWERS_VERSION],
    }
    return scenes.checkpoint_dir / "answers" / f"{stem}-{config_hash(key)[:12]}.json"


def _read_answers(path: Path | None) -> dict | None:
    if path is None or not path.is_file():
        return None
    try:
        return {row: (p, float(sec)) for row, (p, sec) in json.loads(path.read_text()).items()}
    except (OSError, ValueError, TypeError):
        return None  # unreadable: combine again (and write it anew)


def _write_answers(path: Path | None, answers: dict) -> None:
    if path is not None:
        text = json.dumps({row: [p, sec] for row, (p, sec) in answers.items()}, default=float)
        atomic_write_text(path, text)


def _combine_job(args) -> tuple[int, dict]:
    """One scene's answers under every row (in a worker process or in-process)."""
    i, crop, rows, results, seconds = args
    return i, combine_scene(crop, rows, results, seconds, SHARED["observations"][i])


def _fit_and_combine(
    scenes: _Scenes, b: Budget, label: str, rows, ex, workers: int, log
) -> tuple[dict[int, dict], dict[int, list]]:
    """Every scene's seeds fitted, then its answers under every row (:func:`combine_scene`):
    ``{scene: {row: (params, seconds)}}``, and ``{scene: its seeds' results}`` (in the order
    they came in). In ``ex``'s processes a scene is combined as soon as its last seed is in,
    ahead of the seeds still queued, so the re-scoring of one scene runs beside the fitting of
    the next instead of all of it, one scene after another, at the end (for maize, about 1.5
    min per scene on one core)."""
    crop = scenes.observations[0].crop
    n_seeds = b.fit.n_seeds
    per_scene: dict[int, list] = {i: [] for i in range(len(scenes.observations))}
    seconds = dict.fromkeys(per_scene, 0.0)
    answers: dict[int, dict] = {}
    stems = scenes.stems(b, label)
    kept = {}  # position -> where its answers are kept

    def seed_in(i: int, r, sec: float):
        per_scene[i].append(r)
        seconds[i] += sec
        if len(per_scene[i]) < n_seeds:
            return None
        n = scenes.indices[i]
        log(f"  {label} scene {n}: {n_seeds} seeds in {seconds[i]:.0f} s")
        scene_rows = [(row, replace(c, box=scenes.boxes[i])) for row, c in rows]
        kept[i] = _answers_path(scenes, stems[i], crop, scene_rows, per_scene[i])
        got = _read_answers(kept[i])
        if got is not None:
            log(f"  {label} scene {n}: answers read from {kept[i].name}")
            answers[i] = got
            return None
        return (i, crop, scene_rows, per_scene[i], seconds[i])

    def combined(i: int, answer: dict) -> None:
        answers[i] = answer
        _write_answers(kept[i], answer)

    jobs = _seed_jobs(scenes, b, label)
    if ex is None:
        for job in jobs:
            ready = seed_in(*_seed_job(job))
            if ready is not None:
                combined(*_combine_job(ready))
        return answers, per_scene
    queued_seeds, queued_combines = iter(jobs), []
    pending: dict = {}
    window = 2 * max(1, workers)  # enough queued to keep every process busy
    while True:
        while len(pending) < window:
            if queued_combines:
                pending[ex.submit(_combine_job, queued_combines.pop(0))] = "combine"
                continue
            job = next(queued_seeds, None)
            if job is None:
                break
            pending[ex.submit(_seed_job, job)] = "seed"
        if not pending:
            return answers, per_scene
        finished, _ = wait(pending, return_when=FIRST_COMPLETED)
        for fut in finished:
            kind = pending.pop(fut)
            if kind == "seed":
                ready = seed_in(*fut.result())
                if ready is not None:
                    queued_combines.append(ready)
            else:
                combined(*fut.result())


def _predict_mlp(observations, quick: bool, ex=None):
    """The mlp baseline per scene (its network trained once per crop and config, then cached;
    its training pairs made in ``ex``'s worker processes)."""
    from cropcraft_core.fit.mlp import MLPConfig, predict_params

    cfg = MLPConfig(n_pairs=400, epochs=60) if quick else None
    params, seconds = [], []
    for obs in observations:
        t = time.perf_counter()
        params.append(predict_params(obs, cfg, executor=ex))
        seconds.append(time.perf_counter() - t)
    return params, seconds


def print_table(res: dict) -> None:
    crop = res["crop"]
    b = res.get("budget", {})
    idx = res.get("scene_indices")
    some = f" (numbers {idx})" if idx is not None and idx != list(range(len(idx))) else ""
    if res.get("draw"):
        some += f", true canopies of draw {res['draw']}"
    print(
        f"\nSynthetic accuracy, {crop}, {res['scenes']} scenes{some}"
        f"{' (quick budget)' if res['quick'] else ''}: {b.get('n_seeds')} seeds x "
        f"{b.get('n_evals')} evaluations ({b.get('n_initial')} initial), row camera at "
        f"{b.get('image_scale')} x 994x738"
    )
    w = max([16, *(len(k) + 1 for k in res["methods"])])
    head = f"{'method':<{w}}" + "".join(f"{c:>14}" for c in COLUMNS) + f"{'s/scene':>10}"
    print(head)
    print("-" * len(head))
    for label, r in res["methods"].items():
        e = r["errors"]
        cells = "".join(f"{e[c]:>14.3f}" if e.get(c) is not None else f"{'-':>14}" for c in COLUMNS)
        print(f"{label:<{w}}{cells}{r['seconds_per_scene']:>10.1f}")
        paper = PAPER.get((crop, label))
        if paper:
            cells = "".join(f"{paper[c]:>14.2f}" if c in paper else f"{'':>14}" for c in COLUMNS)
            print(f"{'  paper ' + label:<{w}}{cells}")
    bo = res["methods"].get("bo")
    paper = PAPER.get((crop, "bo"))
    if bo and paper:  # the target: better than the paper's BO row on every column
        e = bo["errors"]
        said = [
            f"{c} {e[c]:.3f} {'<' if e[c] < v else 'NOT <'} {v:g}"
            for c, v in paper.items()
            if e.get(c) is not None
        ]
        median = e.get("LAIPE_median")
        if median is not None:
            said.append(f"median LAIPE {median:.3f} {'<=' if median <= 0.10 else 'NOT <='} 0.10")
        met = all("NOT" not in x for x in said)
        print(f"bo against the target: {'; '.join(said)}: {'met' if met else 'NOT met'}")
    for label, r in res["methods"].items():
        cover = r.get("seed_spread")
        if cover:
            n = len(cover["scenes"])
            inside = round(cover["truth_in_lai_range"] * n)
            print(
                f"{label}: the true LAI lies within the seeds' own answers' range on {inside} "
                f"of {n} scenes; that range's median width {cover['lai_relative_range_median']:.0%}"
                " of its mean"
            )
    for label, r in res["methods"].items():
        diag = r.get("diagnosis")
        if diag is None:
            continue
        whose = [d["whose"] for d in diag["scenes"].values()]
        share = diag["share_of_lai_sq_error"]
        print(
            f"{label}: {len(whose)} scenes diagnosed (LAI missed by more than 15 %, or among "
            f"the misses that carry {DIAGNOSE_LAIE_SHARE:.0%} of LAIE's square); by their "
            f"points on {diag['canopies']} canopies, "
            + ", ".join(
                f"{w} {whose.count(w)} ({share[w]:.0%} of the squared LAI error)"
                for w in ("optimiser", "loss")
            )
        )


def _run_flow(a: argparse.Namespace, methods: list[str], overrides: dict) -> dict:
    """The same benchmark through ``flows.benchmark`` (Prefect; Dask scale-out)."""
    from flows.benchmark import run_benchmark

    got = run_benchmark(
        a.runner,
        a.workers,
        crop=a.crop,
        methods=methods,
        quick=a.quick,
        scenes=a.scenes,
        store=a.store,
        overrides={k: v for k, v in overrides.items() if v is not None},
        image_scale=a.image_scale,
    )
    rows = {
        m: {"errors": e, "seconds_per_scene": got["seconds_per_scene"][m]}
        for m, e in got["errors"].items()
    }
    for m, spread in got.get("seed_spread", {}).items():
        rows[m]["seed_spread"] = spread  # the table's seed-coverage line, as a local run's
    n = len(next(iter(got["predictions"].values())))
    return {**got, "crop": a.crop, "quick": a.quick, "scenes": n, "methods": rows}


def _parse_preset(crop: str, items: list[str]) -> dict:
    """``["lambda_lateral=0.25", ...]`` → ``{"lambda_lateral": 0.25}`` (``parse_preset``; an
    unknown key or a bad value exits with the preset's own message)."""
    from cropcraft_core.errors import ConfigError
    from flows.service_cli import parse_preset

    try:
        return parse_preset(crop, items)
    except ConfigError as exc:
        raise SystemExit(f"bench accuracy: {exc}") from None


def _scene_list(text: str) -> tuple[int, ...]:
    try:
        out = tuple(int(x) for x in text.split(",") if x.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"scene numbers by commas, got {text!r}") from None
    if not out or min(out) < 0:
        raise argparse.ArgumentTypeError(f"scene numbers (0 or more) by commas, got {text!r}")
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="cropcraft bench accuracy", description=__doc__.splitlines()[0]
    )
    ap.add_argument("--crop", required=True, choices=["soybean", "maize"])
    ap.add_argument("--scenes", type=at_least(1), help="scenes (default 30; --quick 6)")
    ap.add_argument(
        "--first",
        type=at_least(0),
        default=0,
        help="fit only scenes FIRST.. of --scenes (to split a run over machines or sessions)",
    )
    ap.add_argument(
        "--only",
        type=_scene_list,
        default=(),
        metavar="I,J,...",
        help="fit only these scene numbers of --scenes (e.g. the scenes a change is about)",
    )
    ap.add_argument(
        "--methods",
        help="comma-separated (default bo,trust-region,random,mlp; with --runner no mlp)",
    )
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--crn-ablation", action="store_true")
    ap.add_argument("--json", type=output_file, help="write the whole result here")
    ap.add_argument("--seeds", type=at_least(1), help="override optimiser seeds per scene")
    ap.add_argument("--evals", type=at_least(2), help="override evaluations per seed")
    ap.add_argument("--initial", type=at_least(2), help="override random initial evaluations")
    ap.add_argument(
        "--canopies", type=at_least(1), help="override canopies averaged per evaluation"
    )
    ap.add_argument(
        "--gp-output", choices=["none", "log"], help="override what BO's GP models (FitConfig)"
    )
    ap.add_argument(
        "--estimator",
        choices=["pooled", "unbiased"],
        help="override how an evaluation's loss over several canopies is estimated (FitConfig)",
    )
    ap.add_argument(
        "--local-share",
        type=float,
        help="override the share of each BO seed's evaluations spent last on Nelder-Mead",
    )
    ap.add_argument(
        "--combine",
        choices=list(COMBINE_RULES),
        help="BO's answer rule (the first row; default: the crop's); the other rules but the "
        "opt-in floors are compared on the same seeds as further rows",
    )
    ap.add_argument(
        "--image-scale", type=positive, help="row camera resolution / 994x738 (1; --quick 0.25)"
    )
    ap.add_argument(
        "--workers",
        type=at_least(1),
        help="single-threaded fit processes (default: one per core); with --runner processes "
        "or dask, the pool's or the local cluster's size",
    )
    ap.add_argument(
        "--checkpoint-dir",
        type=folder,
        help="resumable per-seed checkpoints and each scene's answers (a rerun continues)",
    )
    ap.add_argument(
        "--finished-only",
        action="store_true",
        help="fit nothing: score the scenes whose seeds are all finished in --checkpoint-dir",
    )
    ap.add_argument(
        "--runner",
        help="run as the Prefect benchmark flow, one task per seed, on processes (spawned, one "
        "per core), threads, dask (a local cluster) or dask://HOST:PORT (an existing cluster); "
        "the result goes to --store",
    )
    ap.add_argument("--store", help="scene store for the flow's result (default ./cropcraft-data)")
    ap.add_argument(
        "--diagnose",
        type=at_least(0),
        default=0,
        metavar="K",
        help="score each scene whose LAI misses by more than 15 %% (and the misses that carry "
        "most of LAIE) at its answer and its truth on K fresh canopies: whose miss it is, the "
        "optimiser's or the loss's",
    )
    ap.add_argument(
        "--known",
        action="append",
        default=[],
        metavar="NAME",
        help="give every fit the scene's true value of this parameter, as a user who counted "
        "it would (repeatable; such fits keep their own checkpoints)",
    )
    ap.add_argument(
        "--draw",
        type=at_least(0),
        default=0,
        metavar="K",
        help="build every scene's true canopy with draw K's random seed at the same true "
        "parameters (0, the default, is the table's; others keep their own checkpoints)",
    )
    ap.add_argument(
        "--preset",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="change the observation preset of every scene (e.g. lambda_lateral=0.25); "
        "repeatable; such fits keep their own checkpoints",
    )
    a = ap.parse_args(argv)
    try:  # bad input exits 2 with argparse's line, as the other arguments do (it exited 1)
        preset_overrides = _parse_preset(a.crop, a.preset)
    except SystemExit as exc:
        ap.error(str(exc.code).removeprefix("bench accuracy: "))
    names = {p.name for p in param_space(a.crop)}
    for n in a.known:
        if n not in names:
            ap.error(f"--known {n}: not a {a.crop} parameter")
    default_methods = "bo,trust-region,random,mlp"
    if a.runner:  # Prefect only then: the flow maps seeds, so no mlp (it predicts directly)
        from flows.benchmark import SEED_METHODS

        default_methods = ",".join(SEED_METHODS)
    methods = [m.strip() for m in (a.methods or default_methods).split(",") if m.strip()]
    known = default_methods.split(",")
    unknown = [m for m in methods if m not in known]
    if unknown or not methods:  # not after the first methods have fitted every scene
        ap.error(
            f"--methods {a.methods!r}: "
            + (f"unknown method(s) {', '.join(unknown)}; " if unknown else "no method; ")
            + f"choose from {', '.join(known)}"
        )
    overrides = {
        "n_seeds": a.seeds,
        "n_evals": a.evals,
        "n_initial": a.initial,
        "canopies_per_eval": a.canopies,
        "gp_output": a.gp_output,
        "local_share": a.local_share,
        "combine": a.combine,
        "loss_estimator": a.estimator,
    }
    if a.finished_only and not a.checkpoint_dir:
        ap.error("--finished-only reads the seeds in --checkpoint-dir")
    if a.runner:
        if a.finished_only:
            ap.error("--finished-only is not available with --runner")
        if (
            preset_overrides
            or a.known
            or a.first
            or a.only
            or a.diagnose
            or a.checkpoint_dir
            or a.crn_ablation
            or a.draw
        ):
            ap.error(
                "--preset, --known, --first, --only, --diagnose, --draw, --checkpoint-dir and "
                "--crn-ablation are not available with --runner"
            )
        res = _run_flow(a, methods, overrides)
        print_table(res)
        print(f"stored: {res['url']}")
        if a.json:
            write_json(a.json, res)
        return 0
    res = run(
        a.crop,
        methods,
        a.quick,
        a.scenes,
        a.crn_ablation,
        overrides=overrides,
        scale=a.image_scale,
        workers=a.workers or os.cpu_count() or 1,
        checkpoint_dir=a.checkpoint_dir,
        preset_overrides=preset_overrides,
        known=tuple(a.known),
        finished_only=a.finished_only,
        first=a.first,
        only=a.only,
        diagnose=a.diagnose,
        draw=a.draw,
    )
    print_table(res)
    if a.json:
        write_json(a.json, res)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
