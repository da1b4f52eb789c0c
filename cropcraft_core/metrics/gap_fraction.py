"""Instrument-style LAI: "measure" a mesh the way an LAI-2200 plant canopy analyser would.

The LAI-2200 (the paper's ground-truth instrument) sits on the ground under the canopy and reads
the gap fraction T_i — the fraction of sky it sees — in five concentric rings centred at
7°, 23°, 38°, 53° and 68° from the zenith. Under Beer's law T(θ) = exp(−G(θ)·LAI / cos θ), and
Miller's integral LAI = 2 ∫ −ln T(θ) cos θ sin θ dθ becomes

    K_i = −ln(T_i) · cos θ_i,       LAI = 2 · Σ_i K_i · W_i,  W = 0.041, 0.131, 0.200, 0.290, 0.337.

Here each "sensor" is a point a few centimetres above the ground inside the plot (a Latin-hypercube
stratified sample drawn with a seeded Generator) and each ring is a fan of rays at the ring's centre
zenith angle and ``n_azimuths`` evenly spaced azimuths (with a random phase per sensor and ring, so
that the fans do not alias with the rows). A ray that hits no face is a gap.

Like the instrument, this reads *effective plant area*: every face counts (stems and petioles too,
unless ``leaf_only``), and clumping lowers the reading below the true LAI (Ω < 1). The five
rings' weights are exact for randomly inclined leaves (G = 0.5: 2 · Σ 0.5 · W_i = 0.999) but not
for flat ones: horizontal leaves (G = cos θ) read 2 · Σ cos θ_i · W_i = 1.24 times their LAI. So
the reading falls on either side of the truth; the default soybean canopy (mean leaf inclination
15°) reads +5 to +12 % on its leaves alone and +22 to +30 % with every organ (canopy seeds 0–2,
each with its own sensors' draw: sessions 88, 89). Averaging: by
default T_i is pooled over every ray of the ring from every sensor (the LAI-2000's "log of the
mean"); ``log_average=True`` takes −ln T per sensor first and averages those (the LAI-2200's
mean of logs, more sensitive to clumping). T = 0 (no ray escaped) has no logarithm: T is clipped
below at 1 / (number of rays it was computed from), so a fully closed ring reads as the densest
canopy the sample can resolve, and the result is a lower bound there.

Border: a ray at 68° travels h · tan 68° ≈ 2.5 h sideways before it rises through a canopy of
height h. Sensors at the plot edge therefore look through the planted border; unless the mesh
extends at least h · tan 68° beyond the sensor region on every side, outer-ring rays escape over
bare ground and the LAI is underestimated. ``gap_fraction_lai`` measures that margin, reports it,
and warns (``BorderWarning``) when it is short.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import numpy as np

from cropcraft_core.config.layout import CanopyLayout
from cropcraft_core.errors import ConfigError, GeometryError
from cropcraft_core.geometry.mesh import Organ
from cropcraft_core.procedural.structure import Canopy

RING_ZENITH_DEG = np.array([7.0, 23.0, 38.0, 53.0, 68.0])
"""Centre zenith angles of the LAI-2200's five rings (degrees)."""
RING_WEIGHTS = np.array([0.041, 0.131, 0.200, 0.290, 0.337])
"""The LAI-2200's ring weights W_i (sin θ dθ quadrature; they sum to 0.999)."""
SENSOR_HEIGHT = 0.02
"""Default height of the sensor points above the ground (m)."""


class BorderWarning(UserWarning):
    """The canopy does not extend far enough beyond the sensor region for the 68° ring."""


@dataclass(frozen=True)
class SensorRegion:
    """Rectangle on the ground where sensors stand.

    ``(x_min, y_min)``–``(x_max, y_max)`` in a frame rotated by ``rotation_deg`` (counter-
    clockwise, about the world origin) from the world frame: a world point p is at
    R(−rotation)·p in the region frame. Metres.
    """

    x_min: float
    y_min: float
    x_max: float
    y_max: float
    rotation_deg: float = 0.0

    def __post_init__(self) -> None:
        vals = (self.x_min, self.y_min, self.x_max, self.y_max, self.rotation_deg)
        if not all(math.isfinite(v) for v in vals):
            raise ConfigError(f"sensor region must be finite, got {vals}")
        if not (self.x_max > self.x_min and self.y_max > self.y_min):
            raise ConfigError(
                f"sensor region is empty: x {self.x_min:g}..{self.x_max:g}, "
                f"y {self.y_min:g}..{self.y_max:g}"
            )

    @staticmethod
    def from_layout(layout: CanopyLayout) -> SensorRegion:
        """The measured plot: plot_length along the rows × plot_width across, centred at 0."""
        return SensorRegion(
            -layout.plot_length / 2,
            -layout.plot_width / 2,
            layout.plot_length / 2,
            layout.plot_width / 2,
            layout.row_azimuth_deg,
        )

    def _rotation(self) -> np.ndarray:
        a = math.radians(self.rotation_deg)
        return np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])

    def to_world(self, uv: np.ndarray) -> np.ndarray:
        """(n, 2) region-frame points → (n, 2) world xy."""
        return uv @ self._rotation().T

    def to_local(self, xy: np.ndarray) -> np.ndarray:
        """(n, 2) world xy → (n, 2) region-frame points."""
        return xy @ self._rotation()


