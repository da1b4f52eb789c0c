"""Row cameras over the best row's neighbours: the same look-down camera moved across the rows.

The paper observes one row (the row fit's best). Fitted over each row of one reconstruction,
answers differ by tens of points (benchmarks/RESULTS.md#leads-33), so a scene may also be
observed over the rows beside it. The k-th neighbour's camera is the best row's camera moved
by k row spacings along its image y axis (the ground normal of the rows), at the same height
and heading: on the row fit's periodic row pattern, whose phase placed the best row
(``_snap_to_row_pattern``) and whose spacing set the metric scale where it came from the rows.

Optionally (``snap_fraction``) a camera sits over a fitted row instead where one runs there
(parallel within ``max_angle_deg``, within ``snap_fraction`` of a spacing of the expected
place), for plots whose rows are not planted ``row_spacing`` apart. Not the default: the
fitted rows other than the best are plain RANSAC lines (the band of ``line_threshold``
holding the most points of the upper canopy), and on the demo's canopy through SfM both side
rows' lines lay 7 cm off their true rows, on the same side, where the pattern placed the
cameras within 0.8 cm; the side rows' fits there read +133 % and +139 % LAI, while on
observations at exactly one spacing the true parameters scored lower than either of those
answers (benchmarks/RESULTS.md#rows-34, session 36).

Whether a neighbour's view lies inside the reconstruction is the caller's test (it needs the
surfaces: ``no_surface_fraction`` of a render).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from cropcraft_core.errors import ConfigError
from cropcraft_core.geometry.camera import PinholeCamera
from cropcraft_core.rowfit.fit import Row, camera_to_scene

#: The most neighbours fitted on each side of the best row (a 2 m plot holds 2–3 rows; a fit
#: per row is the cost).
MAX_NEIGHBOURS = 4


@dataclass(frozen=True, eq=False)
class RowView:
    """One row camera of a scene.

    index: signed row number, 0 the best row, +k the k-th row along the camera's image y axis
    (image down: to the right of the row direction seen from above), −k the other side.
    offset_m: the camera's signed distance from the best row's camera along that axis (m).
    snapped: whether it sits over a fitted row (else at ``index`` row spacings; always so
    without ``snap_fraction``). camera: the
    look-down camera in the world frame.
    """

    index: int
    offset_m: float
    snapped: bool
    camera: PinholeCamera

    @property
    def label(self) -> str:
        """A store-safe name: ``row_p1`` for +1, ``row_m2`` for −2, ``row_0`` for the best."""
        return row_label(self.index)

    def to_dict(self) -> dict:
        return {
            "index": self.index,
            "label": self.label,
            "offset_m": self.offset_m,
            "snapped": self.snapped,
            "camera": self.camera.to_dict(),
        }


def row_label(index: int) -> str:
    """``row_p1`` / ``row_m1`` / ``row_0``: a row number as a store key segment (no ``+``,
    which some S3 servers read as a space)."""
    i = int(index)
    return "row_0" if i == 0 else f"row_{'p' if i > 0 else 'm'}{abs(i)}"


def neighbour_row_views(
    camera: PinholeCamera,
    rows: Sequence[Row],
    row_spacing: float,
    max_side: int = 2,
    *,
    snap_fraction: float | None = None,
    max_angle_deg: float = 5.0,
) -> list[RowView]:
    """Row cameras over the best row's neighbours, nearest first (+1, −1, +2, −2, ...).

    camera: the best row's camera (world frame, looking down, image x along the row).
    rows: the row fit's rows (world xy lines; ``RowFit.rows``). row_spacing: planting row
    spacing (m). max_side: neighbours considered on each side.
    """
    if not (math.isfinite(row_spacing) and row_spacing > 0):
        raise ConfigError(f"row spacing must be a positive number of metres, got {row_spacing}")
    if int(max_side) < 0:
        raise ConfigError(f"max_side must be >= 0, got {max_side}")
    if snap_fraction is not None and not 0 < snap_fraction < 0.5:
        raise ConfigError(f"snap_fraction must be in (0, 0.5) or None, got {snap_fraction}")
    m = np.asarray(camera.cam_to_world, float)
    x = m[:3, 0].copy()
    x[2] = 0.0
    if np.linalg.norm(x) == 0:
        raise ConfigError("the row camera's image x axis is vertical: not a row camera")
    x /= np.linalg.norm(x)
    y = np.array([x[1], -x[0], 0.0])  # image y of a look-down camera: (-up) × x
    if float(m[:3, 1] @ y) < 0:  # a camera rolled by 180°: keep its own image y
        y = -y
    centre = m[:2, 3]
    cos_max = math.cos(math.radians(max_angle_deg))
    # signed offset of each parallel fitted row where it passes the camera (none consulted
    # without snap_fraction)
    fitted = []
    reach = 0.0 if snap_fraction is None else snap_fraction * row_spacing
    for r in rows if reach else ():
        if abs(float(np.asarray(r.direction) @ x[:2])) < cos_max:
            continue
        # the row line's offset along y, where it passes the camera
        along = np.asarray(r.direction, float)
        rel = centre - np.asarray(r.point, float)
        foot = np.asarray(r.point, float) + along * float(rel @ along)
        fitted.append(float((foot - centre) @ y[:2]))
    out: list[RowView] = []
    for k in range(1, int(max_side) + 1):
        for sign in (1, -1):
            want = sign * k * row_spacing
            # within less than half a spacing: no fitted row can serve two neighbours
            near = [(abs(off - want), off) for off in fitted if abs(off - want) <= reach]
            if near:
                offset, snapped = min(near)[1], True
            else:
                offset, snapped = want, False
            cam = m.copy()
            cam[:3, 3] = m[:3, 3] + offset * y
            view = PinholeCamera(
                camera.width, camera.height, camera.fx, camera.fy, camera.cx, camera.cy, cam
            )
            out.append(RowView(sign * k, float(offset), snapped, view))
    return out


__all__ = ["MAX_NEIGHBOURS", "RowView", "camera_to_scene", "neighbour_row_views", "row_label"]
