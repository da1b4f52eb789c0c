"""Ground plane, crop rows and the row camera from a coloured point cloud (paper "Pose Alignment
for Depth Rendering", supplementary "Additional Row Fitting and Depth Rendering Details").

Pipeline of :func:`fit_ground_and_rows` (settings in :class:`~.presets.RowFitPreset`):

1. keep the points inside the scene box (scene units) and at most ``sample_count`` of them;
2. bring them to metres with ``scale`` (metres per scene unit) and voxel-downsample (1 cm);
3. colour rules in CIELAB: drop dark-bluish points, split the rest into plant (green) / ground;
4. RANSAC plane through the ground points (then one least-squares refit on its inliers); the
   aligned ("world") frame has z along the plane normal, pointing to the side the plants are on,
   the ground at z = 0, and its origin below the scene-box centre;
5. dense-canopy switch when plant points exceed 75 % (soybean);
6. plant points inside the ROI cylinder (maize), above the height percentile, projected onto the
   ground; lines by sequential RANSAC in the ground plane until too few points remain; each line
   refitted by orthogonal least squares on its inliers; the row with the most inliers is the
   "best" row;
7. row camera: ``PinholeCamera.look_down`` above the mean of the best row's inliers at the render
   height, image x along the row.

All random choices come from the ``rng`` argument (RANSAC is implemented here in numpy, since
Open3D's ``segment_plane`` takes no seed), so results are reproducible.

Frames. ``scene``: the input point cloud's frame and units. ``world``: metres, z up from the
ground, ``p_world = world_from_scene @ [p_scene, 1]`` where ``world_from_scene = [[s R, t],
[0, 1]]`` with R a rotation and s = ``scale`` (metres per scene unit).

Metric scale (the chosen source is recorded in ``RowFit.scale_source``):
``"metric_poses"`` (poses imported in metres), ``"camera_height"`` (SfM poses scaled by the
user's camera height), ``"user_hint"`` (a scale given by the user),
``"row_spacing"`` (fitted row spacing against the known planting row spacing, see
:func:`estimate_scale_from_rows` and :func:`fit_rows_with_scale`), or ``"assumed_metric"``
(nothing known; the scene is taken to be in metres).
"""

from __future__ import annotations

import contextlib
import copy
import math
import numbers
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, replace

import numpy as np

from cropcraft_core.errors import ConfigError, CropCraftError, InputError
from cropcraft_core.geometry.camera import PinholeCamera
from cropcraft_core.rowfit.lab import colour_range, srgb_to_lab
from cropcraft_core.rowfit.presets import RowFitPreset
from cropcraft_core.rowfit.presets import preset as make_preset

SCALE_SOURCES = (
    "metric_poses",
    "camera_height",
    "camera_distance",
    "gps",
    "user_hint",
    "row_spacing",
    "assumed_metric",
)


class RowFitError(CropCraftError, ValueError):
    """Row fitting cannot proceed: too few points, no ground found or no rows found."""


def camera_to_scene(
    camera: PinholeCamera, world_from_scene: np.ndarray, scale: float
) -> PinholeCamera:
    """A world-frame camera with a rigid ``cam_to_world`` in the *scene* frame (positions in
    scene units, so a depth rendered from it is in scene units: × ``scale`` for metres)."""
    m = np.linalg.inv(np.asarray(world_from_scene, float)) @ camera.cam_to_world
    r = m[:3, :3] * float(scale)  # undo the similarity's scale on the axes
    u, _, vt = np.linalg.svd(r)
    rigid = np.eye(4)
    rigid[:3, :3] = u @ vt
    rigid[:3, 3] = m[:3, 3]
    c = camera
    return PinholeCamera(c.width, c.height, c.fx, c.fy, c.cx, c.cy, rigid)


# --------------------------------------------------------------------------- results
@dataclass(frozen=True, eq=False)
class Row:
    """One fitted crop row: a line in the ground plane of the world frame (metres).

    direction: (2,) unit xy direction, sign chosen so that x > 0 (or y > 0 when x = 0).
    point: (2,) xy of the mean of the inliers (a point on the line).
    n_inliers: number of plant points within the line threshold.
    """

    direction: np.ndarray
    point: np.ndarray
    n_inliers: int

    @property
    def normal(self) -> np.ndarray:
        """(2,) unit xy normal of the line (direction rotated by +90°)."""
        return np.array([-self.direction[1], self.direction[0]])

    @property
    def azimuth_deg(self) -> float:
        """Direction of the row in the world xy plane, degrees from +x, in (-90, 90]."""
        return math.degrees(math.atan2(self.direction[1], self.direction[0]))

    def distance(self, xy: np.ndarray) -> np.ndarray:
        """(n, 2) world xy → (n,) signed distance from the line along ``normal``."""
        return (np.asarray(xy)[..., :2] - self.point) @ self.normal

    def to_dict(self) -> dict:
        return {
            "direction": self.direction.tolist(),
            "point": self.point.tolist(),
            "n_inliers": self.n_inliers,
        }


@dataclass(frozen=True, eq=False)
class RowFit:
    """Ground plane, rows and row camera of a scene (see the module docstring for the frames)."""

    crop: str
    preset: RowFitPreset
    """The settings actually used (the dense-canopy ones when ``dense``)."""
    ground_normal: np.ndarray
    """(3,) unit normal of the ground plane in the scene frame, pointing to the plants."""
    ground_offset: float
    """Plane ``ground_normal · p + ground_offset = 0`` for scene points p (scene units)."""
    ground_inliers: int
    """Ground-class points within the RANSAC threshold of the plane."""
    world_from_scene: np.ndarray
    """(4, 4) similarity: scene → world (metres, ground z = 0, z up)."""
    scale: float
    """Metres per scene unit."""
    scale_source: str
    """Where ``scale`` came from, one of ``SCALE_SOURCES``."""
    rows: tuple[Row, ...]
    """Fitted rows in the world frame, most inliers first; each refitted by least squares."""
    camera: PinholeCamera
    """The row camera in the world frame."""
    dense: bool
    """Whether the dense-canopy settings were used."""
    row_points: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    """(n, 2) world xy of the plant points rows were fitted to (ROI, above the height cut)."""
    plant_xy: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    """(n, 2) world xy of every plant point within the preset's ``scale_radius`` (any height):
    the row-spacing profile's points."""
    diagnostics: dict = field(default_factory=dict)
    """Point counts per stage and class, plant fraction, why row fitting stopped."""

    @property
    def best_row(self) -> Row:
        """The row with the most inliers (the one the camera looks at)."""
        return self.rows[0]

    def parallel_rows(self, max_angle_deg: float = 10.0) -> int:
        """How many fitted lines lie within ``max_angle_deg`` of the best row (it included):
        the rows; sequential RANSAC also fits lines through leaves across them (a maize drone
        reconstruction: 5 of 6 at 19-67°)."""
        cos_max = math.cos(math.radians(max_angle_deg))
        return sum(abs(float(r.direction @ self.best_row.direction)) >= cos_max for r in self.rows)

    def median_height(self, points: np.ndarray) -> float:
        """The median signed height of (n, 3) scene points above the ground plane, in scene
        units (the cameras' height over the fitted ground, for the scale's checks)."""
        c = np.asarray(points, dtype=np.float64)
        return float(np.median(c @ self.ground_normal + self.ground_offset))

    @property
    def render_height(self) -> float:
        return self.preset.render_height

    @property
    def scene_from_world(self) -> np.ndarray:
        """(4, 4) inverse of ``world_from_scene``."""
        return np.linalg.inv(self.world_from_scene)

    def to_world(self, points: np.ndarray) -> np.ndarray:
        """(n, 3) scene points → (n, 3) world points (metres)."""
        m = self.world_from_scene
        return np.asarray(points, float) @ m[:3, :3].T + m[:3, 3]

    def to_scene(self, points: np.ndarray) -> np.ndarray:
        """(n, 3) world points → (n, 3) scene points."""
        m = self.scene_from_world
        return np.asarray(points, float) @ m[:3, :3].T + m[:3, 3]

    def camera_in_scene(self) -> PinholeCamera:
        """The row camera with a rigid ``cam_to_world`` in the *scene* frame, for rendering the
        NeRF. Its position is in scene units, so a depth it renders is in scene units too:
        multiply by ``scale`` for metres."""
        return camera_to_scene(self.camera, self.world_from_scene, self.scale)

    def row_frame_from_world(self) -> np.ndarray:
        """(4, 4) rigid world → row frame: origin on the ground below the camera, x along the
        best row, z up (the frame of ``generate_canopy`` with row azimuth 0)."""
        cam = self.camera.cam_to_world
        x = cam[:3, 0]
        z = np.array([0.0, 0.0, 1.0])
        y = np.cross(z, x)
        m = np.eye(4)
        m[0, :3], m[1, :3], m[2, :3] = x, y, z
        origin = np.array([cam[0, 3], cam[1, 3], 0.0])
        m[:3, 3] = -m[:3, :3] @ origin
        return m

    def to_dict(self) -> dict:
        return {
            "crop": self.crop,
            "ground_normal": self.ground_normal.tolist(),
            "ground_offset": self.ground_offset,
            "ground_inliers": self.ground_inliers,
            "world_from_scene": self.world_from_scene.tolist(),
            "scale": self.scale,
            "scale_source": self.scale_source,
            "rows": [r.to_dict() for r in self.rows],
            "camera": self.camera.to_dict(),
            "render_height": self.render_height,
            "dense": self.dense,
            "diagnostics": dict(self.diagnostics),
        }


