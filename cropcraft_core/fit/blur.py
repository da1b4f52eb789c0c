"""How soft an observation's leaves are, measured against the fit's own good points.

A fused reconstruction can soften the leaves near their edges (RESULTS *#blur*): on one canopy
(C, 1.1 m tall) blurring the *true mesh's* depth by 6 mm brings its statistics 2.7 times closer to
the observation's; on three others (D, E, F) any blur moves them away. A fixed blur of the predictions
(``ObservePreset.prediction_blur_m``) helps the first kind and hurts the second, so the blur has
to be measured per observation. The truth is not known, but the fit's good points are: the seeds'
best parameters, found with unblurred predictions. :func:`blur_profile` scores each of them
against the observation with its predictions blurred by each width of a grid, on the same
canopies; :meth:`BlurProfile.choose` takes the width whose loss, relative to no blur and averaged
over the points, is lowest, and no blur unless that is a clear gain (:data:`MIN_GAIN`). The
points were fitted unblurred and absorb some of the softness in their parameters, so the width
measured from them errs low (C's seeds: 1.5 mm where its true parameters' canopies say 6).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from cropcraft_core.config import CanopyLayout
from cropcraft_core.errors import ConfigError
from cropcraft_core.observe import Observation, loss, mean_stats, with_overrides

#: Blur widths (metres at the observed canopy's median depth) a profile scores, no blur first.
BLUR_SIGMAS_M = (0.0, 0.0015, 0.003, 0.0045, 0.006, 0.009)
#: Canopy seeds each point is scored on (pooled): past the optimiser's and re-scoring's seeds.
BLUR_CANOPIES = tuple(range(2000, 2008))
#: A width is chosen only where its mean relative loss is at least this much below no blur's:
#: C's profile dipped 13 % at 3 mm, F's (whose true mesh wants no blur) 1.4 % at 1.5 mm.
MIN_GAIN = 0.05


@dataclass(frozen=True)
class BlurProfile:
    """Losses of parameter points with their predictions blurred by each width.

    sigmas_m: the widths, no blur first. losses: (points, widths) pooled losses on the same
    canopies. sigma_px_per_m: the observation's pixels per metre of blur."""

    sigmas_m: tuple[float, ...]
    losses: np.ndarray
    sigma_px_per_m: float

    @property
    def relative(self) -> np.ndarray:
        """(widths,) each width's loss over no blur's, averaged over the points."""
        return (self.losses / self.losses[:, :1]).mean(axis=0)

    def choose(self, min_gain: float = MIN_GAIN) -> float:
        """The width (metres) with the lowest mean relative loss, or 0 when that is less than
        ``min_gain`` below no blur's."""
        rel = self.relative
        j = int(np.argmin(rel))
        return float(self.sigmas_m[j]) if 1.0 - rel[j] >= min_gain else 0.0

    def to_dict(self) -> dict:
        return {
            "sigmas_m": list(self.sigmas_m),
            "losses": self.losses.round(6).tolist(),
            "relative": self.relative.round(4).tolist(),
            "sigma_px_per_m": self.sigma_px_per_m,
            "chosen_m": self.choose(),
        }


def blur_profile(
    observation: Observation,
    points: Sequence[Mapping[str, float]],
    sigmas_m: Sequence[float] = BLUR_SIGMAS_M,
    canopies: Sequence[int] = BLUR_CANOPIES,
    layout: CanopyLayout | None = None,
) -> BlurProfile:
    """Each of ``points`` (parameters by name) scored against ``observation`` with its
    predictions blurred by each of ``sigmas_m`` (the observation's own blur replaced), the
    canopies ``canopies`` rendered once per point and pooled per width. ``ConfigError`` for no
    points, no canopies, or widths that do not start at 0 or are negative."""
    from cropcraft_core.fit.forward import ForwardModel

    sigmas = tuple(float(s) for s in sigmas_m)
    if not points:
        raise ConfigError("a blur profile needs at least one parameter point")
    if not canopies:
        raise ConfigError("a blur profile needs at least one canopy seed")
    if not sigmas or sigmas[0] != 0.0 or min(sigmas) < 0:
        raise ConfigError(f"blur widths must start at 0 and be >= 0, got {list(sigmas_m)}")
    views = [
        dataclasses.replace(
            observation, preset=with_overrides(observation.preset, prediction_blur_m=s)
        )
        for s in sigmas
    ]
    model = ForwardModel(views[0], layout)
    out = np.empty((len(points), len(sigmas)))
    for i, params in enumerate(points):
        per = [[] for _ in sigmas]
        for seed in canopies:
            depth = model.depth(params, int(seed))
            for j, view in enumerate(views):
                per[j].append(view.predicted_stats(depth))
        for j in range(len(sigmas)):
            out[i, j] = loss(observation.stats, mean_stats(per[j]), observation.preset).total
    z = float(np.median(observation.depth[observation.mask]))
    return BlurProfile(sigmas, out, float(observation.camera.fy) / z)
