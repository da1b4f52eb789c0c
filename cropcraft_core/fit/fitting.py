"""Fitting a procedural model to an observation: one seed at a time (the unit the orchestrator
maps), and the whole fit (10 seeds, then one answer chosen from them: ``fit/select.py``).

Noise. The procedural model is stochastic (plant positions, azimuths, angle noise). With
``common_random_numbers=True`` (default) every evaluation of a seed uses the same canopy seed, so
the loss surface a seed explores is a deterministic function of the parameters (plants keep their
random numbers whatever the parameters: ``procedural/randomness.py``) and the GP models smooth
structure instead of noise; different optimiser seeds use different canopy seeds, so averaging
over seeds still averages the model's randomness. ``False`` draws a fresh canopy per evaluation.
``benchmarks/bench_accuracy.py --crn-ablation`` measures the difference.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np

from cropcraft_core.config import CanopyLayout
from cropcraft_core.config.params import ParamBox, is_range
from cropcraft_core.errors import ConfigError, InputError
from cropcraft_core.fit.forward import ESTIMATORS, ForwardModel
from cropcraft_core.observe import Observation
from cropcraft_core.optimize import BOConfig, SeedResult, aggregate, run_seed
from cropcraft_core.optimize.baselines import run_random, run_trust_region
from cropcraft_core.optimize.bo import OUTPUT_TRANSFORMS
from cropcraft_core.parallel import run_jobs

if TYPE_CHECKING:
    from cropcraft_core.fit.select import Selection

METHODS = ("bo", "trust-region", "random", "mlp")
COMBINE_RULES = ("median", "mean", "reevaluate", "guarded", "floors")
#: The rules that re-score candidates on fresh canopies (and so need the observation).
RESCORING_RULES = ("reevaluate", "guarded", "floors")
#: FitConfig settings only the answer rule reads (the seeds' searches do not depend on them).
AGGREGATE_ONLY = frozenset({"combine", "reevaluate_canopies", "polish_starts", "polish_evals"})
#: Rules only asked for by name: no crop's default, and left out of the benchmark's automatic
#: comparison rows (``floors`` polishes every seed's point: 0.4-1.2x its search again).
OPT_IN_RULES = ("floors",)
# Measured on the benchmark's stored seeds (fit/select.py): re-scoring improved maize's LAIE, LAIPE
# and NCPE with each of three sets of re-scoring canopies, and on 12 fresh maize scenes (30-41,
# session 37) it read LAIE 0.180 / NDPE 0.034 against the median's 0.485 / 0.054, though the median
# had won scenes 18-29 (benchmarks/RESULTS.md, *Synthetic accuracy: maize*). On dense soybean the
# loss hardly constrains LAI and the winner jumped with the canopies. Soybean takes the
# per-parameter median of the seeds' best points: a seed or two stranded at a valley's far end pull
# the mean off (first 18 benchmark scenes: median LAIPE 0.059 against the mean's 0.091, NDPE 0.115
# against 0.135, NCPE 0.218 against 0.256, LAIE 0.588 against 0.534; better on 6 of 7 columns on the
# first 13 scenes, LAIE the exception, and on all 7 on the next 5). Since session 31 the median is
# guarded (``select.guard``): where re-scoring's polished winner beats the median's own polished
# floor by two standard errors on 32 fresh canopies, the winner is taken. On all 30 benchmark scenes
# (half-resolution row camera, the same seeds) it took the winner on 11 and read LAIPE 0.116 against
# the median's 0.128, median LAIPE 0.080 / 0.097, NCPE 0.236 / 0.265, AME 10.2 / 10.7 deg, but LAIE
# 0.485 / 0.430 and NDPE 0.145 / 0.135 (two closed canopies read 5-14 points lower); through SfM,
# the demo's canopy (tsdf) +16.2 % against +29.8 % (benchmarks/RESULTS.md, *Combining the seeds*).
DEFAULT_COMBINE = {"soybean": "guarded", "maize": "reevaluate"}
# With the node count given (a value in ``FitConfig.box``, not a range), soybean's seeds no
# longer spread along the valley of fewer, longer internodes with bigger leaves that the median
# guards against, and the paper's mean reads LAI better. 30 benchmark scenes given their true
# count (half-resolution row camera, 10 x 500), mean against median: LAIE 0.384 / 0.446, LAIPE
# 0.083 / 0.098, median LAIPE 0.043 / 0.059, ASDE 1.7 / 1.9 deg; AME 6.1 / 5.3 deg and NDPE
# 0.058 / 0.055 the other way (benchmarks/RESULTS.md, *Known parameters*). Maize keeps
# re-scoring: with its leaf count given it read LAI best of the rules on 8 scenes.
DEFAULT_COMBINE_GIVEN = {"soybean": ("num_nodes", "mean")}


def default_combine(crop: str, box: dict[str, Any] | None = None) -> str:
    """The answer rule of ``crop``'s BO fits when none is set: ``DEFAULT_COMBINE``, or
    ``DEFAULT_COMBINE_GIVEN``'s where ``box`` fixes its parameter to a value."""
    given = DEFAULT_COMBINE_GIVEN.get(crop)
    if given and box and given[0] in box and not is_range(box[given[0]]):
        return given[1]
    return DEFAULT_COMBINE[crop]


