"""Gravity and provisional metric frame of structure-from-motion poses.

SfM returns poses in an arbitrary similarity frame: any rotation, origin and scale. The visible-
surfaces stage needs a frame where the plot is roughly centred, z points up and lengths are
roughly metres (its scene box, voxel size and horizontal plane sweep are set in that frame), and
row fitting then measures the exact ground plane and the metric scale. :func:`level_poses` makes
that frame (nerfstudio's data parsers do the same with their ``orientation_method`` and
``center_method``; here the up direction comes from the scene itself where it can):

* **up**: the normal of the sparse points' dominant plane (RANSAC, inliers within
  ``plane_threshold`` × the median camera-to-point distance, after trimming outliers; the soil
  between rows, or a canopy top — horizontal either way), signed so the cameras are above it;
  only planes that at least 90 % of the cameras look down on by ``min_look_down_deg`` or more
  compete (walk-around and drone captures do; a wall does not); with too few points, or no
  such plane, minus the cameras' mean optical axis;
* **origin**: on the ground (the sparse points' ``ground_percentile``-th height, 1: in a closed
  canopy most sparse points lie on leaves; on a synthetic soybean canopy of LAI 2.3 the 5th
  percentile lay 0.42 m above the soil, which put the soil under the surfaces' scene box and
  the provisional scale 40 % off; the 1st lay 6 mm below it) below the point closest
  to all optical axes (walk-around captures look at the plot), or below the points' median when
  the axes do not converge (drone lawnmower); without points, at that point itself, or below
  the cameras' centroid;
* **scale**: 1 for metric poses; from a user's camera height above the ground
  (``camera_height_m``, a precise hint: ``scale_source="camera_height"``) or a measured
  distance between two photos' camera positions (``camera_distance``, e.g. two tripod spots or
  the ends of a tape laid along the walk: ``"camera_distance"``); or from the photos' own
  GPS positions where they set it well enough (``gps_scale``, :mod:`cropcraft_core.sfm.gps`:
  ``"gps"``); else provisional from
  a typical capture height for the crop (``prior_camera_height_m``, ``"camera_height_prior"``),
  which row fitting replaces by the scale measured from the row spacing.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from cropcraft_core.errors import InputError
from cropcraft_core.rowfit.fit import RowFitError, ransac_plane
from cropcraft_core.sfm.poses import Poses

#: Typical height of the cameras above the ground per crop when nothing better is known (m):
#: a phone held over a soybean plot; a drone over maize (the issue's captures).
PRIOR_CAMERA_HEIGHT_M = {"soybean": 1.4, "maize": 13.0}

#: A hand-held capture's camera height (m), whatever the crop: where metric poses show the
#: cameras looking at the plot from closer than half the crop's prior (a walk round a maize
#: plot, whose prior is a drone's), the ground lies this far below them instead.
HAND_HELD_CAMERA_HEIGHT_M = 1.4

#: ... and where SfM poses (no scale) look down at the plot at a median angle under this
#: (degrees below the horizon: a walk round the plot, 45-70 deg in ``cropcraft synth``; a
#: drone's nadir photos 75-90), their provisional scale takes that hand-held height too.
HAND_HELD_MAX_LOOK_DOWN_DEG = 70.0

FRAME_SCALE_SOURCES = (
    "metric_poses", "camera_height", "camera_distance", "gps", "camera_height_prior",
)  # fmt: skip

#: Imported metric poses (a phone's AR tracking) are gravity-aligned on one axis of their frame:
#: z as nerfstudio writes Polycam's, y as it writes Record3D's (ARKit's own). The up found from
#: the cameras (a walk-around: ~1.7 deg off) is replaced by the nearest axis within this angle.
GRAVITY_AXIS_DEG = 25.0

#: ... and a frame levelled already (z up, the plot's centre within this many metres of its
#: origin, as ``cropcraft synth`` writes it) keeps its origin: the one found without sparse
#: points (under the point the cameras look at, a typical capture height below them) is an
#: estimate, good for placing the scene box, not better than the capture's own.
KEEP_ORIGIN_M = 0.25


@dataclass(frozen=True)
class GravityFrame:
    """How :func:`level_poses` moved the poses: ``world = scale · R · input + t``."""

    world_from_input: np.ndarray
    """(4, 4) similarity input frame → levelled frame (z up, ground z ≈ 0, ~metres)."""
    scale: float
    """Metres per input unit (exact for metric poses or a camera-height hint, else provisional)."""
    scale_source: str
    """One of ``FRAME_SCALE_SOURCES``."""
    up_source: str
    """'sparse_points', 'cameras' or 'input_axis' (the input frame's own, for gravity-aligned
    imported poses)."""
    up_disagreement_deg: float
    """Angle between the points' up and the cameras' mean up (NaN without points)."""
    camera_height_m: float
    """Median camera height above the estimated ground in the levelled frame."""
    ground_source: str = ""
    """Where the ground came from: 'sparse_points', 'prior' (metric poses without points: the
    prior capture height below the cameras), 'input_frame' (a frame levelled already kept its
    own), 'cameras_focus' (the point the cameras look at) or 'none'."""

    @property
    def metric(self) -> bool:
        """Whether the scale is known (metric poses or a user's hint), not provisional."""
        return self.scale_source != "camera_height_prior"

    def summary(self) -> dict:
        """The small, JSON-ready facts (everything but the matrix), for records and reports."""
        return {
            "scale": self.scale,
            "scale_source": self.scale_source,
            "up_source": self.up_source,
            "up_disagreement_deg": self.up_disagreement_deg,
            "camera_height_m": self.camera_height_m,
            "ground_source": self.ground_source,
        }

    def to_dict(self) -> dict:
        return {"world_from_input": self.world_from_input.tolist(), **self.summary()}


def _rotation_to_z(up: np.ndarray) -> np.ndarray:
    """Proper rotation taking unit ``up`` to +z (the shortest one)."""
    z = np.array([0.0, 0.0, 1.0])
    v = np.cross(up, z)
    c = float(up @ z)
    if np.linalg.norm(v) < 1e-12:
        return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + vx + vx @ vx * (1.0 / (1.0 + c))


def _optical_axes(poses: Poses) -> np.ndarray:
    """(n, 3) unit optical axes (the cameras' +z, looking into the scene) in the poses' frame."""
    return np.array([c.cam_to_world[:3, 2] for _, c in poses])


def look_down_deg(axes: np.ndarray, up: np.ndarray) -> float:
    """The cameras' median angle below the horizon (degrees) of (n, 3) unit optical ``axes``,
    ``up`` the frame's unit up: a walk round the plot 45-70, a drone's nadir photos 75-90."""
    look = axes @ up
    return float(np.degrees(np.arcsin(np.clip(-np.median(look), -1.0, 1.0))))


def looks_down(poses: Poses) -> bool:
    """Whether ``poses`` (a z-up frame) look down at the plot as a drone's or a phone held over
    it do (:data:`HAND_HELD_MAX_LOOK_DOWN_DEG` or more), not as a walk round it."""
    up = np.array([0.0, 0.0, 1.0])
    return look_down_deg(_optical_axes(poses), up) >= HAND_HELD_MAX_LOOK_DOWN_DEG


def cameras_up(poses: Poses) -> np.ndarray:
    """Unit up direction from the cameras: minus their mean optical axis (captures look down on
    average), or the mean of their image-up axes when the optical axes cancel out."""
    axes = _optical_axes(poses)
    m = axes.mean(axis=0)
    if np.linalg.norm(m) > 0.3:
        return -m / np.linalg.norm(m)
    ups = -np.array([c.cam_to_world[:3, 1] for _, c in poses]).mean(axis=0)
    n = np.linalg.norm(ups)
    if n < 1e-6:
        raise InputError("the cameras give no up direction (they look in all directions)")
    return ups / n


#: A hand-held capture's image rows stay within about this angle of level (little roll).
LEVEL_ROLL_DEG = 15.0


def level_axis(poses: Poses, max_roll_deg: float = LEVEL_ROLL_DEG) -> np.ndarray | None:
    """The axis of a gravity-aligned frame that is up, by the cameras' image rows, or their
    columns where the phone was held upright (AR tracking writes the sensor's frame however
    the phone is held): a hand-held or drone capture keeps one of them level, so up is the
    axis that one is most nearly perpendicular to (nerfstudio's ``vertical`` orientation uses
    the same fact), signed so the cameras look down on average. None where no axis is within
    ``max_roll_deg`` of every-row-level (or every-column-level) on average, or the cameras
    look neither up nor down along it. Unlike minus the mean optical axis
    (:func:`cameras_up`), which a walk along one side of the plot tilts by its pitch, it does
    not need the walk to close a circle."""
    # mean |sin| of each axis against the rows (first three) and the columns (last three)
    tilt = np.concatenate(
        [np.abs(np.array([c.cam_to_world[:3, k] for _, c in poses])).mean(axis=0) for k in (0, 1)]
    )
    axis = int(np.argmin(tilt)) % 3
    if tilt.min() > math.sin(math.radians(max_roll_deg)):
        return None
    look = float(_optical_axes(poses).mean(axis=0)[axis])
    if abs(look) < 0.1:
        return None
    return np.eye(3)[axis] * (-1.0 if look > 0 else 1.0)


def _trimmed(points: np.ndarray, keep: float = 0.9) -> np.ndarray:
    med = np.median(points, axis=0)
    d = np.linalg.norm(points - med, axis=1)
    return points[d <= np.quantile(d, keep)]


def _axes_focus(poses: Poses) -> np.ndarray | None:
    """The point closest (least squares) to every optical axis, or None if ill-conditioned."""
    a = np.zeros((3, 3))
    b = np.zeros(3)
    for _, c in poses:
        d = c.cam_to_world[:3, 2]
        p = np.eye(3) - np.outer(d, d)
        a += p
        b += p @ c.center
    w = np.linalg.eigvalsh(a)
    if w[0] < 0.05 * len(poses):
        return None
    return np.linalg.solve(a, b)


def check_cameras_face_their_focus(
    poses: Poses, focus: np.ndarray | None, share: float = 0.8
) -> None:
    """InputError where the cameras' optical axes meet at ``focus`` (:func:`_axes_focus`; each
    passes within a quarter of its camera's distance from it) and more than ``share`` of the
    cameras have it behind them: cameras turned round, as a ``transforms.json`` written in
    OpenCV's camera axes and read as nerfstudio's (OpenGL's) makes them. Axes that meet
    nowhere (None: a drone's, nearly parallel) say nothing."""
    if focus is None:
        return
    to = np.array([focus - c.center for _, c in poses])
    axes = _optical_axes(poses)
    dist = np.linalg.norm(to, axis=1)
    along = np.einsum("ij,ij->i", to, axes)
    miss = np.sqrt(np.maximum(dist**2 - along**2, 0.0))  # each axis's distance from the focus
    if np.median(miss) > 0.25 * np.median(dist):
        return
    away = int(np.sum(along < 0))
    if away > share * len(poses):
        raise InputError(
            f"{away} of {len(poses)} cameras look away from the point their optical axes meet "
            "(the plot): the poses' camera axes are turned round. Is the transforms.json in "
            "OpenCV's camera axes (x right, y down, z forward) rather than nerfstudio's "
            "OpenGL ones (x right, y up, z back)? Convert it, or give the COLMAP model instead"
        )


def photo_stem(path: str) -> str:
    """A photo's name without folder (``/`` or ``\\``) or extension: how a camera-distance
    hint's photo is matched to a posed (ingested, maybe renamed) photo."""
    return str(path).replace("\\", "/").rsplit("/", 1)[-1].rsplit(".", 1)[0]


def _camera_span(poses: Poses, hint: tuple[str, str, float]) -> float:
    """Metres per input unit from (photo A, photo B, metres between their cameras)."""
    try:
        a, b, metres = hint
        metres = float(metres)
    except (TypeError, ValueError):
        raise InputError(
            f"camera_distance must be (photo A, photo B, metres), got {hint!r}"
        ) from None
    if not (math.isfinite(metres) and metres > 0):
        raise InputError(f"camera_distance must be a positive number of metres, got {metres!r}")
    names = [n for n, _ in poses]
    stems = {photo_stem(n): n for n in names}

    def centre(photo: str) -> np.ndarray:
        name = photo if photo in names else stems.get(photo_stem(photo))
        if name is None:
            raise InputError(
                f"camera_distance names photo {photo!r}, which has no pose "
                f"({len(names)} posed photos, e.g. {', '.join(names[:3])})"
            )
        return poses.camera(name).center

    d = float(np.linalg.norm(centre(a) - centre(b)))
    if not d > 1e-9 * max(1.0, float(np.ptp(poses.centers(), axis=0).max())):
        raise InputError(
            f"photos {a!r} and {b!r} were taken from the same spot: their distance cannot "
            "set the scale"
        )
    return metres / d


def level_poses(
    poses: Poses,
    points: np.ndarray | None = None,
    *,
    metric: bool = False,
    camera_height_m: float | None = None,
    camera_distance: tuple[str, str, float] | None = None,
    gps_scale: float | None = None,
    prior_camera_height_m: float = 1.4,
    hand_held_prior_m: float | None = HAND_HELD_CAMERA_HEIGHT_M,
    min_look_down_deg: float = 10.0,
    plane_threshold: float = 0.01,
    ransac_iterations: int = 1000,
    seed: int = 0,
    min_points: int = 50,
    ground_percentile: float = 1.0,
    gravity_axis_deg: float | None = None,
    keep_levelled: bool = False,
) -> tuple[Poses, np.ndarray | None, GravityFrame]:
    """Move ``poses`` (and the sparse ``points`` (n, 3) of the same frame) into a levelled,
    centred, roughly metric frame; return (poses, points or None, :class:`GravityFrame`).

    metric: the input is already in metres (only rotate and move). camera_height_m: the user's
    measured median camera height above the ground (sets the scale; above this function's
    ground, which lies on the leaves when the sparse points miss the soil, so
    :func:`cropcraft_core.rowfit.fit_rows_with_scale` measures it again above the dense points'
    fitted ground plane). camera_distance:
    (photo A, photo B, metres) the measured distance between two photos' camera centres (names
    as in ``poses``, or their stems; sets the scale exactly). gps_scale: metres per input unit
    from the photos' GPS positions (:func:`cropcraft_core.sfm.gps.gps_scale`), taken where
    neither a height nor a distance is given. prior_camera_height_m: the assumed
    height otherwise (``PRIOR_CAMERA_HEIGHT_M``); for metric poses without points, the ground
    lies this far below the cameras' median height, or ``hand_held_prior_m`` (if less; None:
    never) below them where the point their optical axes meet lies less than half the prior
    and at most three hand-held heights below them (a walk round the plot), or at that point
    where it lies farther (a low flight); for other poses the
    provisional scale takes ``hand_held_prior_m`` (if less) where the cameras look down at
    under :data:`HAND_HELD_MAX_LOOK_DOWN_DEG`. gravity_axis_deg: replace the up found by the
    input frame's nearest axis (±x, ±y, ±z) within this angle (:data:`GRAVITY_AXIS_DEG`, for
    gravity-aligned captures). keep_levelled: for metric poses already z up, keep the input's
    origin where the one found lies within :data:`KEEP_ORIGIN_M` of it, and its ground where,
    without points, the cameras' median height above it is 0.5-2 times the prior (a frame
    levelled already, as ``cropcraft synth`` writes it). Raises ``InputError`` for fewer than
    3 cameras, a non-positive height or distance, both hints at once, a photo the poses do
    not have, two photos taken from one spot, a camera-height hint without a ground
    estimate, or cameras turned round (:func:`check_cameras_face_their_focus`).
    """
    if len(poses) < 3:
        raise InputError(f"levelling needs at least 3 posed cameras, got {len(poses)}")
    for name, v in (("camera_height_m", camera_height_m), ("prior", prior_camera_height_m)):
        if v is not None and not (math.isfinite(v) and v > 0):
            raise InputError(f"{name} must be a positive number of metres, got {v!r}")
    if camera_height_m is not None and camera_distance is not None:
        raise InputError("give the camera height or a camera distance for the scale, not both")
    span = None if camera_distance is None else _camera_span(poses, camera_distance)
    focus = _axes_focus(poses)  # where the optical axes meet, in the input frame
    check_cameras_face_their_focus(poses, focus)
    centres, axes = poses.centers(), _optical_axes(poses)
    up_cam = cameras_up(poses)
    pts = None if points is None else np.asarray(points, np.float64).reshape(-1, 3)
    usable = pts is not None and len(pts) >= min_points
    up, source, disagree = up_cam, "cameras", float("nan")
    if usable:
        core = _trimmed(pts)
        sin_min = math.sin(math.radians(min_look_down_deg))

        def seen_from_above(normals: np.ndarray) -> np.ndarray:
            n = normals * np.where(normals @ up_cam < 0, -1.0, 1.0)[:, None]
            return np.mean(-(n @ axes.T) >= sin_min, axis=1) >= 0.9

        some = centres[:: max(1, len(centres) // 20)]  # the scene's size: camera-point range
        dist = float(np.median(np.linalg.norm(core[:, None, :] - some[None], axis=2)))
        try:
            n, _, _ = ransac_plane(
                core,
                plane_threshold * dist,
                ransac_iterations,
                np.random.default_rng(seed),
                admissible=seen_from_above,
            )
        except RowFitError:
            n = None
        if n is not None:
            n = n if n @ up_cam >= 0 else -n
            disagree = math.degrees(math.acos(min(1.0, float(n @ up_cam))))
            if seen_from_above(n[None])[0]:
                up, source = n, "sparse_points"
    if gravity_axis_deg is not None:
        axis = int(np.argmax(np.abs(up)))
        if math.degrees(math.acos(min(1.0, abs(float(up[axis]))))) <= gravity_axis_deg:
            up = np.eye(3)[axis] * math.copysign(1.0, float(up[axis]))
            source = "input_axis"
        elif source == "cameras":
            level = level_axis(poses)
            if level is not None:
                up, source = level, "input_axis"
    r = _rotation_to_z(up)

    ground_z: float | None
    prior = prior_camera_height_m
    if not metric and hand_held_prior_m is not None:
        if look_down_deg(axes, up) < HAND_HELD_MAX_LOOK_DOWN_DEG:  # a walk, not a flight
            prior = min(prior, hand_held_prior_m)
    f = None if focus is None else r @ focus
    if usable:
        core_r = core @ r.T
        ground_z, ground = float(np.percentile(core_r[:, 2], ground_percentile)), "sparse_points"
        centre_xy = np.median(core_r[:, :2], axis=0) if f is None else f[:2]
    elif metric:  # metres already: the ground a typical capture height below the cameras
        cam_z = float(np.median((centres @ r.T)[:, 2]))
        ground_z, ground = cam_z - prior, "prior"
        above = cam_z - f[2] if f is not None else math.inf  # over where the cameras look
        if hand_held_prior_m is not None and 0 < above < 0.5 * prior:
            if above <= 3 * hand_held_prior_m:  # a walk round the plot
                prior = min(prior, hand_held_prior_m)
                ground_z = cam_z - prior
            else:  # a low flight: the ground no higher than where the cameras look
                ground_z = float(f[2])
        centre_xy = (centres @ r.T)[:, :2].mean(axis=0) if f is None else f[:2]
    elif f is not None:
        ground_z, centre_xy, ground = float(f[2]), f[:2], "cameras_focus"
    else:
        ground_z, centre_xy, ground = None, (centres @ r.T)[:, :2].mean(axis=0), "none"
    heights = (centres @ r.T)[:, 2] - (ground_z if ground_z is not None else 0.0)
    med_h = float(np.median(heights))
    if metric:
        scale, scale_source = 1.0, "metric_poses"
    elif span is not None:
        scale, scale_source = span, "camera_distance"
    elif camera_height_m is None and gps_scale is not None:
        if not (math.isfinite(gps_scale) and gps_scale > 0):
            raise InputError(f"gps_scale must be a positive number, got {gps_scale!r}")
        scale, scale_source = float(gps_scale), "gps"
    elif ground_z is None or med_h <= 0:
        if camera_height_m is not None:
            raise InputError(
                "a camera-height hint needs the ground under the cameras, but neither sparse "
                "points nor converging optical axes locate it: give the scale instead"
            )
        scale, scale_source = 1.0, "camera_height_prior"
    elif camera_height_m is not None:
        scale, scale_source = camera_height_m / med_h, "camera_height"
    else:
        scale, scale_source = prior / med_h, "camera_height_prior"

    t = -scale * np.array([centre_xy[0], centre_xy[1], ground_z or 0.0])
    if keep_levelled and scale == 1.0 and np.array_equal(r, np.eye(3)):
        # a frame levelled already (cropcraft synth's, a survey's): its own origin where the
        # estimate is near it, and its own ground where the cameras stand a plausible height
        # above it and no points measure the ground
        if float(np.hypot(t[0], t[1])) <= KEEP_ORIGIN_M:
            t[:2] = 0.0
        h = float(np.median(centres[:, 2]))
        if not usable and 0.5 <= h / prior <= 2.0:
            t[2], med_h, ground = 0.0, h, "input_frame"
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = scale * r, t
    out_poses = poses.transformed(scale, r, t)
    out_pts = None if pts is None else pts @ (scale * r).T + t
    frame = GravityFrame(
        world_from_input=m,
        scale=float(scale),
        scale_source=scale_source,
        up_source=source,
        up_disagreement_deg=disagree,
        camera_height_m=float(med_h * scale),
        ground_source=ground,
    )
    return out_poses, out_pts, frame