# --------------------------------------------------------------------------- building blocks
def voxel_downsample(
    points: np.ndarray, colors: np.ndarray, voxel: float
) -> tuple[np.ndarray, np.ndarray]:
    """Average (n, 3) points and (n, 3) colours per cubic voxel of side ``voxel`` (like Open3D's
    ``voxel_down_sample``). Returns ((m, 3), (m, 3)) float64, voxels in lexicographic order."""
    if len(points) == 0:
        return points.astype(float).reshape(0, 3), colors.astype(float).reshape(0, 3)
    idx = np.floor(points / voxel).astype(np.int64)
    idx -= idx.min(axis=0)
    dims = idx.max(axis=0) + 1
    if float(dims[0]) * float(dims[1]) * float(dims[2]) < 2**62:
        key = (idx[:, 0] * dims[1] + idx[:, 1]) * dims[2] + idx[:, 2]
        _, inverse, counts = np.unique(key, return_inverse=True, return_counts=True)
    else:  # astronomically sparse cloud: fall back to row-wise unique
        _, inverse, counts = np.unique(idx, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.ravel()
    m = len(counts)
    out_p = np.empty((m, 3))
    out_c = np.empty((m, 3))
    for k in range(3):
        out_p[:, k] = np.bincount(inverse, weights=points[:, k], minlength=m) / counts
        out_c[:, k] = np.bincount(inverse, weights=colors[:, k], minlength=m) / counts
    return out_p, out_c


def _score_subset(n: int, cap: int, rng: np.random.Generator) -> np.ndarray | None:
    return None if n <= cap else rng.choice(n, cap, replace=False)


def _best_hypothesis(
    score: np.ndarray,
    nrm: np.ndarray,
    off: np.ndarray,
    valid: np.ndarray,
    threshold: float,
    chunk: int,
) -> int | None:
    """Index of the RANSAC hypothesis ``nrm · p + off = 0`` (nrm (k, d) unit, off (k,)) with the
    most ``score`` points (n, d) within ``threshold``, first on ties; invalid (degenerate)
    hypotheses never win; None when all are invalid. Scored ``chunk`` hypotheses at a time."""
    k = len(nrm)
    counts = np.full(k, -1, dtype=np.int64)
    for s in range(0, k, chunk):
        e = min(k, s + chunk)
        dist = np.abs(score @ nrm[s:e].T + off[s:e])
        counts[s:e] = np.where(valid[s:e], (dist < threshold).sum(axis=0), -1)
    best = int(np.argmax(counts))
    return None if counts[best] < 0 else best


def ransac_plane(
    points: np.ndarray,
    threshold: float,
    iterations: int,
    rng: np.random.Generator,
    score_points: int = 20_000,
    admissible: Callable[[np.ndarray], np.ndarray] | None = None,
) -> tuple[np.ndarray, float, np.ndarray]:
    """RANSAC plane through (n, 3) points, then one least-squares refit on the inliers.

    Returns (normal (3,) unit, offset, inliers (n,) bool) with ``normal · p + offset = 0``.
    Hypotheses are scored on a random subset of at most ``score_points`` points;
    ``admissible(normals (k, 3)) -> (k,) bool`` rules hypotheses out (e.g. planes the cameras
    could not be looking down on).
    """
    n = len(points)
    if n < 3:
        raise RowFitError(f"a plane needs at least 3 points, got {n}")
    sub = _score_subset(n, score_points, rng)
    score = points if sub is None else points[sub]
    tri = rng.integers(0, n, size=(iterations, 3))
    a, b, c = points[tri[:, 0]], points[tri[:, 1]], points[tri[:, 2]]
    nrm = np.cross(b - a, c - a)
    length = np.linalg.norm(nrm, axis=1)
    valid = length > 1e-12
    nrm = nrm / np.where(valid, length, 1.0)[:, None]
    off = -np.einsum("ij,ij->i", nrm, a)
    if admissible is not None:
        valid &= np.asarray(admissible(nrm), bool)
    best = _best_hypothesis(score, nrm, off, valid, threshold, chunk=64)
    if best is None:
        raise RowFitError(
            "all plane hypotheses were degenerate (collinear points) or not admissible"
        )
    normal, offset = nrm[best], float(off[best])
    inliers = np.abs(points @ normal + offset) < threshold
    if inliers.sum() >= 3:  # least-squares refit: the plane through the inliers' centroid
        q = points[inliers]
        centroid = q.mean(axis=0)
        _, _, vt = np.linalg.svd(q - centroid, full_matrices=False)
        refit = vt[2] * (1.0 if vt[2] @ normal >= 0 else -1.0)
        normal, offset = refit, float(-refit @ centroid)
        inliers = np.abs(points @ normal + offset) < threshold
    return normal, offset, inliers


def ransac_line_2d(
    xy: np.ndarray,
    threshold: float,
    iterations: int,
    rng: np.random.Generator,
    score_points: int = 20_000,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """RANSAC line through (n, 2) points. Returns (direction (2,) unit, point (2,), inliers (n,)
    bool); distances are perpendicular to the line."""
    n = len(xy)
    if n < 2:
        raise RowFitError(f"a line needs at least 2 points, got {n}")
    sub = _score_subset(n, score_points, rng)
    score = xy if sub is None else xy[sub]
    pair = rng.integers(0, n, size=(iterations, 2))
    p0, p1 = xy[pair[:, 0]], xy[pair[:, 1]]
    d = p1 - p0
    length = np.linalg.norm(d, axis=1)
    valid = length > 1e-12
    d = d / np.where(valid, length, 1.0)[:, None]
    nrm = np.column_stack([-d[:, 1], d[:, 0]])
    off = -np.einsum("ij,ij->i", nrm, p0)
    best = _best_hypothesis(score, nrm, off, valid, threshold, chunk=128)
    if best is None:
        raise RowFitError("all row-line hypotheses were degenerate (coincident points)")
    inliers = np.abs(xy @ nrm[best] + off[best]) < threshold
    return d[best], p0[best], inliers


def fit_line_lsq(xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Orthogonal least-squares line through (n, 2) points: (direction (2,) unit, centroid (2,))."""
    centroid = xy.mean(axis=0)
    _, _, vt = np.linalg.svd(xy - centroid, full_matrices=False)
    return vt[0], centroid


def _canonical(direction: np.ndarray) -> np.ndarray:
    d = np.asarray(direction, float) / np.linalg.norm(direction)
    if d[0] < 0 or (d[0] == 0 and d[1] < 0):
        d = -d
    return d


def _as_rng(rng: np.random.Generator | int | None) -> np.random.Generator:
    if isinstance(rng, np.random.Generator):
        return rng
    if rng is None:
        return np.random.default_rng(0)
    if isinstance(rng, int | np.integer) and not isinstance(rng, bool):
        return np.random.default_rng(int(rng))
    raise ConfigError(f"rng must be a numpy Generator or an integer seed, got {type(rng)}")


# --------------------------------------------------------------------------- main entry
def fit_ground_and_rows(
    points: np.ndarray,
    colors: np.ndarray,
    crop: str,
    preset: RowFitPreset | None = None,
    rng: np.random.Generator | int | None = None,
    *,
    scale: float = 1.0,
    scale_source: str = "assumed_metric",
) -> RowFit:
    """Fit the ground plane and the crop rows of a coloured point cloud; place the row camera.

    points: (n, 3) scene-frame positions. colors: (n, 3) sRGB, 0–1 floats or 0–255.
    crop: ``"soybean"`` or ``"maize"``; preset: settings (default ``preset(crop)``).
    rng: numpy Generator or integer seed (``None`` = seed 0); the result is a deterministic
    function of the inputs and the generator's state.
    scale: metres per scene unit; scale_source: where it comes from (``SCALE_SOURCES``).

    Raises ``RowFitError`` for too few points, no ground found and no rows found, and
    ``InputError`` / ``ConfigError`` for malformed arguments.
    """
    p = make_preset(crop) if preset is None else preset
    if p.crop != crop:
        raise ConfigError(f"preset is for {p.crop!r}, not {crop!r}")
    if scale_source not in SCALE_SOURCES:
        raise ConfigError(
            f"scale_source must be one of {', '.join(SCALE_SOURCES)}, got {scale_source!r}"
        )
    if not (
        isinstance(scale, numbers.Real)
        and not isinstance(scale, bool)
        and math.isfinite(scale)
        and scale > 0
    ):
        raise ConfigError(f"scale (metres per scene unit) must be a positive number, got {scale!r}")
    scale = float(scale)
    rng = _as_rng(rng)
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise InputError(f"points must have shape (n, 3), got {pts.shape}")
    col = np.asarray(colors)
    if col.shape != pts.shape:
        raise InputError(f"colors must have the same shape as points {pts.shape}, got {col.shape}")
    stored = col.dtype
    col = col.astype(np.float64)
    finite = np.all(np.isfinite(pts), axis=1) & np.all(np.isfinite(col), axis=1)
    pts, col = pts[finite], col[finite]
    # the range from the points kept: one inf colour made every colour dark
    lab_max = colour_range(col, stored)
    diag: dict = {"n_input": int(len(finite)), "n_finite": int(finite.sum())}

    # 1. scene box and sampling
    if p.box_size is not None:
        lo = np.asarray(p.box_center) - 0.5 * np.asarray(p.box_size)
        hi = np.asarray(p.box_center) + 0.5 * np.asarray(p.box_size)
        inside = np.all((pts >= lo) & (pts <= hi), axis=1)
        pts, col = pts[inside], col[inside]
        origin_scene = np.asarray(p.box_center, dtype=float)
    diag["n_in_box"] = int(len(pts))
    if len(pts) > p.sample_count:
        keep = np.sort(rng.choice(len(pts), p.sample_count, replace=False))
        pts, col = pts[keep], col[keep]
    diag["n_sampled"] = int(len(pts))

    # 2. metric scale and voxel downsampling
    pts_m, col = voxel_downsample(pts * scale, col, p.voxel_size)
    diag["n_voxels"] = int(len(pts_m))
    if len(pts_m) < p.min_points:
        raise RowFitError(
            f"too few points for row fitting: {len(pts_m)} after the scene-box crop and "
            f"{p.voxel_size * 100:g} cm voxel downsampling (of {diag['n_input']} given), need at "
            f"least {p.min_points}; check the box (box_center/box_size, scene units) and the "
            f"scale ({scale:g} m per scene unit)"
        )
    if p.box_size is None:
        origin_scene = np.median(pts_m, axis=0) / scale

    # 3. colour rules
    lab = srgb_to_lab(col, max_value=lab_max)
    removed = (lab[:, 0] < p.remove_l_below) & (lab[:, 2] < p.remove_b_below)
    plant = ~removed & (lab[:, 1] < p.plant_a_below)
    ground = ~removed & ~plant
    n_plant, n_ground = int(plant.sum()), int(ground.sum())
    plant_fraction = n_plant / max(1, n_plant + n_ground)
    diag.update(
        n_removed=int(removed.sum()),
        n_ground=n_ground,
        n_plant=n_plant,
        plant_fraction=float(plant_fraction),
    )

    # 4. ground plane and the aligned frame
    if n_ground < p.min_ground_points:
        raise RowFitError(
            f"no ground found: only {n_ground} of {len(pts_m)} points are ground-coloured "
            f"(a* >= {p.plant_a_below:g}), need at least {p.min_ground_points}; is soil visible "
            f"in the scene box (a closed canopy hides it from every photo), and are the "
            f"colours sRGB?"
        )
    normal, offset, g_in = ransac_plane(
        pts_m[ground], p.ground_threshold, p.ground_iterations, rng, p.ransac_score_points
    )
    lower = _lower_ground(pts_m, ground, normal, offset, g_in, plant, p, rng)
    if lower is not None:
        diag["ground_moved_down_from"] = int(g_in.sum())
        normal, offset, g_in = lower
    n_ground_in = int(g_in.sum())
    diag["n_ground_inliers"] = n_ground_in
    if n_ground_in < p.min_ground_points:
        raise RowFitError(
            f"no ground found: the best plane holds {n_ground_in} of {n_ground} ground-coloured "
            f"points (of {len(pts_m)}) within {p.ground_threshold:g} m, need at least "
            f"{p.min_ground_points}: the photos see too little soil (a closed canopy hides it) "
            f"or those points are not soil"
        )
    soil_canopy = soil_coloured_canopy(pts_m[~removed], ground[~removed], normal, offset, p)
    diag["soil_coloured_canopy"] = soil_canopy
    limit = p.max_soil_coloured_canopy
    if soil_canopy is not None and limit is not None and soil_canopy > limit:
        raise RowFitError(
            f"the canopy's leaves are not green: {soil_canopy:.0%} of the points standing more "
            f"than {2 * p.ground_threshold:g} m above the ground are soil-coloured "
            f"(a* >= {p.plant_a_below:g}), over the {limit:.0%} allowed, so the colour split "
            "would read the leaves as soil and the LAI far too low. A senescent (yellowing or "
            "brown) canopy, or colours that are not sRGB? "
            "(rowfit.preset.max_soil_coloured_canopy: null lets it through)"
        )
    if n_plant == 0:
        raise RowFitError(
            f"no rows found: none of {len(pts_m)} points is plant-coloured "
            f"(a* < {p.plant_a_below:g})"
        )
    if np.median(pts_m[plant] @ normal + offset) < 0:
        normal, offset = -normal, -offset
    rot = _frame_rotation(normal)
    origin_m = origin_scene * scale
    origin_m = origin_m - (origin_m @ normal + offset) * normal  # onto the ground plane
    world_from_scene = np.eye(4)
    world_from_scene[:3, :3] = scale * rot
    world_from_scene[:3, 3] = -rot @ origin_m

    # 5. dense-canopy switch
    dense = p.dense_plant_fraction is not None and plant_fraction > p.dense_plant_fraction
    used = p.dense() if dense else p

    # 6. rows
    q = (pts_m[plant] - origin_m) @ rot.T
    radius = np.hypot(q[:, 0], q[:, 1])
    scale_radius = used.roi_radius if used.scale_radius is None else used.scale_radius
    plant_xy = q[:, :2] if scale_radius is None else q[radius <= scale_radius, :2]
    if used.roi_radius is not None:
        q = q[radius <= used.roi_radius]
    diag["n_plant_roi"] = int(len(q))
    if len(q) == 0:
        raise RowFitError(
            f"no rows found: no plant points within the {used.roi_radius:g} m ROI cylinder"
        )
    top = float(np.percentile(q[:, 2], 99.5))
    diag["canopy_top"] = top
    if used.clear_canopy:
        from cropcraft_core.observe.presets import clear_render_height, observed_clearance

        h = clear_render_height(crop, used.render_height, top, observed_clearance(crop))
        if h != used.render_height:
            diag["render_height_raised_from"] = float(used.render_height)
            used = replace(used, render_height=h)
    cut = np.percentile(q[:, 2], used.height_percentile)
    xy = q[q[:, 2] >= cut, :2]
    diag["height_cut"] = float(cut)
    diag["n_row_points"] = int(len(xy))
    rows, inlier_sets, stop = _sequential_rows(xy, used, rng)
    diag["row_stop"] = stop
    if not rows:
        raise RowFitError(
            f"no rows found: {len(xy)} plant points above the {used.height_percentile:g}th "
            f"height percentile ({cut:.3f} m) hold no line with at least {used.min_row_inliers} "
            f"points within {used.line_threshold:g} m (stop: {stop})"
        )
    order = sorted(range(len(rows)), key=lambda i: -rows[i].n_inliers)
    rows = [rows[i] for i in order]
    best_xy = inlier_sets[order[0]]
    if used.refine_direction_deg is not None:
        soil = (pts_m[ground][g_in] - origin_m) @ rot.T
        rows[0], best_xy = _refine_row(
            xy, rows[0], used, direction_xy=q[:, :2], soil_xy=soil[:, :2]
        )
        if used.row_spacing is not None:
            rows[0], best_xy, diag["row_phase_from"] = _snap_to_row_pattern(
                q[:, :2], xy, rows[0], used, soil_xy=soil[:, :2]
            )

    # 7. camera above the mean of the best row's inliers (on the pattern's line when snapped)
    center = rows[0].point if used.row_spacing is not None else best_xy.mean(axis=0)
    camera = PinholeCamera.look_down(
        (float(center[0]), float(center[1])),
        used.render_height,
        (float(rows[0].direction[0]), float(rows[0].direction[1])),
        0.0,
    )
    return RowFit(
        crop=crop,
        preset=used,
        ground_normal=normal.copy(),
        ground_offset=float(offset / scale),
        ground_inliers=n_ground_in,
        world_from_scene=world_from_scene,
        scale=float(scale),
        scale_source=scale_source,
        rows=tuple(rows),
        camera=camera,
        dense=bool(dense),
        row_points=xy,
        plant_xy=plant_xy,
        diagnostics=diag,
    )


#: The canopy's points must be at least this share of all points for
#: :func:`soil_coloured_canopy` to judge their colour (on bare soil the few points above it
#: are floaters).
CANOPY_MIN_SHARE = 0.1


#: :func:`_lower_ground`: another plane counts as the same ground's only within this angle.
LOWER_GROUND_MAX_ANGLE_DEG = 10.0
#: ... and is sought only where at least this share of the plant points lie more than two
#: thresholds on the fitted plane's less populated side (a ground has the plants on one side;
#: the stored clouds whose ground was right read under 3 %, a 25 m flight's plane 13 %).
LOWER_GROUND_MIN_ACROSS = 0.05


def _plants_across(plants: np.ndarray, normal: np.ndarray, offset: float, t: float) -> float:
    """The share of ``plants`` more than ``t`` from the plane on its less populated side."""
    h = plants @ normal + offset
    return float(min((h > t).sum(), (h < -t).sum())) / max(1, len(plants))


def _lower_ground(
    pts: np.ndarray,
    ground: np.ndarray,
    normal: np.ndarray,
    offset: float,
    inliers: np.ndarray,
    plant: np.ndarray,
    p: RowFitPreset,
    rng: np.random.Generator,
) -> tuple[np.ndarray, float, np.ndarray] | None:
    """The ground plane again where the RANSAC's (``normal``, ``offset``) cuts through the
    canopy (:data:`LOWER_GROUND_MIN_ACROSS` of the plant points on its less populated side):
    the ground-coloured points more than two thresholds off it on either side are searched for
    a parallel plane (:data:`LOWER_GROUND_MAX_ANGLE_DEG`) with at least ``p.lower_ground_share``
    of its inliers, and the one with the fewest plant points across it is the ground where it
    has at most half the first's. Returns (normal, offset, inliers over ``ground``'s points)
    or None. It draws from a copy of ``rng``, so the fit's own draws are as before."""
    share = p.lower_ground_share
    if share is None:
        return None
    t = 2 * p.ground_threshold
    plants = pts[plant]
    across = _plants_across(plants, normal, offset, t)
    if across < LOWER_GROUND_MIN_ACROSS:
        return None
    g = pts[ground]
    h = g @ normal + offset
    need = max(p.min_ground_points, share * int(inliers.sum()))
    rng = copy.deepcopy(rng)
    best = None
    for side in (h > t, h < -t):
        if side.sum() < need:
            continue
        n2, off2, in2 = ransac_plane(
            g[side], p.ground_threshold, p.ground_iterations, rng, p.ransac_score_points
        )
        if in2.sum() < need or abs(float(n2 @ normal)) < math.cos(
            math.radians(LOWER_GROUND_MAX_ANGLE_DEG)
        ):
            continue
        a2 = _plants_across(plants, n2, off2, t)
        if a2 <= 0.5 * across and (best is None or a2 < best[0]):
            best = (a2, n2, off2)
    if best is None:
        return None
    _, n2, off2 = best
    return n2, off2, np.abs(g @ n2 + off2) < p.ground_threshold


def soil_coloured_canopy(
    points: np.ndarray, ground: np.ndarray, normal: np.ndarray, offset: float, p: RowFitPreset
) -> float | None:
    """The share of the canopy's points that are soil-coloured (``ground``): the canopy is
    the points more than ``2 * p.ground_threshold`` from the ground plane on the side that
    holds more of them. None where those are under :data:`CANOPY_MIN_SHARE` of ``points``."""
    h = points @ normal + offset
    t = 2 * p.ground_threshold
    up, down = h > t, h < -t
    canopy = up if up.sum() >= down.sum() else down
    if canopy.sum() < CANOPY_MIN_SHARE * max(1, len(points)):
        return None
    return float(ground[canopy].mean())


def _frame_rotation(normal: np.ndarray) -> np.ndarray:
    """(3, 3) rotation whose rows are the world axes in scene coordinates: z = ``normal``, x =
    the scene x axis projected onto the ground (scene y if x is nearly vertical)."""
    z = normal / np.linalg.norm(normal)
    for axis in (np.array([1.0, 0, 0]), np.array([0, 1.0, 0])):
        x = axis - (axis @ z) * z
        if np.linalg.norm(x) > 0.1:
            break
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z])