DEFAULT_CANOPIES = {"soybean": 2, "maize": 1}
# The paper's optimiser (no closing local search) for both crops: on soybean a closing
# Nelder-Mead (share 0.2) halved the seeds' losses but did not bring their answers closer to
# the truth on 16 benchmark scenes (README, "Where the fit departs from the paper").
DEFAULT_LOCAL_SHARE = {"soybean": 0.0, "maize": 0.0}
# What BO's GP models, per crop: the loss (the paper's) for both, for now. A maize seed's loss
# spans five to seven orders of magnitude (initial design's median 0.2-0.45, a small plant's
# truth 1e-7-1e-4), so the GP on the loss, standardised by that spread, models the valley
# floors as one flat zero and EI explores instead of resolving them; on log(loss) the floors
# keep their shape. Measured on maize scenes 16-29 (pinned, 10 x 500): LAIE 0.396 -> 0.234,
# LAIPE 0.063 -> 0.044, median LAIPE 0.048 -> 0.039, NDPE 0.087 -> 0.078, NCPE 0.098 -> 0.105
# (benchmarks/RESULTS.md, *#maize-log*); on scenes 0-15 the other way (LAIE 0.135 -> 0.193,
# NDPE 0.037 -> 0.044, NCPE 0.042 -> 0.033). All 30: LAIE 0.288 -> 0.213, NDPE tied (0.0603 ->
# 0.0599), NCPE 0.068 -> 0.067. The tie went to fresh scenes 30-37 by a rule written first
# (switch iff log's LAIE is lower): LAIE 0.113 -> 0.131, so maize stays on the loss.
DEFAULT_GP_OUTPUT = {"soybean": "none", "maize": "none"}
CANOPY_SEED_BASE = 7919  # canopy seeds of optimiser seed s: CANOPY_SEED_BASE + s (CRN)


def initial_evals(n_evals: int) -> int:
    """The random initial design for ``n_evals`` evaluations: the paper's 200 of 500, and the
    same 40 % of a smaller budget (at least 2). Clipping 200 to a budget of 200 or fewer
    made every evaluation a random one: a random search under the name ``bo``."""
    return max(2, min(200, round(0.4 * n_evals)))