@dataclass(frozen=True)
class GapFractionResult:
    """An instrument reading.

    lai: 2 Σ K_i W_i (m² m⁻²). transmittance, k, zenith_deg: (5,) per ring. n_sensors,
    n_rays_per_ring (rays per ring over all sensors). canopy_height: highest face above the
    sensors (m). border_needed = canopy_height · tan 68°; border_available: the smallest distance,
    over the four sides, from the sensor region to the edge of the mesh's bounding box in the
    region frame (m); border_ok = available ≥ needed. rings_closed: the rings through which
    no ray escaped (T at its clip floor: the LAI is then that floor's, not a reading).
    """

    lai: float
    transmittance: np.ndarray
    k: np.ndarray
    zenith_deg: np.ndarray
    n_sensors: int
    n_rays_per_ring: int
    canopy_height: float
    border_needed: float
    border_available: float
    border_ok: bool
    rings_closed: int = 0


def sensor_points(
    region: SensorRegion,
    n: int,
    rng: np.random.Generator,
    height: float = SENSOR_HEIGHT,
) -> np.ndarray:
    """``n`` sensor positions (n, 3) in world metres, z = ``height``.

    Latin-hypercube stratified over the region: each of n equal strips along x and each along y
    holds exactly one point, placed uniformly at random inside its cell.
    """
    if n < 1:
        raise ConfigError(f"need at least one sensor, got {n}")
    u = (rng.permutation(n) + rng.random(n)) / n
    v = (rng.permutation(n) + rng.random(n)) / n
    uv = np.stack(
        [
            region.x_min + u * (region.x_max - region.x_min),
            region.y_min + v * (region.y_max - region.y_min),
        ],
        axis=1,
    )
    xy = region.to_world(uv)
    return np.column_stack([xy, np.full(n, float(height))])


def ring_directions(n_sensors: int, n_azimuths: int, rng: np.random.Generator) -> np.ndarray:
    """Upward unit ray directions (n_sensors, 5, n_azimuths, 3) for the five rings.

    Ring i's rays make ``RING_ZENITH_DEG[i]`` with the vertical; azimuths are evenly spaced with a
    random phase per sensor and ring.
    """
    if n_azimuths < 1:
        raise ConfigError(f"need at least one azimuth per ring, got {n_azimuths}")
    phase = rng.random((n_sensors, len(RING_ZENITH_DEG), 1))
    phi = 2.0 * np.pi * (np.arange(n_azimuths)[None, None, :] + phase) / n_azimuths
    zen = np.radians(RING_ZENITH_DEG)[None, :, None]
    return np.stack(
        np.broadcast_arrays(np.sin(zen) * np.cos(phi), np.sin(zen) * np.sin(phi), np.cos(zen)),
        axis=-1,
    )


def lai_from_transmittance(transmittance: np.ndarray) -> tuple[float, np.ndarray]:
    """LAI-2200 reduction: (5,) ring gap fractions in (0, 1] → (2 Σ K_i W_i, K (5,))."""
    t = np.asarray(transmittance, dtype=np.float64)
    if t.shape != RING_WEIGHTS.shape or not np.all((t > 0) & (t <= 1)):
        raise ConfigError(f"ring gap fractions must be 5 values in (0, 1], got {t}")
    k = -np.log(t) * np.cos(np.radians(RING_ZENITH_DEG))
    return float(2.0 * np.sum(k * RING_WEIGHTS)), k