def _sequential_rows(
    xy: np.ndarray, p: RowFitPreset, rng: np.random.Generator
) -> tuple[list[Row], list[np.ndarray], str]:
    """Sequential RANSAC lines on (n, 2) ground-plane points. Returns the rows (refitted by least
    squares), each row's (k, 2) inlier points and why fitting stopped."""
    start = len(xy)
    remaining = xy
    rows: list[Row] = []
    inlier_sets: list[np.ndarray] = []
    while True:
        if len(remaining) < p.stop_min_points:
            return rows, inlier_sets, f"fewer than {p.stop_min_points} points remain"
        if len(remaining) < p.stop_min_fraction * start:
            return rows, inlier_sets, f"fewer than {p.stop_min_fraction:.0%} of the points remain"
        if len(rows) >= p.max_rows:
            return rows, inlier_sets, f"max_rows ({p.max_rows}) reached"
        direction, point, inl = ransac_line_2d(
            remaining, p.line_threshold, p.line_iterations, rng, p.ransac_score_points
        )
        if inl.sum() < max(2, p.min_row_inliers):
            return rows, inlier_sets, f"best line has fewer than {p.min_row_inliers} inliers"
        sel = remaining[inl]
        for i in range(p.refit_iterations):
            direction, point = fit_line_lsq(sel)
            if i + 1 < p.refit_iterations:  # re-gather the inliers around the refitted line
                nrm = np.array([-direction[1], direction[0]])
                again = np.abs((remaining - point) @ nrm) < p.line_threshold
                if again.sum() < 2:
                    break
                inl, sel = again, remaining[again]
        point = sel.mean(axis=0)
        rows.append(Row(_canonical(direction), point, int(inl.sum())))
        inlier_sets.append(sel)
        remaining = remaining[~inl]