@dataclass(frozen=True)
class FitConfig:
    """How to fit (paper defaults)."""

    method: str = "bo"
    """bo (Bayesian optimisation), trust-region, random or mlp."""
    n_seeds: int = 10
    """Independent optimiser seeds; how one answer is chosen from them is ``combine``."""
    combine: str | None = None
    """BO's final parameters from its seeds: ``mean`` (the paper's mean of the seeds' best
    points), ``median`` (their per-parameter median: robust to a seed stranded at the far end
    of a loss valley) or ``reevaluate`` (every seed's best point, their mean and the minimum of
    the seeds' averaged GPs re-scored on fresh canopies, the lowest wins: ``fit/select.py``,
    where its measurements are) or ``guarded`` (the median, unless the re-scoring's polished
    winner scores significantly lower than the median's own polished floor on further fresh
    canopies: ``select.guard``) or ``floors`` (opt-in: every seed polishes its own point in its
    own run, every candidate's floor is ranked on fresh canopies and the lowest is guarded
    against the median's floor: ``select.floors``). None: the crop's default,
    ``DEFAULT_COMBINE`` (soybean with its node count given: the mean,
    ``DEFAULT_COMBINE_GIVEN``). The baselines
    follow the paper: random takes the mean, trust-region the lowest-loss seed."""
    reevaluate_canopies: int = 16
    """Fresh canopies (the same for every candidate) each ``reevaluate`` candidate is scored on."""
    polish_starts: int = 1
    """``reevaluate``: how many of the lowest re-scored candidates are then refined by
    Nelder-Mead on the same canopies (``fit/select.py``, where the measurements are)."""
    polish_evals: int = 60
    """``reevaluate``, ``guarded``, ``floors``: loss evaluations (each on
    ``reevaluate_canopies`` canopies) per polished candidate; 0: no polishing."""
    n_evals: int = 500
    """Objective evaluations per seed (bo, random, trust-region). Trust-region: its
    iterations are capped at this too (the paper's 500), but the evaluations cap it first
    (2-point differences: ~6 evaluations an iteration in 5-D, so ~83 iterations), so that
    each method gets a BO seed's budget; one start per seed, the lowest-loss seed's answer
    (the paper's 10 starts)."""
    n_initial: int = 200
    """Random initial evaluations of a BO seed."""
    box: dict[str, Any] = field(default_factory=dict, hash=False)
    """What is already known of the parameters: name → a value (fixed, not fitted; e.g. the
    main-stem nodes counted in the field) or ``[low, high]`` inside the model's range. The
    optimisers search the remaining box (``ParamBox``); empty: the crop's whole box."""
    common_random_numbers: bool = True
    """Same canopy seed for every evaluation of an optimiser seed (see module docstring)."""
    refit_every: int = 10
    """GP hyper-parameter refit period of BO."""
    gp_output: str | None = None
    """What BO's GP models: ``none`` (the loss) or ``log`` (its logarithm; ``BOConfig.
    output_transform``). None: the crop's default, ``DEFAULT_GP_OUTPUT`` (the loss where the
    loss estimator is ``unbiased``, which can be negative)."""
    local_share: float | None = None
    """The share of a BO seed's ``n_evals`` (at most those after the initial design) spent
    last on a Nelder-Mead search from its lowest point (``BOConfig.local_evals``). None: the
    crop's default, ``DEFAULT_LOCAL_SHARE``."""
    canopies_per_eval: int | None = None
    """Procedural canopies (seeds) whose histograms are averaged per evaluation, so that the
    predicted statistics estimate the parameters' expected statistics with 1/K of the variance.
    None: the crop's default, ``DEFAULT_CANOPIES`` (measured on a soybean observation at its
    true parameters over 6 draws: loss 0.123 ± 0.064 with K = 1, 0.079 ± 0.023 with K = 2,
    0.072 ± 0.028 with K = 4; maize's loss noise is ~0.0002, so K = 1)."""

    loss_estimator: str = "pooled"
    """How an evaluation's loss over several canopies is estimated (``ForwardModel.estimator``):
    ``pooled`` (the loss of their mean statistics: the paper's and the default) or
    ``unbiased`` (its U-statistic, without the predictions' own draw variance, which favours
    parameters whose canopies vary less). Applies to the seeds' objective (with
    ``canopies_per_eval`` >= 2), the re-scoring and polish, and the guard's and floors'
    checks (the U-statistic's jackknife pseudo-values, ``select._per_canopy``)."""

    def resolved(self, crop: str) -> FitConfig:
        """This config with every setting left to ``crop``'s default (None) written out:
        ``combine`` (``default_combine``), ``gp_output`` (``DEFAULT_GP_OUTPUT``),
        ``canopies_per_eval`` (``DEFAULT_CANOPIES``) and ``local_share``
        (``DEFAULT_LOCAL_SHARE``). The one place those defaults are read: the
        fit uses it, and the flows hash it so that a release changing a default recomputes."""
        gp_output = self.gp_output
        if gp_output is None:
            gp_output = "none" if self.loss_estimator == "unbiased" else DEFAULT_GP_OUTPUT[crop]
        return replace(
            self,
            combine=self.combine or default_combine(crop, self.box),
            gp_output=gp_output,
            canopies_per_eval=self.canopies_per_eval or DEFAULT_CANOPIES[crop],
            local_share=DEFAULT_LOCAL_SHARE[crop] if self.local_share is None else self.local_share,
        )

    def canopies(self, crop: str) -> int:
        return self.resolved(crop).canopies_per_eval

    def combine_rule(self, crop: str) -> str:
        return self.resolved(crop).combine

    def reevaluates(self, crop: str) -> bool:
        """Whether :func:`combine` re-scores candidates (and so needs the observation)."""
        return self.method == "bo" and self.combine_rule(crop) in RESCORING_RULES

    def param_box(self, crop: str) -> ParamBox:
        """The box the optimisers search for ``crop`` (checked: ``ParamBox.of``)."""
        return ParamBox.of(crop, self.box)

    def validate(self) -> FitConfig:
        if not isinstance(self.box, dict):
            raise ConfigError(
                f"box must map parameter names to a value or [low, high], got {self.box!r}"
            )
        if self.method not in METHODS:
            raise ConfigError(f"unknown method {self.method!r}: choose one of {', '.join(METHODS)}")
        for name in (
            "n_seeds", "n_evals", "n_initial", "refit_every", "reevaluate_canopies",
            "polish_starts", "polish_evals", "canopies_per_eval",
        ):  # fmt: skip
            v = getattr(self, name)
            if v is None and name == "canopies_per_eval":
                continue
            if not isinstance(v, int | np.integer) or isinstance(v, bool):
                raise ConfigError(f"{name} must be a whole number, got {v!r}")
        share = self.local_share
        if share is not None and (not isinstance(share, int | float) or isinstance(share, bool)):
            raise ConfigError(f"local_share must be a number in [0, 1] or null, got {share!r}")
        if self.canopies_per_eval is not None and self.canopies_per_eval < 1:
            raise ConfigError(f"canopies_per_eval must be at least 1, got {self.canopies_per_eval}")
        if self.combine is not None and self.combine not in COMBINE_RULES:
            raise ConfigError(
                f"unknown combine rule {self.combine!r}: choose one of {', '.join(COMBINE_RULES)}"
            )
        if self.reevaluate_canopies < 1:
            raise ConfigError(
                f"reevaluate_canopies must be at least 1, got {self.reevaluate_canopies}"
            )
        if self.polish_starts < 1 or self.polish_evals < 0:
            raise ConfigError(
                f"need polish_starts >= 1 (got {self.polish_starts}) and polish_evals >= 0 "
                f"(got {self.polish_evals})"
            )
        if self.local_share is not None and not 0.0 <= self.local_share <= 1.0:
            raise ConfigError(f"local_share must be in [0, 1], got {self.local_share}")
        if self.gp_output is not None and self.gp_output not in OUTPUT_TRANSFORMS:
            raise ConfigError(
                f"unknown gp_output {self.gp_output!r}: "
                f"choose one of {', '.join(OUTPUT_TRANSFORMS)}"
            )
        if self.loss_estimator not in ESTIMATORS:
            raise ConfigError(
                f"unknown loss_estimator {self.loss_estimator!r}: "
                f"choose one of {', '.join(ESTIMATORS)}"
            )
        if self.loss_estimator == "unbiased" and self.gp_output == "log":
            raise ConfigError(
                "gp_output='log' models the loss's logarithm, but the unbiased loss estimator "
                "can be negative: use gp_output='none' with it"
            )
        if self.n_seeds < 1:
            raise ConfigError(f"n_seeds must be at least 1, got {self.n_seeds}")
        if self.n_evals < 2:
            raise ConfigError(f"n_evals must be at least 2, got {self.n_evals}")
        if self.method == "bo" and not 2 <= self.n_initial <= self.n_evals:
            raise ConfigError(
                f"need 2 <= n_initial ({self.n_initial}) <= n_evals ({self.n_evals}): n_initial "
                "is BO's initial design"
            )
        return self

    def bo_config(self, crop: str) -> BOConfig:
        return BOConfig(
            n_evals=self.n_evals,
            n_initial=self.n_initial,
            refit_every=self.refit_every,
            output_transform=self.resolved(crop).gp_output,
            local_evals=self.local_evals(crop),
        )

    def local_evals(self, crop: str) -> int:
        """BO's closing local-search evaluations: the share (``local_share`` or the crop's
        default) of ``n_evals``, at most those after the initial design."""
        share = self.resolved(crop).local_share
        return min(round(share * self.n_evals), self.n_evals - self.n_initial)

    def papers_optimiser(self, crop: str) -> bool:
        """Whether BO runs as the paper's: the GP on the loss itself, no closing local search
        (so a seed fitted before these settings existed is the same fit). The other methods
        have no GP: theirs is the paper's whatever these settings say."""
        if self.method != "bo":
            return True
        return self.resolved(crop).gp_output == "none" and self.local_evals(crop) == 0

    def to_dict(self) -> dict:
        return asdict(self)


