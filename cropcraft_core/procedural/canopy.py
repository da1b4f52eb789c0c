"""Canopies: plants of one species planted in rows (``CanopyLayout``), built in one vectorised pass.

``generate_canopy`` is the forward model the optimiser calls thousands of times, so it takes an
optional ``region`` (row frame: x along the rows) and builds only the plants standing there —
e.g. ``view_region(camera, ...)``, the plants a row camera can see. Plants are addressed by their
(row, slot) position and draw their random numbers from that address (``randomness.py``): the
same seed gives the same plant whatever region is built, and the same random numbers whatever the
parameters (common random numbers).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from types import ModuleType

import numpy as np

from cropcraft_core.config.layout import CanopyLayout, default_layout
from cropcraft_core.config.params import check_crop, resolve_params
from cropcraft_core.errors import ConfigError
from cropcraft_core.geometry.camera import PinholeCamera
from cropcraft_core.procedural import maize, soybean
from cropcraft_core.procedural.builder import MeshBuilder
from cropcraft_core.procedural.randomness import normals_from_uniforms, plant_uniforms
from cropcraft_core.procedural.structure import Canopy

SPECIES: dict[str, ModuleType] = {"soybean": soybean, "maize": maize}

# slots shared by every species before the species' own: base azimuth, jitter along, jitter
# across, colour tint
_COMMON_SLOTS = 4

#: The most plants one canopy is built with (~75M faces of soybean): more is a plot or a density
#: in other units (200 × 200 "m", 275,000 plants "per m²"), which ended in a bare MemoryError.
MAX_PLANTS = 50_000

Region = tuple[float, float, float, float]  # xmin, xmax, ymin, ymax in the row frame (m)


def leaflets_per_node(crop: str) -> int:
    return SPECIES[check_crop(crop)].LEAFLETS_PER_NODE


def max_reach(crop: str, params: Mapping[str, float]) -> float:
    """A bound on how far (m, horizontally) any part of a plant reaches from its stem base."""
    if check_crop(crop) == "soybean":
        return (
            0.235 * params["petiole_length"]
            + 0.115 * params["leaf_length"] * 1.1
            + (soybean.BRANCH["internode_m"] * 2 + soybean.BRANCH["petiole_m"]) * 2.0
        )
    return 0.99 * params["leaf_length"] + 0.02


def plot_region(layout: CanopyLayout, margin: float | None = None) -> Region:
    m = layout.margin if margin is None else margin
    hx, hy = layout.plot_length / 2 + m, layout.plot_width / 2 + m
    return (-hx, hx, -hy, hy)


def view_region(camera: PinholeCamera, layout: CanopyLayout, reach: float) -> Region:
    """The row-frame rectangle of plant bases whose parts can appear in ``camera``'s image: its
    ground footprint grown by ``reach``."""
    corners = camera.ground_footprint(0.0)
    c, s = _rot(layout)
    x = corners[:, 0] * c + corners[:, 1] * s
    y = -corners[:, 0] * s + corners[:, 1] * c
    return (x.min() - reach, x.max() + reach, y.min() - reach, y.max() + reach)


def _rot(layout: CanopyLayout) -> tuple[float, float]:
    a = math.radians(layout.row_azimuth_deg)
    return math.cos(a), math.sin(a)


def _plot_slots(layout: CanopyLayout) -> tuple[range, range]:
    """Rows k and in-row slots j of the plants in the measured plot."""
    s, d = layout.row_spacing, layout.in_row_spacing
    kmax = math.floor(layout.plot_width / 2 / s + 1e-9)
    j0 = math.ceil(-layout.plot_length / 2 / d - 0.5 - 1e-9)
    j1 = math.ceil(layout.plot_length / 2 / d - 0.5 - 1e-9)
    return range(-kmax, kmax + 1), range(j0, j1)


def plants_in_region(layout: CanopyLayout, region: Sequence[float]) -> int:
    """How many plants ``layout`` plants in ``region`` (xmin, xmax, ymin, ymax; m)."""
    xmin, xmax, ymin, ymax = (float(v) for v in region)
    s, d = layout.row_spacing, layout.in_row_spacing
    n_rows = math.floor(ymax / s + 1e-9) - math.ceil(ymin / s - 1e-9) + 1
    n_row = math.floor(xmax / d - 0.5 + 1e-9) - math.ceil(xmin / d - 0.5 - 1e-9) + 1
    return max(n_rows, 0) * max(n_row, 0)


def generate_canopy(
    crop: str,
    params: Mapping[str, float] | None = None,
    layout: CanopyLayout | None = None,
    seed: int = 0,
    region: Region | None = None,
    view: PinholeCamera | None = None,
) -> Canopy:
    """Build a canopy of ``crop`` with ``params`` (missing ones take the middle of their range).

    region: row-frame (xmin, xmax, ymin, ymax) of plant bases to build; default: the plot plus the
    layout's planted margin. The plot's plants are flagged in ``Canopy.plant_in_plot``.
    view: a camera whose image is all the canopy is built for: the organs wholly outside its
    view are left out of the mesh (every kept face the same as without ``view``, so its depth
    map is the same to the bit; the plant and node records stay whole). Such a canopy is for
    rendering from that camera, not for measuring traits.
    """
    crop = check_crop(crop)
    if not (isinstance(seed, int | np.integer) and not isinstance(seed, bool)) or not (
        0 <= seed < 2**32
    ):  # the plants' random streams take 32 bits: seed 2**32 would build seed 0's canopy
        raise ConfigError(f"canopy seed must be a whole number in [0, 2**32), got {seed!r}")
    species = SPECIES[crop]
    params = resolve_params(crop, params)
    layout = layout or default_layout(crop)
    region = plot_region(layout) if region is None else region
    try:
        xmin, xmax, ymin, ymax = (float(v) for v in region)
    except (TypeError, ValueError):
        raise ConfigError(
            f"region must be four numbers (xmin, xmax, ymin, ymax), got {region!r}"
        ) from None
    if not all(math.isfinite(v) for v in (xmin, xmax, ymin, ymax)):
        raise ConfigError(f"region must be four finite numbers, got {region!r}")
    if not (xmin < xmax and ymin < ymax):
        raise ConfigError(f"empty region {region}")
    s, d = layout.row_spacing, layout.in_row_spacing
    n_plants = plants_in_region(layout, (xmin, xmax, ymin, ymax))
    if n_plants > MAX_PLANTS:  # before any array: a bare MemoryError
        raise ConfigError(
            f"the canopy would hold {n_plants:,} plants ({xmax - xmin:g} × "
            f"{ymax - ymin:g} m with its border, {layout.density:g} plants/m²), over "
            f"{MAX_PLANTS:,}: a plot is metres across and the density per m² (not cm, not per "
            "hectare)"
        )
    plot_rows, plot_slots = _plot_slots(layout)
    n_slots = _COMMON_SLOTS + species.N_SLOTS

    rows, slots, us = [], [], []
    for k in range(math.ceil(ymin / s - 1e-9), math.floor(ymax / s + 1e-9) + 1):
        j0 = math.ceil(xmin / d - 0.5 - 1e-9)
        j1 = math.floor(xmax / d - 0.5 + 1e-9)
        if j1 < j0:
            continue
        us.append(plant_uniforms(seed, k, j0, j1 - j0 + 1, n_slots))
        rows.append(np.full(j1 - j0 + 1, k))
        slots.append(np.arange(j0, j1 + 1))
    if not rows:
        raise ConfigError(f"no plant stands in region {tuple(round(v, 3) for v in region)}")
    row = np.concatenate(rows)
    slot = np.concatenate(slots)
    u = np.concatenate(us)
    g = normals_from_uniforms(u[:, 1:3])
    x = (slot + 0.5) * d + layout.jitter_along * d * g[:, 0]
    y = row * s + layout.jitter_across * g[:, 1]
    base = np.column_stack([x, y, np.zeros_like(x)])
    azimuth0 = 2 * np.pi * u[:, 0]
    in_plot = (
        (row >= plot_rows.start)
        & (row < plot_rows.stop)
        & (slot >= plot_slots.start)
        & (slot < plot_slots.stop)
    )
    plant_ids = np.arange(len(row), dtype=np.int32)

    c, sn = _rot(layout)
    rot = np.array([[c, -sn, 0], [sn, c, 0], [0, 0, 1.0]])  # row frame → world
    if view is not None and (sn != 0.0 or c != 1.0):  # the plants are built in the row frame
        to_row = np.eye(4)
        to_row[:3, :3] = rot.T
        view = dataclasses.replace(view, cam_to_world=to_row @ view.cam_to_world)
    builder = MeshBuilder(view=view)
    nodes = species.build(params, base, azimuth0, u[:, _COMMON_SLOTS:], plant_ids, builder)
    mesh = builder.build()

    if sn != 0.0 or c != 1.0:
        mesh = type(mesh)(mesh.vertices @ rot.T, mesh.faces, mesh.organ, mesh.plant, mesh.node)
        base = base @ rot.T
        nodes.xyz = nodes.xyz @ rot.T
    # the ground of the plot's plants built: a region cutting the plot builds fewer of them
    # (its ground was the whole plot's, so a 1 m square of the default plot read LAI 6x low)
    full = len(plot_rows) * len(plot_slots)
    ground_area = len(plot_rows) * s * len(plot_slots) * d * (int(in_plot.sum()) / full)
    return Canopy(
        crop=crop,
        params=params,
        layout=layout,
        seed=int(seed),
        mesh=mesh,
        plant_xy=base[:, :2],
        plant_in_plot=in_plot,
        ground_area=float(ground_area),
        node_plant=nodes.plant,
        node_id=nodes.node_id,
        node_stem=nodes.stem,
        node_xyz=nodes.xyz,
        node_internode=nodes.internode,
        info={"region": [float(v) for v in region], "plant_tint": u[:, 3]},
    )