#: The widest lateral profile binned as it is (metres; 1 cm bins): a field a kilometre across.
#: Wider, the points beyond half of it from their median are stray ones (a NeRF's or SfM's
#: floaters far from the plot, with no scene box to cut them) and are left out: their
#: distance made the profile's time and memory grow without bound (10 km: 10 s per fit;
#: 1e5 km: a 74 GiB allocation).
PROFILE_SPAN_M = 1000.0


def _lateral_profile(u: np.ndarray, period_bins: int, sigma_bins: float = 2.0) -> np.ndarray:
    """The row-scale part of the lateral profile of offsets ``u`` (m): their 1 cm-bin histogram
    less its moving average over ``period_bins`` bins (the plot's envelope, a closed canopy's
    fill between rows), smoothed by a Gaussian of ``sigma_bins`` bins (structure finer than
    that: a TSDF's voxel lattice, single leaf edges)."""
    from scipy.ndimage import gaussian_filter1d, uniform_filter1d

    if u.size and float(u.max() - u.min()) > PROFILE_SPAN_M:  # far floaters: left out
        u = u[np.abs(u - np.median(u)) <= 0.5 * PROFILE_SPAN_M]
    h = np.bincount(np.floor((u - u.min()) / 0.01).astype(np.int64)).astype(float)
    return gaussian_filter1d(h - uniform_filter1d(h, period_bins, mode="nearest"), sigma_bins)


def _autocorrelation(h: np.ndarray, lo: int, hi: int) -> np.ndarray:
    """``sum_b h[b] h[b + L]`` for the lags L = ``lo`` … ``hi``, each one dot product: the same
    numbers as ``np.correlate(h, h, "full")`` at those lags (bit for bit: numpy's correlate
    takes the same dot per lag), without its every other lag. A 120 m wide field's 12,000-bin
    profile took 0.27 s an angle in full."""
    return np.array([h[: len(h) - lag] @ h[lag:] for lag in range(lo, hi + 1)])