def canopy_seed(optimiser_seed: int, eval_index: int, crn: bool) -> int:
    return (
        CANOPY_SEED_BASE + optimiser_seed
        if crn
        else ((CANOPY_SEED_BASE + optimiser_seed) * 1_000_003 + eval_index) % (2**31)
    )


def make_objective(
    forward: ForwardModel,
    optimiser_seed: int,
    crn: bool,
    canopies: int = 1,
    box: ParamBox | None = None,
) -> Callable[[np.ndarray, int], float]:
    """The loss of the free parameters ``x`` (``box``: the crop's whole box by default)."""
    box = box or ParamBox.of(forward.crop)

    def objective(x: np.ndarray, eval_index: int) -> float:
        params = box.params(x)
        base = canopy_seed(optimiser_seed, eval_index, crn)
        seeds = [base + 104_729 * k for k in range(canopies)]
        return forward.loss(params, seeds)

    return objective


class SeedObjective(NamedTuple):
    """What one seed optimises: ``objective(x, eval_index)``, the ``box`` it searches and the
    ``forward`` model behind it (its timings)."""

    objective: Callable[[np.ndarray, int], float]
    box: ParamBox
    forward: ForwardModel


def seed_objective(
    observation: Observation,
    seed: int,
    config: FitConfig,
    layout: CanopyLayout | None = None,
) -> SeedObjective:
    """Seed ``seed``'s objective under ``config`` (its loss estimator, canopies per evaluation,
    common random numbers): what :func:`fit_seed` optimises, and what a benchmark gives another
    optimiser to compare on the same objective."""
    forward = ForwardModel(observation, layout, config.loss_estimator)
    box = config.param_box(observation.crop)
    canopies = config.canopies(observation.crop)
    objective = make_objective(forward, seed, config.common_random_numbers, canopies, box)
    return SeedObjective(objective, box, forward)


