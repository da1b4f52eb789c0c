"""Metric scale of structure-from-motion poses from the photos' own GPS positions.

Every drone photo, and most phone photos, carry the camera's position in EXIF (latitude,
longitude, altitude; read by :func:`cropcraft_core.sfm.ingest.exif_gps`). SfM's camera centres
are the same positions up to a similarity, so the similarity's scale (metres per SfM unit) is
the metric scale, with no camera height or row spacing assumed: it tells a drone 25 m up from
one 13 m up, which the rows' period cannot (their double period), and a soybean flight from a
phone held over the plot, which nothing else in the photos can.

It is only as good as the positions' spread against their error. Consumer GPS is off by metres
in absolute terms, but a flight's fixes move together (the error drifts slowly), so over a
flight line tens of metres long the relative positions hold to a few decimetres; a phone walked
round a 2 m plot spreads less than its GPS errs. :func:`gps_scale` therefore fits the similarity
robustly (pycolmap's LO-RANSAC, :func:`pycolmap.estimate_sim3d_robust`), then measures how
well the photos determine the scale: a *block jackknife* over contiguous runs of photos in
capture order (so a drifting error shared by neighbouring photos counts as one, not as many
independent ones) gives its relative standard error, and the scale is used only where that is
at most :data:`MAX_RELATIVE_SE` and most photos agree with the fit. A bias every block
shares escapes the jackknife: a fix drifting steadily through a lawnmower flight (time runs
across its lines) stretches the flight across them, and two flights merged, each with its own
altitude offset, stretch it vertically; a similarity absorbs neither into its residual (a
helper's audit: 8-15 % scale errors accepted at a reported 2-3 %). So the fixes must also be a
similarity's and not a stretched one's: an affine fit's scale along each direction the
cameras spread in must agree with the similarity's within :data:`MAX_ANISOTROPY`. A GPS that
cannot set the scale is said (``reason``) and the poses keep the scale they would have had
without it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from cropcraft_core.errors import InputError

#: The scale's relative standard error (block jackknife) above which the GPS does not set it.
#: A scene's LAI goes with the square of its scale (the fitted leaves grow with the scene while
#: the planting layout stays metric), so 3 % is about 6 % of LAI at one standard error.
MAX_RELATIVE_SE = 0.03
#: Photos with a GPS position, among the posed ones, below which the GPS is not tried.
MIN_PHOTOS = 8
#: Share of those photos the robust fit must keep (the others' fixes jumped).
MIN_INLIER_FRACTION = 0.8
#: Contiguous blocks of photos in capture order for the jackknife (fewer with few photos).
JACKKNIFE_BLOCKS = 8
#: The most an affine fit of the fixes may stretch or shrink them, along any direction the
#: cameras spread in, against the similarity (a drift or offset a similarity cannot show):
#: an RTK flight read 0.1 %, a 1.5 m drift through an 8 m flight 15.8 % (its scale 8.5 % off),
#: two merged flights with their own altitude offsets 15.4 % (11.6 % off). At 3 % the worst
#: scale accepted over 1,350 simulated drifting flights (8-30 m, 0.5-2 m of drift) was 4.8 %
#: off; at 6 %, 6.3 % (benchmarks/RESULTS.md, *#gps-98*).
MAX_ANISOTROPY = MAX_RELATIVE_SE
#: LO-RANSAC inlier threshold (metres): a fix this far from where the fit puts its camera has
#: jumped (multipath, a lost lock); consumer GPS's relative error over a flight is well under.
OUTLIER_M = 5.0


@dataclass(frozen=True)
class GpsScale:
    """What :func:`gps_scale` found. ``scale`` is set only where the GPS sets the scale."""

    scale: float | None
    """Metres per pose unit, or None where the GPS cannot set it (``reason`` says why)."""
    n_photos: int
    """Posed photos with a GPS position."""
    n_inliers: int = 0
    """Of those, the ones the robust fit kept."""
    residual_m: float = math.nan
    """RMS distance (m) between the kept photos' GPS positions and their fitted cameras."""
    spread_m: float = math.nan
    """RMS distance (m) of the kept photos' GPS positions from their centroid."""
    relative_se: float = math.nan
    """The scale's relative standard error: the block jackknife's, or the residual over the
    spread over the square root of the blocks where that is larger."""
    anisotropy: float = math.nan
    """The largest relative stretch of an affine fit against the similarity along a direction
    the cameras spread in."""
    fitted_scale: float = math.nan
    """The similarity's scale whether or not it is used (NaN where no fit)."""
    reason: str = ""
    """Why the GPS does not set the scale (empty where it does)."""

    @property
    def used(self) -> bool:
        return self.scale is not None

    def summary(self) -> dict:
        """Small, JSON-ready facts for the poses stage's record."""
        out = {
            "used": self.used,
            "n_photos": self.n_photos,
            "n_inliers": self.n_inliers,
            "residual_m": _finite_or_none(self.residual_m),
            "spread_m": _finite_or_none(self.spread_m),
            "relative_se": _finite_or_none(self.relative_se),
            "anisotropy": _finite_or_none(self.anisotropy),
            "scale": _finite_or_none(self.fitted_scale),
        }
        if self.reason:
            out["reason"] = self.reason
        return out