def _direction_scores(
    rel: np.ndarray, angles: np.ndarray, period_m: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """How well (n, 2) points line up along each of (k,) angles, from their row-scale lateral
    profile ``h`` across the lines (:func:`_lateral_profile`, high-passed at ``period_m``, 1-bin
    Gaussian, mean removed). Returns (k,) each of:

    * periodicity: the profile's autocorrelation sum ``sum_b h[b] h[b + L]`` at its best lag L
      within 0.6–1.6 × ``period_m`` and overlapping at least one period (0 where the profile
      is too short for that: one row's tails correlate by chance) -- the parallel rows line up
      with each other only along the true direction. Noise (a closed canopy's fill,
      reconstruction speckle) adds nothing to it in expectation at a lag other than 0, unlike
      the profile's energy;
    * normalised: that correlation per overlapping bin over the energy per bin (the period's
      strength, 0–1, as in :func:`estimate_scale_from_rows`);
    * energy: ``sum_b h[b]^2``, for scenes with no visible period (a single row).

    Measured against the raw sharpness used before (sum of squared 1 cm-bin counts, no
    high-pass or smoothing), which failed both ways on SfM scenes: marching-cubes vertices lie
    on the TSDF's voxel edges, whose lattice aliases with 1 cm bins into a spike at exactly the
    scene axes (98.7 % of the row peak on one reconstruction; above it on another of the same
    SfM model: 6.2° off), and a leaf fill inside the axis-aligned scene box projects to a box,
    the sharpest envelope, along the box's axes (8–20° off, the axis, on synthetic closed
    canopies with twice as many fill points as leaf points; 82° with as many, on a 7.5 mm
    lattice)."""
    period_bins = max(3, round(period_m / 0.01))
    lo, hi = int(0.6 * period_bins), int(math.ceil(1.6 * period_bins))
    periodic, normalised, energy = (np.zeros(len(angles)) for _ in range(3))
    for i, a in enumerate(angles):
        h = _lateral_profile(rel @ np.array([-math.sin(a), math.cos(a)]), period_bins, 1.0)
        h -= h.mean()
        energy[i] = float(h @ h)
        top = min(hi, len(h) - period_bins)  # at least a period of overlap: not one row's tails
        if top < lo or energy[i] <= 0:
            continue
        ac = _autocorrelation(h, lo, top)
        j = int(np.argmax(ac))
        periodic[i] = float(ac[j])
        normalised[i] = (ac[j] / (len(h) - lo - j)) / (energy[i] / len(h))
    return periodic, normalised, energy


def _refine_row(
    xy: np.ndarray,
    row: Row,
    p: RowFitPreset,
    direction_xy: np.ndarray | None = None,
    soil_xy: np.ndarray | None = None,
) -> tuple[Row, np.ndarray]:
    """Refine the best row (not in the paper; ``refine_direction_deg=None`` turns it off).

    Direction: within ±``refine_direction_deg`` of the RANSAC row, the direction whose lateral
    profile of ``direction_xy`` (default: all (n, 2) row points; the row fit passes every plant
    point, at any height — the points above the height cut of a closed canopy once gave a
    sharper profile 33° off the rows on an SfM scene, all plant points did not) is most
    periodic at about the row period (the preset's ``row_spacing``, else 4 × ``line_threshold``;
    :func:`_direction_scores`), or, where no period shows (normalised correlation at most
    ``direction_min_correlation``, or along a profile with under half the largest energy: one
    row), has the most row-scale energy: parallel rows,
    stems and the gaps between rows line up only along the true direction, whatever the length
    of the chord through the scene box (plain RANSAC counts favour the box diagonal when the
    canopy is nearly closed). Searched at 0.5° steps, then 0.02° steps around the best.
    With ``soil_xy`` (j, 2), the ground plane's soil points (at least
    ``MIN_SOIL_PHASE_POINTS``), their profile is scored too, and the direction comes from the
    soil's where its period is clearly the stronger (normalised correlation above the plants' by
    ``SOIL_DIRECTION_MARGIN``, and above ``SOIL_MIN_CORRELATION``): in a closed canopy of wide
    plants the soil between the rows is the clearer pattern (a synthetic soybean canopy with
    long petioles, true poses: plants 6.2° off at 0.50, soil 0.2° off at 0.81), but where both
    show the period the plants' direction is the more precise (four other canopies: plants
    0.09–0.38° off at 0.89–0.96, soil 0.41–1.6° off at 0.69–0.91).
    Offset: the paper's criterion along that direction -- the band of half-width
    ``line_threshold`` holding the most points -- then mean shift of the band to the mean of its
    points. Returns the row and its (k, 2) inliers."""
    base = math.atan2(row.direction[1], row.direction[0])
    span = math.radians(p.refine_direction_deg)
    c0 = xy.mean(axis=0)
    rel = xy - c0
    dxy = rel if direction_xy is None else direction_xy - direction_xy.mean(axis=0)
    # high-pass at the row period: the known planting spacing, else a typical row's 4 line widths
    period = p.row_spacing if p.row_spacing is not None else 4 * p.line_threshold
    step = math.radians(0.5)
    # every 0.5° within the span, the RANSAC row's own direction among them however narrow
    coarse = base + (
        np.arange(-span, span + 1e-12, step) if span >= step else np.r_[-span, 0, span]
    )
    periodic, normalised, energy = _direction_scores(dxy, coarse, period)
    k = int(np.argmax(periodic))
    # the rows' period where it shows (as strong as the scale estimate needs) along a sharp
    # profile; else the energy: one row seen obliquely correlates with its own smeared tails
    # (normalised 0.61 at 21° off on a synthetic single row, with 5 % of the sharpest energy;
    # every multi-row cloud measured had its period's direction at the energy's maximum)
    periodic_ok = normalised[k] > p.direction_min_correlation and energy[k] >= 0.5 * energy.max()
    if soil_xy is not None and len(soil_xy) >= MIN_SOIL_PHASE_POINTS:
        sxy = soil_xy - soil_xy.mean(axis=0)
        s_per, s_norm, s_en = _direction_scores(sxy, coarse, period)
        ks = int(np.argmax(s_per))
        soil_ok = s_norm[ks] > SOIL_MIN_CORRELATION and s_en[ks] >= 0.5 * s_en.max()
        if soil_ok and (not periodic_ok or s_norm[ks] > normalised[k] + SOIL_DIRECTION_MARGIN):
            dxy, periodic, normalised, energy, k, periodic_ok = sxy, s_per, s_norm, s_en, ks, True
    use = 0 if periodic_ok else 2
    a0 = float(coarse[k] if use == 0 else coarse[int(np.argmax(energy))])
    fine = a0 + np.radians(np.arange(-1.0, 1.0 + 1e-9, 0.02))
    if span < math.pi / 2:  # within the span (at 90° either side every direction is in it)
        fine = np.clip(fine, base - span, base + span)
    a = float(fine[int(np.argmax(_direction_scores(dxy, fine, period)[use]))])
    d = np.array([math.cos(a), math.sin(a)])
    u = rel @ np.array([-d[1], d[0]])
    us = np.sort(u)
    w = 2 * p.line_threshold
    counts = np.searchsorted(us, us + w, side="right") - np.arange(len(us))
    c = float(us[int(np.argmax(counts))] + p.line_threshold)
    inl = np.abs(u - c) < p.line_threshold
    for _ in range(100):
        if inl.sum() < 2:
            break
        c_new = float(u[inl].mean())
        inl_new = np.abs(u - c_new) < p.line_threshold
        if inl_new.sum() < 2:
            break
        converged = abs(c_new - c) < 1e-6
        c, inl = c_new, inl_new
        if converged:
            break
    sel = xy[inl]
    return Row(_canonical(d), sel.mean(axis=0), int(inl.sum())), sel


def _snap_to_row_pattern(
    plant_xy: np.ndarray,
    xy: np.ndarray,
    row: Row,
    p: RowFitPreset,
    soil_xy: np.ndarray | None = None,
) -> tuple[Row, np.ndarray, str]:
    """Move the best row onto the nearest centre line of the periodic row pattern (see
    ``RowFitPreset.row_spacing``); inliers are taken from the row points ``xy`` (k, 2) as before.

    The pattern's phase comes from the lateral offsets, modulo the spacing, of either *all*
    plant points (m, 2) (the upper slice alone is only weakly periodic: their circular mean is
    the row) or the ground plane's soil points ``soil_xy`` (j, 2) (soil shows between the rows:
    their circular mean plus half a spacing is the row), whichever is the more periodic (the
    larger mean resultant length). In a closed canopy of wide plants the leaves of neighbouring
    rows pile up between the rows and the plant points' phase is the inter-row: on a synthetic
    soybean canopy with long petioles (true poses) the plant phase was 0.377 m off (strength
    0.11) and the soil's 0.008 m (0.59); on two others the soil's strength was 0.36 and 0.85
    against the plants' 0.15 and 0.21 (cameras 1.4 → 0.4 and 3.9 → 2.3 cm off the row), on a
    fourth 0.66 against 0.11 and the camera went from 0.4 to 3.1 cm off. Returns the row, its
    inliers and the cue used ('plant' or 'soil')."""
    d = row.direction
    n = np.array([-d[1], d[0]])
    k = 2 * math.pi / p.row_spacing

    def circular(points: np.ndarray) -> tuple[float, float]:
        z = np.exp(1j * k * ((points - row.point) @ n)).mean()
        return float(np.angle(z)) / k, float(abs(z))

    phase, strength = circular(plant_xy)
    cue = "plant"
    if soil_xy is not None and len(soil_xy) >= MIN_SOIL_PHASE_POINTS:
        soil_phase, soil_strength = circular(soil_xy)
        if soil_strength > strength:
            phase, cue = soil_phase + 0.5 * p.row_spacing, "soil"
    c = phase + p.row_spacing * round(-phase / p.row_spacing)  # the line nearest the band's
    u = (xy - row.point) @ n
    inl = np.abs(u - c) < p.line_threshold
    sel = xy[inl]
    along = float(((sel - row.point) @ d).mean()) if len(sel) else 0.0
    return Row(d, row.point + along * d + c * n, int(inl.sum())), sel, cue


#: fewest soil points whose phase :func:`_snap_to_row_pattern` weighs against the plants'
MIN_SOIL_PHASE_POINTS = 100
#: the soil's period sets the direction only where its normalised correlation beats the plants'
#: by this much: with fewer points in broader bands it gives a less precise direction (on a
#: synthetic canopy whose soil scored 0.91 against the plants' 0.90 the row went 0.77° off
#: instead of 0.08°, and 0.81° through SfM)
SOIL_DIRECTION_MARGIN = 0.1
#: the soil's period sets the direction only above this normalised correlation: uniform soil
#: (300–20,000 points, no rows) reaches up to 0.50 by chance; the soil between real rows
#: measured 0.68–0.90 on five synthetic soybean canopies
SOIL_MIN_CORRELATION = 0.6


# --------------------------------------------------------------------------- metric scale
@dataclass(frozen=True)
class ScaleEstimate:
    """Result of :func:`estimate_scale_from_rows`."""

    factor: float
    """Multiply the fit's scale (metres per scene unit) by this to make it metric."""
    spacing: float | None
    """Measured row spacing in the fit's current metres; ``None`` when it could not be measured."""
    n_rows: int
    """Parallel fitted rows (at least half the best row's inliers, within 10° of it)."""
    method: str
    """``"profile_autocorrelation"``, ``"neighbour_median"`` or ``"fallback_unchanged"``."""
    neighbour_spacing: float | None = None
    """Robust median of the gaps between neighbouring parallel fitted rows (a cross-check)."""


def _neighbour_spacing(rowfit: RowFit, max_angle_deg: float, min_fraction: float) -> tuple:
    best = rowfit.best_row
    cos_max = math.cos(math.radians(max_angle_deg))
    par = [
        r
        for r in rowfit.rows
        if abs(float(r.direction @ best.direction)) >= cos_max
        and r.n_inliers >= min_fraction * best.n_inliers
    ]
    if len(par) < 2:
        return None, len(par)
    gaps = np.diff(np.sort([float(best.distance(r.point)) for r in par]))
    m0 = float(np.median(gaps))
    k = np.round(gaps / m0) if m0 > 0 else np.zeros_like(gaps)
    ok = k >= 1
    if not ok.any():
        return None, len(par)
    return float(np.median(gaps[ok] / k[ok])), len(par)


def estimate_scale_from_rows(
    rowfit: RowFit,
    known_row_spacing: float,
    search: tuple[float, float] = (0.6, 1.6),
    min_correlation: float = 0.1,
    max_angle_deg: float = 10.0,
    min_inlier_fraction: float = 0.5,
) -> ScaleEstimate:
    """Scale correction from the fitted rows against the known planting row spacing (metres).

    Primary (``"profile_autocorrelation"``): the lateral profile across the best row (1 cm
    histogram of the offsets along its normal) of every plant point within the preset's
    ``scale_radius`` is periodic with the row spacing; it is high-passed (its moving average
    over one known spacing removed, then a 2-bin Gaussian) and autocorrelated (per overlapping
    bin), and the spacing is the lag of the strongest *peak* (local maximum)
    within ``search`` × ``known_row_spacing`` (parabolic sub-bin refinement), accepted when the
    normalised autocorrelation there exceeds ``min_correlation``. This uses every point, not
    only the few fitted lines, and is immune to the biases of individual RANSAC bands.

    Secondary (``"neighbour_median"``): fitted rows within ``max_angle_deg`` of the best row and
    with at least ``min_inlier_fraction`` of its inliers are projected onto its normal; the gaps
    between neighbours, each divided by its near-integer multiple of the median gap (rows missed
    in between), give the spacing as their median. Always reported as ``neighbour_spacing``;
    used only when the profile shows no period. On synthetic canopies it is the less reliable
    of the two: band positions of neighbouring rows are biased by several cm on flat-topped
    canopies, and leftovers between rows form spurious mid-row lines (half the spacing), which
    is why only rows with at least half the best row's inliers count.

    Fallback (``"fallback_unchanged"``): when neither works -- one row only, no periodic
    profile -- the factor is 1 (scale unchanged); callers then keep their previous scale source
    or ask for a scale hint.
    """
    if not (math.isfinite(known_row_spacing) and known_row_spacing > 0):
        raise ConfigError(f"known row spacing must be positive, got {known_row_spacing!r}")
    nb, n_rows = _neighbour_spacing(rowfit, max_angle_deg, min_inlier_fraction)
    period_bins = max(3, round(known_row_spacing / 0.01))

    def profile_acf(xy: np.ndarray) -> np.ndarray | None:
        """Normalised autocorrelation of the lateral profile, high-passed: the plot's envelope
        (and a dense canopy's fill between rows) would make it fall monotonically, so that its
        largest value in the window sat on the window's edge (measured: a 36 % scale error per
        pass on a dense SfM scene)."""
        if len(xy) < 10:
            return None
        h = _lateral_profile(xy @ rowfit.best_row.normal, period_bins)
        h -= h.mean()
        # the lags up to just past the search window (a peak there needs its right neighbour)
        ac = _autocorrelation(h, 0, min(len(h) - 1, int(search[1] * known_row_spacing / 0.01) + 2))
        # per overlapping bin: the plain sum falls with the lag (fewer overlapping bins), which
        # pulled peaks to shorter lags (0.7 % on an exact canopy cloud)
        ac = ac / np.maximum(len(h) - np.arange(len(ac)), 1)
        return ac / ac[0] if ac[0] > 0 else None

    # every plant point, at any height: the row period shows even through a closed canopy's
    # fill (the soil between rows shows it more clearly but measured the period 1-2 % short:
    # oblique views see the gaps' far sides)
    ac = profile_acf(rowfit.plant_xy if len(rowfit.plant_xy) else rowfit.row_points)
    if ac is not None:
        lags = np.arange(len(ac)) * 0.01
        window = np.flatnonzero(
            (lags >= search[0] * known_row_spacing) & (lags <= search[1] * known_row_spacing)
        )
        window = window[(window > 0) & (window < len(ac) - 1)]
        peaks = window[(ac[window] >= ac[window - 1]) & (ac[window] >= ac[window + 1])]
        if len(peaks):
            i = int(peaks[np.argmax(ac[peaks])])
            if ac[i] > min_correlation:
                off = 0.0
                if 0 < i < len(ac) - 1:
                    y0, y1, y2 = ac[i - 1 : i + 2]
                    den = y0 - 2 * y1 + y2
                    off = 0.5 * (y0 - y2) / den if den != 0 else 0.0
                spacing = (i + off) * 0.01
                return ScaleEstimate(
                    known_row_spacing / spacing, spacing, n_rows, "profile_autocorrelation", nb
                )
    if nb is not None:
        return ScaleEstimate(known_row_spacing / nb, nb, n_rows, "neighbour_median", nb)
    return ScaleEstimate(1.0, None, n_rows, "fallback_unchanged", None)


def fit_rows_with_scale(
    points: np.ndarray,
    colors: np.ndarray,
    crop: str,
    preset: RowFitPreset | None = None,
    rng: np.random.Generator | int | None = None,
    *,
    metric_scale: float | None = None,
    scale_hint: float | None = None,
    known_row_spacing: float | None = None,
    metric_source: str = "metric_poses",
    camera_height: tuple[np.ndarray, float] | None = None,
    max_passes: int = 3,
    tolerance: float = 0.01,
    cameras: np.ndarray | None = None,
    nadir: bool = False,
    gps_reason: str | None = None,
) -> RowFit:
    """:func:`fit_ground_and_rows` with the metric scale chosen by priority:

    0. ``camera_height`` ((n, 3) camera centres in the scene frame, the user's measured median
       camera height in metres): the scale is the metres over the cameras' median height above
       the *fitted* ground plane, refitted until it changes by at most ``tolerance`` (at most
       ``max_passes`` fits) → ``"camera_height"``. :func:`cropcraft_core.sfm.level_poses`
       scaled the poses by the same hint over the height above its own ground, the sparse
       points' lowest; under a closed canopy SfM finds no soil (a 2.2 m maize canopy from a
       drone: every sparse point at least 0.93 m up), which made that scale 20 % too large;
    1. ``metric_scale`` (metres per scene unit from metric imported poses, usually 1) →
       ``metric_source`` (``"metric_poses"``, or ``"camera_height"`` / ``"camera_distance"``
       for SfM poses scaled by
       the user's camera height in :func:`cropcraft_core.sfm.level_poses`);
    2. ``scale_hint`` (a user-given metres per scene unit) → ``"user_hint"``;
    3. ``known_row_spacing`` (metres): fit at scale 1, measure the row spacing, rescale and refit
       until the correction is within ``tolerance`` (at most ``max_passes`` refits) →
       ``"row_spacing"``; if the spacing cannot be measured, or a refit at the estimated
       scale does not confirm it, the scale-1 fit is returned with ``"assumed_metric"`` and
       ``diagnostics["scale_fallback"]`` explains why;
    4. nothing → scale 1, ``"assumed_metric"``.

    ``cameras`` ((n, 3) camera centres in the scene frame) with ``metric_scale`` and
    ``known_row_spacing``: the cameras' height the scale implies is put to the rows as a
    camera height's is (a camera distance in feet taken as metres); with the row-spacing
    route, a canopy standing far below the cameras (:data:`FAR_ABOVE_RATIO`) is warned of
    (``diagnostics["scale_warning"]``); ``nadir`` (the photos look straight down,
    ``sfm.frame.looks_down``): a hand-held scale that a drone's height could explain as well
    is refused (:data:`NADIR_AMBIGUOUS_RATIO`), saying ``gps_reason`` (why the photos' GPS
    positions did not set the scale) where given.

    The row-spacing route needs the first pass to find several rows: the metric thresholds
    (20 cm lines, 0.76 m rows) tolerate a scene scale off by roughly ±30 %.
    """
    if camera_height is not None:
        with _given_scale("the camera height given"):
            return _fit_with_camera_height(
                points,
                colors,
                crop,
                preset,
                _as_rng(rng),
                camera_height,
                max_passes,
                tolerance,
                known_row_spacing,
            )
    if metric_scale is not None:
        given = {
            "camera_height": "the camera height given",
            "camera_distance": "the camera distance given",
            "gps": "the photos' GPS positions",
        }.get(metric_source)
        with _given_scale(given) if given else contextlib.nullcontext():
            fit = fit_ground_and_rows(
                points, colors, crop, preset, rng, scale=metric_scale, scale_source=metric_source
            )
        if cameras is None or known_row_spacing is None:
            return fit
        if metric_source == "gps":
            # a scale the photos' positions measured (their spread against their error): the
            # rows only say how their period reads at it (a drone's rows can read a double
            # period, a soybean flight's the stereo's sampling: they cannot overrule it)
            est = estimate_scale_from_rows(fit, known_row_spacing, search=(0.85, 1.15))
            found = est.factor if est.method == "profile_autocorrelation" else None
            return replace(fit, diagnostics={**fit.diagnostics, "rows_factor": found})
        seed = int(_as_rng(rng).integers(2**63 - 1))  # after the fit: its draws are as before
        # the cameras' height the given scale implies, put to the rows like a camera height's
        above = fit.median_height(cameras)
        if not above > 0:
            return fit
        metres = above * metric_scale
        if metric_source == "metric_poses":
            from cropcraft_core.sfm.frame import HAND_HELD_CAMERA_HEIGHT_M

            if _within_check_factor(metres / HAND_HELD_CAMERA_HEIGHT_M):
                return fit  # a phone's height over any crop (a walk round maize)
            given = f"the imported poses, read as metres (they put the cameras {metres:.3g} m up)"
            advice = "if the poses are not in metres, set poses.imported_metric=false"
        else:
            given = f"{given or 'the scale'} (it puts the cameras {metres:.3g} m up)"
            advice = "check --camera-height"
        warning = _rows_disagree(
            points, colors, crop, preset, seed, above, metres, metric_scale,
            known_row_spacing, max_passes, tolerance, given=given, advice=advice,
        )  # fmt: skip
        if not warning:
            return fit
        return replace(fit, diagnostics={**fit.diagnostics, "scale_warning": warning})
    if scale_hint is not None:
        with _given_scale("the scale given (rowfit.scale)"):
            return fit_ground_and_rows(
                points, colors, crop, preset, rng, scale=scale_hint, scale_source="user_hint"
            )
    if known_row_spacing is None:
        return fit_ground_and_rows(points, colors, crop, preset, rng)
    fit = _fit_by_row_spacing(
        points, colors, crop, preset, rng, known_row_spacing, max_passes, tolerance
    )
    if cameras is not None and nadir:
        _check_nadir_scale(fit, cameras, gps_reason)
    warning = None if cameras is None else _far_above_warning(fit, cameras)
    if not warning:
        return fit
    return replace(fit, diagnostics={**fit.diagnostics, "scale_warning": warning})


#: Where the scale is the rows' (or assumed), a canopy whose top stands under this share of
#: the cameras' height above the ground is warned of: the photos were likely taken from far
#: higher than the crop's hand-held prior put them. Measured on stored scenes (session 96):
#: soybean walks 0.09 (a young canopy, 0.125 m) to 0.6, maize walks 0.7-1.3; drones over
#: soybean 0.04 and maize 0.02-0.09. A soybean drone flight (13 m) through SfM took the
#: hand-held 1.4 m prior, its rows "confirmed" a period 14x off and it read LAI 0.09 for 1.26
#: with nothing said of the scale (its canopy stood 3 cm tall, 3 % of the cameras' height).
FAR_ABOVE_RATIO = 0.06
_SCALE_FROM = {
    "row_spacing": "the rows' alone",
    "assumed_metric": "assumed (the crop's usual capture height)",
}


def _heights_at_scale(fit: RowFit, cameras: np.ndarray) -> tuple[float, float | None]:
    """``(the cameras' median height above fit's ground, its canopy top)`` in metres at fit's
    scale, the cameras ((n, 3), scene frame) taken on either side of the ground: at a scale
    far off the ground plane can lie in the canopy with the plants below it and the cameras
    then on its far side (a soybean drone flight read LAI 0.32 for 1.26 with nothing said:
    session 96's last audit)."""
    return abs(fit.median_height(cameras)) * fit.scale, fit.diagnostics.get("canopy_top")


def _far_above_warning(fit: RowFit, cameras: np.ndarray) -> str | None:
    """The warning where ``fit``'s canopy top is under :data:`FAR_ABOVE_RATIO` of the
    ``cameras``' ((n, 3), scene frame) median height above its ground, else None. The ratio
    does not depend on the scale, so it cannot tell a right scale from a wrong one: the warning
    gives the cameras' height and the canopy's at the scale for the user to judge."""
    above, top = _heights_at_scale(fit, cameras)
    if not (above > 0 and top is not None and top < FAR_ABOVE_RATIO * above):
        return None
    return (
        f"the cameras stand {above / max(top, 1e-9):.0f}x the canopy's height above the ground "
        f"(a drone's view?) and the scale is {_SCALE_FROM.get(fit.scale_source, fit.scale_source)}"
        f": at it the cameras are {above:.3g} m up and the canopy {100 * top:.3g} cm tall; if "
        "they are not, give --camera-height M (the cameras' height above the ground): a soybean "
        "drone flight scaled by the hand-held height read a canopy 14x too small"
    )


def _fit_by_row_spacing(
    points: np.ndarray,
    colors: np.ndarray,
    crop: str,
    preset: RowFitPreset | None,
    rng: np.random.Generator | int | None,
    known_row_spacing: float,
    max_passes: int,
    tolerance: float,
) -> RowFit:
    """The ``known_row_spacing`` route of :func:`fit_rows_with_scale` (its item 3)."""
    rng = _as_rng(rng)
    seed = int(rng.integers(2**63 - 1))
    scale = 1.0
    fit = fit_ground_and_rows(points, colors, crop, preset, np.random.default_rng(seed), scale=1.0)
    first = fit
    history = []
    for i in range(max_passes):
        # later passes only refine: a wide window could hop to another peak each pass
        est = estimate_scale_from_rows(
            fit, known_row_spacing, search=(0.6, 1.6) if i == 0 else (0.85, 1.15)
        )
        history.append(est.factor)
        if est.method == "fallback_unchanged":  # the scale-1 fit stands
            diag = {**first.diagnostics, "scale_fallback": "row spacing could not be measured"}
            if i:  # the first estimate took a wrong peak: no rows within 15 % at its scale
                diag["scale_fallback"] = (
                    f"row spacing not confirmed: the fit rescaled by {scale:.4g} shows no row "
                    "period within 15 % of the known spacing"
                )
                diag["scale_factors"] = history
            return replace(first, diagnostics=diag)
        scale *= est.factor
        fit = _seeded_fit(points, colors, crop, preset, seed, scale, "row_spacing")
        if abs(est.factor - 1.0) <= tolerance:
            break
    diag = {**fit.diagnostics, "scale_factors": history}
    return replace(fit, diagnostics=diag)


#: Nadir photos (a drone's, or a phone held over the plot) scaled by the hand-held prior whose
#: canopy top stands under this share of the cameras' height above the ground are refused
#: without a scale: the photos could be either's and the hand-held height a guess up to 10x
#: off. Measured (session 97), soybean by drone through SfM at that prior: 8 m 0.062, 13 m
#: 0.031-0.039, a 14 cm canopy from 13 m 0.0028, 20 m 0.013; its rows "confirmed" a scale
#: 7-14x off on three of the five (the drone's sampling ripples the plant points' profile at
#: the rows' period there: the rows cannot tell either). Nadir SfM clouds read the canopy's
#: top at 0.76-0.81 of the truth (those flights), so a drone 8 m or more up over a canopy up
#: to 1.5 m reads under 0.15; a phone held 1.7 m straight down over a 0.61 m canopy read
#: 0.337 through SfM (its top at 0.94 of the truth) and its rows set the scale.
NADIR_AMBIGUOUS_RATIO = 0.15


def _length(metres: float) -> str:
    """A height for a message: centimetres under a metre (2 figures), else metres."""
    return f"{100 * metres:.2g} cm" if metres < 1 else f"{metres:.2g} m"


def _check_nadir_scale(fit: RowFit, cameras: np.ndarray, gps_reason: str | None = None) -> None:
    """Stop where ``fit`` (nadir photos, the rows' or assumed scale) has its cameras at a
    hand-held height (within :data:`SCALE_CHECK_FACTOR` of ``HAND_HELD_CAMERA_HEIGHT_M``) and
    its canopy top under :data:`NADIR_AMBIGUOUS_RATIO` of it: a drone could have taken them.
    ``gps_reason``: why the photos' own GPS positions could not set the scale, said too."""
    from cropcraft_core.sfm.frame import HAND_HELD_CAMERA_HEIGHT_M

    above, top = _heights_at_scale(fit, cameras)
    if not (
        above > 0 and top is not None and _within_check_factor(above / HAND_HELD_CAMERA_HEIGHT_M)
    ):
        return
    if top >= NADIR_AMBIGUOUS_RATIO * above:
        return  # a canopy too tall for a drone 8 m up to show so: a phone held over it
    raise RowFitError(
        "the scale cannot be measured: the photos look straight down, as a drone's or a phone "
        f"held over the plot do, and the cameras stand {above / max(top, 1e-9):.0f}x the "
        f"canopy's height above the ground: {HAND_HELD_CAMERA_HEIGHT_M:g} m up the canopy "
        f"would be {_length(top * HAND_HELD_CAMERA_HEIGHT_M / above)} tall, 13 m up "
        f"{_length(top * 13.0 / above)}, and the rows cannot tell which (a 13 m soybean "
        "flight's rows confirmed the hand-held scale 14x off). Give --camera-height M (the "
        "cameras' median height above the ground; in a season, camera_height in that date's "
        "known.json) or --camera-distance PHOTO_A PHOTO_B M"
        + (f". The photos' GPS positions could not set it: {gps_reason}" if gps_reason else "")
    )


@contextlib.contextmanager
def _given_scale(source: str) -> Iterator[None]:
    """A row fit at a scale the rows did not set: its failure names where the scale came from
    (a camera distance 10x short read the canopy 3.7 cm tall and said only "no rows found")."""
    try:
        yield
    except RowFitError as exc:
        raise RowFitError(
            f"{exc}; the scale came from {source}: if it is off, every height and spacing "
            "above is too"
        ) from exc


def _fit_with_camera_height(
    points: np.ndarray,
    colors: np.ndarray,
    crop: str,
    preset: RowFitPreset | None,
    rng: np.random.Generator,
    camera_height: tuple[np.ndarray, float],
    max_passes: int,
    tolerance: float,
    known_row_spacing: float | None = None,
) -> RowFit:
    """The ``camera_height`` route of :func:`fit_rows_with_scale`; with ``known_row_spacing``,
    checked against the rows where the height is far from the crop's usual one
    (:func:`_rows_disagree`)."""
    centres, metres = camera_height
    c = np.asarray(centres, dtype=np.float64)
    if c.ndim != 2 or c.shape[1] != 3 or not len(c) or not np.all(np.isfinite(c)):
        raise InputError(f"camera centres must be finite with shape (n, 3), got {c.shape}")
    if not (isinstance(metres, int | float) and math.isfinite(metres) and metres > 0):
        raise InputError(f"camera height must be a positive number of metres, got {metres!r}")
    seed = int(rng.integers(2**63 - 1))
    scale, history = 1.0, []
    for _ in range(max_passes):
        fit = _seeded_fit(points, colors, crop, preset, seed, scale, "camera_height")
        above = fit.median_height(c)
        if not above > 0:
            raise RowFitError(
                "the cameras are not above the fitted ground plane (median height "
                f"{above:.3g} scene units): the camera-height hint cannot set the scale"
            )
        factor = float(metres) / above / scale
        history.append(factor)
        if abs(factor - 1.0) <= tolerance:
            break
        scale *= factor
    diag = {**fit.diagnostics, "scale_factors": history}
    if known_row_spacing is not None:
        warning = _rows_disagree(
            points, colors, crop, preset, seed, above, metres, scale,
            known_row_spacing, max_passes, tolerance,
        )  # fmt: skip
        if warning:
            diag["scale_warning"] = warning
    return replace(fit, diagnostics=diag)


#: How far a camera-height hint may lie from the crop's usual capture height, and the rows'
#: scale from the hint's, as a factor either way, before the rows are asked and a warning is
#: given: wide enough that a half or double row period (a dense canopy's mid-row fill, a
#: missed row) raises none. A 1.4 m hint for 13 m drone photos read LAI 0.018 against 1.79
#: with nothing said.
SCALE_CHECK_FACTOR = 2.5


def _within_check_factor(ratio: float) -> bool:
    """Whether two heights or scales of ratio ``ratio`` lie within :data:`SCALE_CHECK_FACTOR`
    of each other, either way."""
    return 1 / SCALE_CHECK_FACTOR <= ratio <= SCALE_CHECK_FACTOR


def _rows_disagree(
    points: np.ndarray,
    colors: np.ndarray,
    crop: str,
    preset: RowFitPreset | None,
    seed: int,
    above_units: float,
    metres: float,
    scale: float,
    known_row_spacing: float,
    max_passes: int,
    tolerance: float,
    given: str | None = None,
    advice: str = "check --camera-height",
) -> str | None:
    """A warning where the rows contradict a camera-height hint ``metres`` (the scene's scale
    ``scale`` m per unit): only where the hint is more than :data:`SCALE_CHECK_FACTOR` from
    the crop's usual capture height (``sfm.frame.PRIOR_CAMERA_HEIGHT_M``), the rows' scale is
    sought from that usual height (the cameras ``above_units`` over the fitted ground) as the
    row-spacing route seeks it; confirmed and more than the factor from ``scale``, the rows
    disagree. None otherwise (no rows' period found: nothing to say). ``given``: what set the
    scale, for the warning (default: the camera height); ``advice``: what to check."""
    from cropcraft_core.sfm.frame import PRIOR_CAMERA_HEIGHT_M

    usual = PRIOR_CAMERA_HEIGHT_M.get(crop)
    if usual is None or _within_check_factor(metres / usual):
        return None
    rows = usual / above_units
    try:
        fit = _seeded_fit(points, colors, crop, preset, seed, rows, "row_spacing")
        for i in range(max_passes):
            est = estimate_scale_from_rows(
                fit, known_row_spacing, search=(0.6, 1.6) if i == 0 else (0.85, 1.15)
            )
            if est.method == "fallback_unchanged":
                return None  # no period, or not confirmed at its scale
            rows *= est.factor
            fit = _seeded_fit(points, colors, crop, preset, seed, rows, "row_spacing")
            if abs(est.factor - 1.0) <= tolerance:
                break
    except RowFitError:  # no ground or rows at that scale: the rows cannot say
        return None
    if _within_check_factor(rows / scale):
        return None
    given = given or f"the camera height given ({metres:g} m)"
    return (
        f"{given} and the rows disagree: at its scale the "
        f"rows are {known_row_spacing * scale / rows:.3g} m apart, not the layout's "
        f"{known_row_spacing:g} m; the rows put the cameras {metres * rows / scale:.3g} m "
        f"up. Every length and the LAI are read at the given scale: {advice} "
        "(or check the rows' spacing, --row-spacing M)"
    )


def _seeded_fit(
    points: np.ndarray,
    colors: np.ndarray,
    crop: str,
    preset: RowFitPreset | None,
    seed: int,
    scale: float,
    scale_source: str,
) -> RowFit:
    """One pass of the scale loops: the same seed every pass, so passes differ by scale only."""
    return fit_ground_and_rows(
        points,
        colors,
        crop,
        preset,
        np.random.default_rng(seed),
        scale=scale,
        scale_source=scale_source,
    )