def seed_identity(
    observation: Observation,
    config: FitConfig,
    box: ParamBox,
    layout: CanopyLayout | None = None,
) -> str:
    """sha256 of everything a seed's evaluations depend on besides its seed and the optimiser's
    own settings: the observation (camera, preset, depth, mask, statistics), the fit settings
    that shape the objective (not the answer rule's), the parameter box with its fixed values,
    and the planting layout. A checkpoint records it, so
    one of another observation or config is refused, not resumed."""
    import hashlib
    import json

    crop = observation.crop
    cfg = config.resolved(crop).to_dict()
    # not the seed count, nor the answer rule's settings: a floors seed's polish is checked
    # against its own record (``seed_floor``), so a new polish reuses the search
    for k in ("n_seeds", *AGGREGATE_ONLY):
        cfg.pop(k, None)
    head = {
        "crop": crop,
        "camera": observation.camera.to_dict(),
        "preset": observation.preset.to_dict(),
        "box_mask": bool(observation.box_mask),
        "config": cfg,
        "box": [box.low.tolist(), box.high.tolist()],
        "layout": None if layout is None else layout.to_dict(),
    }
    h = hashlib.sha256(json.dumps(head, sort_keys=True, default=str).encode())
    st = observation.stats
    for a in (observation.depth, observation.mask, st.depth, st.lateral, st.sobel):
        h.update(np.ascontiguousarray(a).tobytes())
    h.update(np.float64(st.mask_area).tobytes())
    return h.hexdigest()