def _finite_or_none(v: float) -> float | None:
    return float(v) if math.isfinite(v) else None


def to_enu(lat_lon_alt: np.ndarray) -> np.ndarray:
    """(n, 3) latitude, longitude (degrees, WGS84) and altitude (m) → (n, 3) east, north, up
    (m) about their median position (pycolmap's :class:`GPSTransform`)."""
    import pycolmap

    lla = np.asarray(lat_lon_alt, dtype=np.float64).reshape(-1, 3)
    if not np.all(np.isfinite(lla)):
        raise InputError("GPS positions must be finite (latitude, longitude, altitude)")
    if np.any(np.abs(lla[:, 0]) > 90) or np.any(np.abs(lla[:, 1]) > 180):
        raise InputError("GPS latitude must lie in [-90, 90] and longitude in [-180, 180]")
    ref = np.median(lla, axis=0)
    t = pycolmap.GPSTransform(pycolmap.GPSTransformEllipsoid.WGS84)
    return np.asarray(t.ellipsoid_to_enu(lla, *map(float, ref)), dtype=np.float64)


def _rms_spread(x: np.ndarray) -> float:
    """RMS distance of the (n, 3) points ``x`` from their centroid."""
    return float(np.sqrt(np.mean(np.sum((x - x.mean(axis=0)) ** 2, axis=1))))


def _scale_of(src: np.ndarray, tgt: np.ndarray) -> float:
    """The least-squares similarity's scale, tgt ≈ s·R·src + t (NaN where degenerate)."""
    import pycolmap

    sim = pycolmap.estimate_sim3d(src, tgt)
    return math.nan if sim is None else float(sim.scale)


def _anisotropy(pred: np.ndarray, tgt: np.ndarray, min_share: float = 0.05) -> float:
    """The largest |u'Bu - 1| of the affine fit ``tgt ≈ B pred + c`` over the principal
    directions u of ``pred`` holding at least ``min_share`` of its largest variance (a nadir
    flight's vertical holds none: its heights tell nothing of a stretch)."""
    p0 = pred - pred.mean(axis=0)
    t0 = tgt - tgt.mean(axis=0)
    b, *_ = np.linalg.lstsq(p0, t0, rcond=None)  # t0 ≈ p0 @ b, so B = b.T
    w, v = np.linalg.eigh(p0.T @ p0)
    axes = v[:, w >= min_share * w.max()]
    return float(max(abs(float(u @ b.T @ u) - 1.0) for u in axes.T))


