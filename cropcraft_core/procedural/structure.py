"""The generated canopy: its labelled mesh plus the plant and node records metrics need."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from cropcraft_core.config.layout import CanopyLayout
from cropcraft_core.geometry.mesh import CanopyMesh


@dataclass(frozen=True, eq=False)
class Canopy:
    """A procedural canopy.

    Plants (p of them): ``plant_xy`` (p, 2) base positions (m), ``plant_in_plot`` (p,) bool, true
    for the plants planted in the measured plot: the rows whose centre line lies in it (edges
    included; always an odd number, centred on the plot) and the in-row positions whose slot
    does, before their jitter (metrics use only these; the others are the planted border).
    Plant ids in ``mesh.plant`` index these arrays.

    Nodes (k of them, every node of every plant): ``node_plant`` (k,) int32, ``node_id`` (k,)
    int32 (the id faces carry in ``mesh.node``), ``node_stem`` (k,) int16 (-1 main stem, b ≥ 0
    branch b), ``node_xyz`` (k, 3) position where the petiole/leaf leaves the stem,
    ``node_internode`` (k,) length of the stem segment below the node (m; for a branch's first node,
    the segment from the main stem; for the main stem's first node, its profile internode
    without the base stem under it, ``BASE_STEM_M``, which the internode traits leave out).

    ``ground_area`` (m²): the ground the in-plot plants built stand for, their number × row
    spacing × in-row spacing, so LAI = leaf area of in-plot plants / ground_area. It is the
    planted rows' ground, which is not the plot's area (a 1.52 m wide plot of 0.76 m rows
    plants three rows: 2.28 m of ground across).
    """

    crop: str
    params: dict[str, float]
    layout: CanopyLayout
    seed: int
    mesh: CanopyMesh
    plant_xy: np.ndarray
    plant_in_plot: np.ndarray
    ground_area: float
    node_plant: np.ndarray
    node_id: np.ndarray
    node_stem: np.ndarray
    node_xyz: np.ndarray
    node_internode: np.ndarray
    info: dict = field(default_factory=dict)

    @property
    def n_plants(self) -> int:
        return int(self.plant_in_plot.sum())

    def plot_mesh(self) -> CanopyMesh:
        """The faces of the in-plot plants only."""
        return self.mesh.select(self.plant_in_plot[self.mesh.plant])