def fit_seed(
    observation: Observation,
    seed: int,
    config: FitConfig | None = None,
    layout: CanopyLayout | None = None,
    checkpoint: str | Path | None = None,
    callback: Callable[[int, np.ndarray, float], None] | None = None,
) -> SeedResult:
    """One optimiser seed against ``observation``: pure and resumable (``checkpoint``). Under
    ``combine="floors"`` a BO seed then polishes its own reported point on the re-scoring's
    canopies (``select.seed_floor``, ``SeedResult.floor``) and checkpoints it, so that the fit's
    combining step only ranks the floors."""
    cfg = (config or FitConfig()).validate()
    if cfg.method == "mlp":
        raise ConfigError("the mlp method predicts directly: use cropcraft_core.fit.mlp")
    objective, box, forward = seed_objective(observation, seed, cfg, layout)
    b = box.bounds
    # a checkpoint of another observation, config, box or layout is refused, not resumed
    run_id = seed_identity(observation, cfg, box, layout) if checkpoint is not None else None
    if cfg.method == "bo":
        res = run_seed(
            objective,
            b,
            cfg.bo_config(observation.crop),
            seed=seed,
            checkpoint=checkpoint,
            callback=callback,
            run_id=run_id,
        )
    elif cfg.method == "random":
        res = run_random(
            objective,
            b,
            n_evals=cfg.n_evals,
            seed=seed,
            checkpoint=checkpoint,
            callback=callback,
            run_id=run_id,
        )
    else:
        res = run_trust_region(
            objective,
            b,
            seed=seed,
            n_starts=1,
            maxiter=cfg.n_evals,
            # the same evaluation budget as a BO seed (uncapped, one start made ~13,700 calls)
            max_evals=cfg.n_evals,
            checkpoint=checkpoint,
            callback=callback,
            run_id=run_id,
        )
    if cfg.method == "bo" and cfg.combine_rule(observation.crop) == "floors":
        from cropcraft_core.fit.select import seed_floor

        floored = seed_floor(forward, res, cfg.reevaluate_canopies, cfg.polish_evals, box)
        if floored is not res and checkpoint is not None:
            floored.save(checkpoint)
        res = floored
    res.extra = {**getattr(res, "extra", {}), "forward_timings": dict(forward.timings)}
    return res


