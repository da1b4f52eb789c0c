"""Row-fit errors against a known truth (synthetic scenes, surveyed plots).

The truth frame is metric, z up, ground z = 0, with rows at ``y = k · row_spacing`` after rotating
by the layout's row azimuth (the frame of :func:`cropcraft_core.procedural.generate_canopy` and of
``cropcraft synth`` scenes). ``scene_from_true`` maps truth points into the scene frame the row fit
worked in (a similarity: SfM frames have arbitrary scale, rotation and origin).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from cropcraft_core.config.layout import CanopyLayout
from cropcraft_core.errors import InputError
from cropcraft_core.geometry.camera import PinholeCamera
from cropcraft_core.rowfit.fit import RowFit


@dataclass(frozen=True)
class RowFitErrors:
    direction_deg: float
    """Angle between the fitted best row and the true row direction."""
    lateral_m: float
    """Distance of the row camera's ground point from the nearest true row."""
    height_rel: float
    """|true height of the row camera above the ground − render height| / render height: the
    metric-scale and ground-plane error as the observation sees it."""
    ground_normal_deg: float
    """Angle between the fitted up direction and the true one."""

    def to_dict(self) -> dict:
        return asdict(self)


def true_from_world(fit: RowFit, scene_from_true: np.ndarray) -> np.ndarray:
    """(4, 4) similarity: the fit's world frame → the truth frame (identity for a perfect fit)."""
    return np.linalg.inv(fit.world_from_scene @ np.asarray(scene_from_true, float))


def camera_in_truth(fit: RowFit, scene_from_true: np.ndarray) -> PinholeCamera:
    """The row camera placed in the truth frame (rigid: the similarity's scale is divided out
    of the rotation, the centre keeps its true position), to render the true mesh from."""
    t = true_from_world(fit, scene_from_true)
    r = t[:3, :3] / np.cbrt(np.linalg.det(t[:3, :3]))
    u, _, vt = np.linalg.svd(r)
    c = fit.camera
    m = np.eye(4)
    m[:3, :3] = (u @ vt) @ c.cam_to_world[:3, :3]
    m[:3, 3] = t[:3, :3] @ c.center + t[:3, 3]
    return PinholeCamera(c.width, c.height, c.fx, c.fy, c.cx, c.cy, m)


def row_fit_errors(fit: RowFit, scene_from_true: np.ndarray, layout: CanopyLayout) -> RowFitErrors:
    """Direction, lateral, height and ground-normal errors of ``fit`` in the true metric frame."""
    t = true_from_world(fit, scene_from_true)
    r = t[:3, :3] / np.cbrt(np.linalg.det(t[:3, :3]))
    a = math.radians(layout.row_azimuth_deg)
    d = r @ np.array([*fit.best_row.direction, 0.0])
    d /= np.linalg.norm(d)
    along = abs(float(d @ [math.cos(a), math.sin(a), 0.0]))
    c = t[:3, :3] @ fit.camera.center + t[:3, 3]
    y = -c[0] * math.sin(a) + c[1] * math.cos(a)
    lateral = abs(y - round(y / layout.row_spacing) * layout.row_spacing)
    n = r @ np.array([0.0, 0.0, 1.0])
    return RowFitErrors(
        direction_deg=math.degrees(math.acos(min(1.0, along))),
        lateral_m=float(lateral),
        height_rel=float(abs(c[2] - fit.render_height) / fit.render_height),
        ground_normal_deg=math.degrees(math.acos(min(1.0, float(n[2]) / np.linalg.norm(n)))),
    )


@dataclass(frozen=True)
class ContentRegistration:
    """How far a reconstruction's surfaces sit from where its cameras put them (truth frame)."""

    shift_m: tuple[float, float, float]
    """Translation (x, y, z) that moves the reconstructed points onto the true surfaces: x, y
    across the ground, + z = the reconstruction lies too low."""
    rotation_deg: float
    """Angle of the rigid correction's rotation."""
    fitness: float
    """Fraction of the reconstructed points within the last distance of a true surface."""
    rmse_m: float
    """RMS distance of those points from it."""

    def to_dict(self) -> dict:
        return asdict(self)


def register_to_truth(
    points: np.ndarray,
    scene_from_true: np.ndarray,
    true_points: np.ndarray,
    distances: tuple[float, ...] = (0.3, 0.1, 0.05),
) -> tuple[np.ndarray, ContentRegistration]:
    """Refine ``scene_from_true`` so that the reconstruction's own surfaces, not its cameras,
    land on the truth: rigid point-to-point ICP (Open3D) of ``points`` (n, 3, scene frame, mapped
    into the truth frame by the similarity) onto ``true_points`` (m, 3, truth frame: samples of
    the true mesh and of the ground), run at each of the decreasing matching ``distances`` (m)
    from the previous one's answer. The similarity's scale is kept.

    Why: the camera centres fix the similarity, but a structure-from-motion model's points can
    sit centimetres off its cameras (nearly parallel drone views leave a tilt of the whole model
    weakly constrained). The row camera is placed among the reconstructed plants, so its error
    against the rows is measured in this frame; the camera-centre frame adds the model's own
    shift. Returns the refined (4, 4) ``scene_from_true`` and the correction."""
    import open3d as o3d

    s = np.asarray(scene_from_true, float)
    true_from_scene = np.linalg.inv(s)
    pt = np.asarray(points, float) @ true_from_scene[:3, :3].T + true_from_scene[:3, 3]
    if len(pt) < 3 or len(true_points) < 3:
        raise InputError("register_to_truth needs at least 3 reconstructed and 3 true points")
    if not distances:
        raise InputError("register_to_truth needs at least one matching distance")
    src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pt))
    tgt = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(true_points, float)))
    t = np.eye(4)
    for d in distances:
        result = o3d.pipelines.registration.registration_icp(
            src,
            tgt,
            float(d),
            t,
            o3d.pipelines.registration.TransformationEstimationPointToPoint(),
            o3d.pipelines.registration.ICPConvergenceCriteria(max_iteration=60),
        )
        t = np.asarray(result.transformation)
    refined = s @ np.linalg.inv(t)
    cos = float(np.clip((np.trace(t[:3, :3]) - 1.0) / 2.0, -1.0, 1.0))
    return refined, ContentRegistration(
        shift_m=tuple(float(x) for x in t[:3, 3]),
        rotation_deg=math.degrees(math.acos(cos)),
        fitness=float(result.fitness),
        rmse_m=float(result.inlier_rmse),
    )
