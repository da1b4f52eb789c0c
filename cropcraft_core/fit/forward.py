"""The forward model of a fit: parameters → procedural canopy → row-camera depth → statistics.

The predicted canopy is planted in the row frame (rows along x, one row under the camera at
y = 0) and rendered from the observation's row camera moved over the origin; only the plants that
can appear in the image are built (``view_region``), so one evaluation is one small
``generate_canopy`` and one raster pass. The predicted mask is every rendered pixel: no
background is rendered (supplementary "Mask and Histogram Details").
"""

from __future__ import annotations

import threading
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from cropcraft_core.config import CanopyLayout, default_layout, resolve_params
from cropcraft_core.errors import ConfigError
from cropcraft_core.geometry import PinholeCamera
from cropcraft_core.observe import HistogramStats, Observation, mean_stats, observe_views
from cropcraft_core.procedural import Canopy, generate_canopy, max_reach, view_region
from cropcraft_core.render.raster import depth_map

#: :attr:`ForwardModel.estimator` values.
ESTIMATORS = ("pooled", "unbiased")


class Stopped(RuntimeError):
    """A :class:`ForwardModel` was asked for a canopy after its ``stop`` event was set: the
    work it served was called off (``cropcraft_core.fit.select.beside``)."""


def row_frame_camera(camera: PinholeCamera) -> PinholeCamera:
    """``camera``'s intrinsics and height above the ground, over the origin, looking straight
    down with image x along +x: where the predicted canopy's centre row runs."""
    pose = PinholeCamera.look_down((0.0, 0.0), float(camera.center[2])).cam_to_world
    return PinholeCamera(
        camera.width, camera.height, camera.fx, camera.fy, camera.cx, camera.cy, pose
    )


@dataclass
class ForwardModel:
    """Renders procedural canopies exactly as ``observation`` was rendered.

    layout: planting (row spacing, density); its row azimuth is ignored (the prediction is built
    in the row frame) and so is its plot size (the view decides which plants are built).
    ``timings`` accumulates seconds spent per stage over all calls.
    """

    observation: Observation
    layout: CanopyLayout | None = None
    estimator: str = "pooled"
    """How the loss of several canopies is estimated (:meth:`loss`): ``pooled`` (the loss of
    their mean statistics) or ``unbiased`` (its U-statistic, which removes the predictions'
    own draw variance)."""
    timings: dict[str, float] = field(
        default_factory=lambda: {"generate": 0.0, "render": 0.0, "stats": 0.0, "calls": 0}
    )
    stop: threading.Event | None = field(default=None, repr=False, compare=False)
    """Once set, every further canopy raises :class:`Stopped` (a second thread's work whose
    caller failed ends at its next canopy instead of running to its end)."""

    def __post_init__(self) -> None:
        if self.estimator not in ESTIMATORS:
            raise ConfigError(
                f"unknown loss estimator {self.estimator!r}: choose one of {', '.join(ESTIMATORS)}"
            )
        crop = self.observation.crop
        self.layout = (self.layout or default_layout(crop)).with_(row_azimuth_deg=0.0)
        self.camera = row_frame_camera(self.observation.camera)

    @property
    def crop(self) -> str:
        return self.observation.crop

    def canopy(self, params: Mapping[str, float], seed: int, culled: bool = False) -> Canopy:
        """The predicted canopy: the plants whose parts can reach into the row camera's view;
        with ``culled``, without the organs wholly outside it (for rendering only: the same
        depth map to the bit in about half the generation time, ``generate_canopy``'s
        ``view``)."""
        p = resolve_params(self.crop, params)
        region = view_region(self.camera, self.layout, max_reach(self.crop, p))
        view = self.camera if culled else None
        return generate_canopy(self.crop, p, self.layout, seed=seed, region=region, view=view)

    def depth(self, params: Mapping[str, float], seed: int) -> np.ndarray:
        """(H, W) float32 z-depth of the predicted canopy, NaN where nothing is rendered."""
        if self.stop is not None and self.stop.is_set():
            raise Stopped("the work this forward model served was called off")
        t0 = time.perf_counter()
        c = self.canopy(params, seed, culled=True)
        t1 = time.perf_counter()
        d = depth_map(c.mesh.vertices, c.mesh.faces, self.camera)
        self.timings["generate"] += t1 - t0
        self.timings["render"] += time.perf_counter() - t1
        return d

    def stats(self, params: Mapping[str, float], seed: int | Sequence[int]) -> HistogramStats:
        """Statistics of the canopy built with ``seed``; with several seeds, the mean of their
        statistics (histograms and mask area averaged bin by bin)."""
        seeds = [seed] if isinstance(seed, int | np.integer) else list(seed)
        out = []
        for s in seeds:
            d = self.depth(params, int(s))
            t = time.perf_counter()
            out.append(self.observation.predicted_stats(d))
            self.timings["stats"] += time.perf_counter() - t
            self.timings["calls"] += 1
        return mean_stats(out)  # one canopy's statistics as they are

    def loss(self, params: Mapping[str, float], seed: int | Sequence[int]) -> float:
        """The loss of the canopies built with ``seed`` (one or several). ``pooled``: the loss
        of their mean statistics, whose expectation over canopies is the squared distance of
        the parameters' expected statistics from the observation plus the trace of one
        canopy's statistics' covariance over K, so that parameters whose canopies vary less
        from draw to draw score lower at the same distance. ``unbiased`` (K >= 2): the
        U-statistic ``(K L(mean) - mean_k L(s_k)) / (K - 1)``, i.e. the mean over pairs of
        canopies j != k of the loss's bilinear form of ``s_j - o`` and ``s_k - o`` (the loss is
        a weighted sum of squares), whose expectation is that distance alone; it can be
        negative. With one canopy both are the loss."""
        from cropcraft_core.observe import loss

        o, p = self.observation.stats, self.observation.preset
        seeds = [seed] if isinstance(seed, int | np.integer) else list(seed)
        if self.estimator == "pooled" or len(seeds) < 2:
            return loss(o, self.stats(params, seeds), p).total
        return unbiased_loss(self.observation, [self.stats(params, s) for s in seeds])