@dataclass
class FitResult:
    """The fit of one observation: final parameters, their spread over seeds, every seed."""

    crop: str
    method: str
    params: dict[str, float]
    params_std: dict[str, float]
    seed_params: list[dict[str, float]]
    seed_losses: list[float]
    seconds: float
    config: dict
    extra: dict = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def combine(
    crop: str,
    results: list[SeedResult],
    config: FitConfig,
    seconds: float,
    observation: Observation | None = None,
    layout: CanopyLayout | None = None,
    selection: Selection | None = None,
) -> FitResult:
    """One answer from per-seed results. BO: ``config.combine_rule`` (``reevaluate`` needs the
    ``observation`` the seeds were fitted to, and their ``layout``); random: the paper's mean of
    the seeds' best parameters; trust-region: the lowest-loss seed's. ``params_std`` is always
    the spread of the seeds' best points; ``extra["selection"]`` holds every re-scored candidate.
    ``selection``: the re-scoring already made on these ``results`` and this observation under
    ``config``'s re-scoring options (:func:`select`; benchmarks share one between the rules that
    re-score), used instead of re-scoring again; its seconds are still counted. ``floors``
    records every floor under ``extra["floors"]`` and re-scores nothing else."""
    if not results:
        raise ConfigError("no seed results to combine")
    config = config.validate()
    if observation is not None and observation.crop != crop:
        raise ConfigError(f"observation is of {observation.crop}, the seeds of {crop}")
    box = config.param_box(crop)
    for r in results:
        if r.bounds.shape != box.bounds.shape or not np.allclose(r.bounds, box.bounds):
            raise ConfigError(
                f"seed {r.seed} searched {r.bounds.tolist()}, the box ({', '.join(box.names)}) "
                f"is {box.bounds.tolist()}: it was fitted under another parameter box"
            )
    per_seed = [box.params(r.reported_x) for r in results]
    losses = [float(r.best_y) for r in results]
    agg = aggregate(results)
    extra: dict[str, Any] = {}
    if not all(np.isfinite(losses)) or not all(np.isfinite(r.reported_x).all() for r in results):
        bad = [
            r.seed
            for r in results
            if not (np.isfinite(r.best_y) and np.isfinite(r.reported_x).all())
        ]
        raise InputError(f"seed result(s) {bad} hold a non-finite loss or answer (damaged?)")
    if config.method == "trust-region":
        best = int(np.argmin(losses))
        final = results[best].reported_x
        std = agg.std_x  # the seeds' spread, as every rule reports it (was 0: "SD 0")
    elif config.reevaluates(crop):
        rule = config.combine_rule(crop)
        if observation is None:
            raise ConfigError(
                f"combine={rule!r} re-scores candidates against the observation: pass it "
                "(or use combine='mean', the paper's rule)"
            )
        from cropcraft_core.fit import select as sl

        forward = ForwardModel(observation, layout, config.loss_estimator)
        k_canopies, evals = config.reevaluate_canopies, config.polish_evals
        if rule == "floors":
            fl = sl.floors(forward, results, k_canopies, evals, box)
            final, std = fl.x, agg.std_x
            extra["floors"] = fl.to_dict(box)
            seconds += fl.seconds
        else:

            def selected(fm: ForwardModel = forward) -> sl.Selection:
                return selection or sl.select(
                    fm, results, k_canopies, config.polish_starts, evals, box=box
                )

            floor = None
            if rule == "guarded" and selection is None and evals > 0:
                # the median's floor needs no re-scoring: made beside it, in a second thread
                seeds = sl.reevaluation_seeds(k_canopies)
                sel, floor = sl.beside(
                    forward, selected, lambda fm: sl.median_floor(fm, results, seeds, evals, box)
                )
            else:
                sel = selected()
            final, std = sel.x, agg.std_x
            extra["selection"] = sel.to_dict(box)
            seconds += sel.seconds
            if rule == "guarded":
                g = sl.guard(forward, results, sel, evals, box, floor=floor)
                final = g.x
                extra["guard"] = g.to_dict(box)
                seconds += g.seconds
    elif config.method == "bo" and config.combine_rule(crop) == "median":
        final, std = np.median(agg.per_seed, axis=0), agg.std_x
    else:
        final, std = agg.mean_x, agg.std_x
    return FitResult(
        crop=crop,
        method=config.method,
        params=box.params(final),
        params_std=box.spread(std),
        seed_params=per_seed,
        seed_losses=losses,
        seconds=seconds,
        config=config.to_dict(),
        extra=extra,
    )


def _combine_job(args) -> FitResult:
    """:func:`combine` on (crop, results, config, seconds, observation, layout), for a pool."""
    return combine(*args)


def _fit_seed_job(args) -> SeedResult:
    """:func:`fit_seed` on (observation, seed, config, layout, checkpoint): a module-level
    function, so that a process pool can run it."""
    return fit_seed(*args)