def gps_scale(
    centres: np.ndarray,
    lat_lon_alt: np.ndarray,
    *,
    max_relative_se: float = MAX_RELATIVE_SE,
    min_photos: int = MIN_PHOTOS,
    min_inlier_fraction: float = MIN_INLIER_FRACTION,
    blocks: int = JACKKNIFE_BLOCKS,
    outlier_m: float = OUTLIER_M,
    seed: int = 0,
) -> GpsScale:
    """The metric scale (metres per unit of ``centres``) of camera centres ``centres`` (n, 3),
    in capture order, whose GPS positions are ``lat_lon_alt`` (n, 3; degrees, degrees, metres).

    Returns a :class:`GpsScale` whose ``scale`` is None, with the ``reason``, where there are
    fewer than ``min_photos`` positions, they are one position (a stale fix), the robust fit
    keeps under ``min_inlier_fraction`` of them, the block jackknife's relative standard error
    exceeds ``max_relative_se`` or the fixes are stretched against the cameras by more than
    :data:`MAX_ANISOTROPY`.
    """
    c = np.asarray(centres, dtype=np.float64).reshape(-1, 3)
    lla = np.asarray(lat_lon_alt, dtype=np.float64).reshape(-1, 3)
    if len(c) != len(lla):
        raise InputError(f"{len(c)} camera centres for {len(lla)} GPS positions")
    n = len(c)
    if n < min_photos:
        return GpsScale(
            None, n, reason=f"{n} posed photos carry a GPS position; at least {min_photos} needed"
        )
    enu = to_enu(lla)
    if _rms_spread(enu) < 0.01:
        return GpsScale(
            None, n, reason=f"all {n} photos carry the same GPS position (a stale or "
            "placeholder fix): it cannot set the scale",
        )  # fmt: skip
    import pycolmap

    opts = pycolmap.RANSACOptions()
    opts.max_error = float(outlier_m)
    opts.random_seed = int(seed)
    found = pycolmap.estimate_sim3d_robust(c, enu, opts)
    if not found:
        sv = np.linalg.svd(c - c.mean(axis=0), compute_uv=False)
        if sv[1] <= 1e-9 * sv[0]:
            return GpsScale(None, n, reason="the cameras lie on one line, which a similarity "
                            "to their GPS positions cannot turn about")  # fmt: skip
        return GpsScale(None, n, reason="no similarity fits the cameras to their GPS positions")
    keep = np.asarray(found["inlier_mask"], dtype=bool)
    k = int(keep.sum())
    if k < max(min_photos, min_inlier_fraction * n):
        return GpsScale(
            None, n, k,
            reason=f"only {k} of {n} photos' GPS positions agree with their cameras "
            f"(within {outlier_m:g} m)",
        )  # fmt: skip
    src, tgt = c[keep], enu[keep]
    sim = pycolmap.estimate_sim3d(src, tgt)  # least squares on the kept photos
    if sim is None:
        return GpsScale(None, n, k, reason="the kept photos' positions are degenerate")
    s = float(sim.scale)
    fitted = np.asarray(sim.matrix(), dtype=np.float64)
    pred = src @ fitted[:, :3].T + fitted[:, 3]
    residual = float(np.sqrt(np.mean(np.sum((pred - tgt) ** 2, axis=1))))
    spread = _rms_spread(tgt)
    b = max(2, min(int(blocks), k // 3))
    parts = np.array_split(np.arange(k), b)  # contiguous in capture order
    jack = np.array([_scale_of(np.delete(src, p, 0), np.delete(tgt, p, 0)) for p in parts])
    if not np.all(np.isfinite(jack)):
        se = math.inf
    else:
        se = math.sqrt((b - 1) / b * float(np.sum((jack - jack.mean()) ** 2))) / s
        # ... and never below what the residual allows over as many independent blocks: a
        # jackknife of few blocks can read small by chance (measured on simulated flights with
        # drifting fixes: a 6 % error with a jackknife of 2.5 %)
        se = max(se, residual / max(spread, 1e-12) / math.sqrt(b))
    stretch = _anisotropy(pred, tgt)
    facts = dict(
        n_inliers=k, residual_m=residual, spread_m=spread, relative_se=se, anisotropy=stretch,
        fitted_scale=s,
    )  # fmt: skip
    if not (math.isfinite(s) and s > 0):
        return GpsScale(None, n, **facts, reason="the GPS positions give no positive scale")
    if not se <= max_relative_se:
        return GpsScale(
            None, n, **facts,
            reason=f"the photos' GPS positions spread {spread:.2g} m and lie {residual:.2g} m "
            f"(RMS) from their cameras: the scale they give is uncertain by "
            f"{100 * se:.1f} % (at most {100 * max_relative_se:g} % is used)",
        )  # fmt: skip
    if not stretch <= MAX_ANISOTROPY:
        return GpsScale(
            None, n, **facts,
            reason=f"the photos' GPS positions are stretched {100 * stretch:.1f} % along one "
            f"direction against their cameras (at most {100 * MAX_ANISOTROPY:g} %): a fix "
            "drifting through the flight, or flights merged with their own offsets",
        )  # fmt: skip
    return GpsScale(s, n, **facts)
