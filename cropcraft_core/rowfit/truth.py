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