def fit_observation(
    observation: Observation,
    config: FitConfig | None = None,
    layout: CanopyLayout | None = None,
    checkpoint_dir: str | Path | None = None,
    seeds: list[int] | None = None,
    executor=None,
) -> FitResult:
    """Every seed in turn in this process, or spread over ``executor`` (anything with
    ``map``: :func:`cropcraft_core.parallel.pool`'s processes, which ``cropcraft fit
    --workers`` makes; the Prefect flow maps ``fit_seed`` as tasks instead). The seeds'
    results are combined in seed order either way; ``mlp`` makes its training pairs there."""
    cfg = (config or FitConfig()).validate()
    t = time.perf_counter()
    if cfg.method == "mlp":
        from cropcraft_core.fit.mlp import predict_params

        # the network predicts every parameter; what the user knows replaces its guess
        params = cfg.param_box(observation.crop).clip(
            predict_params(observation, layout=layout, executor=executor)
        )
        zero = {k: 0.0 for k in params}
        return FitResult(
            observation.crop,
            "mlp",
            params,
            zero,
            [params],
            [float("nan")],
            time.perf_counter() - t,
            cfg.to_dict(),
        )
    seeds = list(range(cfg.n_seeds)) if seeds is None else seeds
    jobs = [
        (
            observation,
            s,
            cfg,
            layout,
            Path(checkpoint_dir) / f"seed-{s}.json" if checkpoint_dir else None,
        )
        for s in seeds
    ]
    results = list(run_jobs(executor, _fit_seed_job, jobs))
    return combine(observation.crop, results, cfg, time.perf_counter() - t, observation, layout)


def fit_observations(
    observations: list[Observation],
    config: FitConfig | None = None,
    layout: CanopyLayout | None = None,
    executor=None,
) -> list[FitResult]:
    """Several observations of one plot (its rows) under one config, each answer the one
    :func:`fit_observation` gives that observation alone. Every seed of every observation goes
    to ``executor`` in one map, and then every observation's combination (re-scoring, guard)
    in another, so that the rows finish together instead of one after another (no process
    idles at the end of one row's seeds). Each result's ``seconds``: the wall time of the
    shared seed stage plus its own combination's."""
    cfg = (config or FitConfig()).validate()
    if cfg.method == "mlp":  # one prediction each; the network is trained (or loaded) once
        return [fit_observation(o, cfg, layout=layout, executor=executor) for o in observations]
    t = time.perf_counter()
    seeds = range(cfg.n_seeds)
    jobs = [(o, s, cfg, layout, None) for o in observations for s in seeds]
    results = list(run_jobs(executor, _fit_seed_job, jobs))
    seconds = time.perf_counter() - t
    n = cfg.n_seeds
    combos = [
        (o.crop, results[i * n : (i + 1) * n], cfg, seconds, o, layout)
        for i, o in enumerate(observations)
    ]
    return list(run_jobs(executor, _combine_job, combos))


#: Where the answer presses the search box: within this share of a parameter's range of one
#: of its ends, on at least :data:`EDGE_WARN_PARAMS` fitted parameters at once.
EDGE_SHARE = 0.01
EDGE_WARN_PARAMS = 2


def edge_warning(
    crop: str, params: Mapping[str, float], box: Mapping[str, object] | None = None
) -> str | None:
    """A warning where the answer ``params`` lies on the edge of the box searched (the crop's
    box narrowed by ``box``, the fit's ``fit.box``) for :data:`EDGE_WARN_PARAMS` or more of
    its fitted parameters: the best the model could do was its limit, as when the photos show
    another crop (a maize canopy fitted as soybean pressed three at once, reading LAI +26 %
    and leaf angles 30° off with nothing said) or a scale far off. None otherwise."""
    from cropcraft_core.config.params import ParamBox

    pb = ParamBox.of(crop, box)
    at = []
    for name, (low, high) in zip(pb.names, pb.bounds, strict=True):
        v, tol = float(params[name]), EDGE_SHARE * (high - low)
        if v <= low + tol or v >= high - tol:
            at.append(f"{name} {v:.4g} (searched {low:g} to {high:g})")
    if len(at) < EDGE_WARN_PARAMS:
        return None
    return (
        f"the answer lies on the edge of the {crop} parameter box for {', '.join(at)}: the "
        "model could not go as far as the photos asked; is the crop right, the scale "
        "(rows, camera height) and the row spacing (--row-spacing)? Weeds, straw or stakes in "
        "the rows pull the answer too"
    )