def unbiased_loss(observation: Observation, each: Sequence[HistogramStats]) -> float:
    """The loss's U-statistic over the statistics ``each`` of K >= 2 canopies of one parameter
    point: ``(K L(mean) - mean_k L(s_k)) / (K - 1)`` (:meth:`ForwardModel.loss`, ``unbiased``)."""
    from cropcraft_core.observe import loss

    o, p = observation.stats, observation.preset
    k = len(each)
    if k < 2:
        raise ConfigError(f"the unbiased loss needs at least 2 canopies, got {k}")
    per = float(np.mean([loss(o, s, p).total for s in each]))
    return float((k * loss(o, mean_stats(each), p).total - per) / (k - 1))


def unbiased_pseudovalues(observation: Observation, each: Sequence[HistogramStats]) -> np.ndarray:
    """The jackknife pseudo-values ``K U - (K - 1) U_(-j)`` of the loss's U-statistic ``U``
    (:func:`unbiased_loss`) over the statistics ``each`` of K >= 3 canopies (``U_(-j)``:
    without canopy j). Their mean is ``U`` exactly and their standard deviation over sqrt(K)
    its jackknife standard error, so they compare two parameter points scored on the same
    canopies value by value, every pair of canopies counted (taking disjoint pairs instead
    keeps K/2 of the K(K-1)/2 cross terms, and near the observation, where the cross terms
    are pure draw noise, their mean varies about K/4 times more)."""
    k = len(each)
    if k < 3:
        raise ConfigError(f"the unbiased loss needs at least 3 canopies for its jackknife, got {k}")
    full = unbiased_loss(observation, each)
    return np.array(
        [
            k * full - (k - 1) * unbiased_loss(observation, [*each[:j], *each[j + 1 :]])
            for j in range(k)
        ],
        dtype=np.float64,
    )


def observe_canopy(
    canopy: Canopy, observation_preset, camera: PinholeCamera | None = None, meta=None
) -> Observation:
    """A synthetic observation: ``canopy`` rendered from the row camera (default: the preset's,
    over the origin) with no background, its mask the finite depth and no box (``box_mask``
    False, so neither are the predictions cut) — the paper's synthetic-scene protocol. Where
    the preset pools several row cameras (``views_along``, ``views_across``), the canopy is
    rendered from each, its rows ``canopy.layout.row_spacing`` apart
    (:func:`~cropcraft_core.observe.observe_views`)."""
    cam = camera or observation_preset.row_camera()

    def view(dx: float, dy: float):
        c = cam.shifted(dx, dy)
        d = depth_map(canopy.mesh.vertices, canopy.mesh.faces, c)
        return c, d, np.isfinite(d), None

    return observe_views(
        canopy.crop,
        observation_preset,
        view,
        canopy.layout.row_spacing,
        meta=meta,
        box_mask=False,
    )