def gap_fraction_lai(
    vertices: np.ndarray,
    faces: np.ndarray,
    region: SensorRegion,
    rng: np.random.Generator,
    *,
    n_sensors: int = 64,
    n_azimuths: int = 64,
    sensor_height: float = SENSOR_HEIGHT,
    log_average: bool = False,
    warn_border: bool = True,
) -> GapFractionResult:
    """Cast LAI-2200 ring rays up from ground sensors in ``region`` through a triangle mesh.

    vertices (n, 3) float metres (z up, ground z = 0), faces (m, 3) int: every face the
    instrument would see, border plants included. ``rng`` draws the sensor positions and ring
    phases. ``n_sensors`` × 5 × ``n_azimuths`` rays are cast. T_i is pooled over all rays of
    ring i (``log_average=False``) or −ln T is averaged over sensors (``log_average=True``);
    either way T is clipped below at 1 / (rays it is computed from). Warns with ``BorderWarning``
    when the mesh extends less than canopy height × tan 68° beyond the region (see module doc).
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or faces.ndim != 2 or faces.shape[1] != 3:
        raise GeometryError(
            f"need vertices (n, 3) and faces (m, 3), got {vertices.shape}, {faces.shape}"
        )
    if not np.all(np.isfinite(vertices)):
        raise GeometryError("mesh has non-finite vertices")
    if not (math.isfinite(sensor_height) and sensor_height >= 0):
        raise ConfigError(f"sensor height must be ≥ 0 m, got {sensor_height!r}")

    origins = sensor_points(region, n_sensors, rng, sensor_height)
    dirs = ring_directions(n_sensors, n_azimuths, rng)
    n_rings = len(RING_ZENITH_DEG)

    if len(faces):
        from cropcraft_core.render.raycast import build_scene, cast_rays

        scene = build_scene(vertices, faces)
        o = np.broadcast_to(origins[:, None, None, :], dirs.shape).reshape(-1, 3)
        t_hit, _ = cast_rays(scene, o, dirs.reshape(-1, 3))
        gap = ~np.isfinite(np.asarray(t_hit)).reshape(n_sensors, n_rings, n_azimuths)
        used = vertices[np.unique(faces)]
        height = max(float(used[:, 2].max()) - sensor_height, 0.0)
        uv = region.to_local(used[:, :2])
        available = float(
            min(
                region.x_min - uv[:, 0].min(),
                uv[:, 0].max() - region.x_max,
                region.y_min - uv[:, 1].min(),
                uv[:, 1].max() - region.y_max,
            )
        )
    else:
        gap = np.ones((n_sensors, n_rings, n_azimuths), dtype=bool)
        height, available = 0.0, math.inf

    if log_average:
        t_sensor = np.maximum(gap.mean(axis=2), 1.0 / n_azimuths)  # (n_sensors, 5)
        transmittance = np.exp(np.mean(np.log(t_sensor), axis=0))
    else:
        transmittance = np.maximum(gap.mean(axis=(0, 2)), 1.0 / (n_sensors * n_azimuths))
    lai, k = lai_from_transmittance(transmittance)

    needed = height * math.tan(math.radians(RING_ZENITH_DEG[-1]))
    ok = available >= needed
    if warn_border and not ok:
        warnings.warn(
            f"gap-fraction LAI: the canopy reaches only {max(available, 0):.2f} m beyond the "
            f"sensor region, but its {height:.2f} m height needs {needed:.2f} m "
            f"(height x tan 68 deg) of planted border; the outer rings see bare ground and the "
            f"LAI reads low. Widen the border (layout margin) or shrink the sensor region.",
            BorderWarning,
            stacklevel=2,
        )
    return GapFractionResult(
        lai=lai,
        transmittance=transmittance,
        k=k,
        zenith_deg=RING_ZENITH_DEG.copy(),
        n_sensors=n_sensors,
        n_rays_per_ring=n_sensors * n_azimuths,
        canopy_height=height,
        border_needed=needed,
        border_available=available,
        border_ok=bool(ok),
        rings_closed=int((~gap.any(axis=(0, 2))).sum()),
    )


def canopy_gap_fraction(
    canopy: Canopy,
    rng: np.random.Generator,
    *,
    region: SensorRegion | None = None,
    leaf_only: bool = False,
    n_sensors: int = 64,
    n_azimuths: int = 64,
    sensor_height: float = SENSOR_HEIGHT,
    log_average: bool = False,
    warn_border: bool = True,
) -> GapFractionResult:
    """``gap_fraction_lai`` on a whole canopy (border plants included: they shade the plot).

    ``region`` defaults to the measured plot (``SensorRegion.from_layout(canopy.layout)``);
    ``leaf_only`` casts against leaf faces only (the instrument itself sees stems and petioles
    too, so the default keeps every organ). The border needed is height × tan 68° (about 2.5 m
    for a 1 m soybean canopy): compare it with ``canopy.layout.margin``.
    """
    mesh = canopy.mesh
    if leaf_only:
        mesh = mesh.select(mesh.organ == Organ.LEAF)
    if region is None:
        region = SensorRegion.from_layout(canopy.layout)
    return gap_fraction_lai(
        mesh.vertices,
        mesh.faces,
        region,
        rng,
        n_sensors=n_sensors,
        n_azimuths=n_azimuths,
        sensor_height=sensor_height,
        log_average=log_average,
        warn_border=warn_border,
    )
