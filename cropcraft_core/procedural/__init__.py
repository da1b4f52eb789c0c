"""Procedural crop models (one module per species) and row-planted canopies."""

from cropcraft_core.procedural.canopy import (
    SPECIES,
    generate_canopy,
    max_reach,
    plot_region,
    view_region,
)
from cropcraft_core.procedural.structure import Canopy

__all__ = ["SPECIES", "Canopy", "generate_canopy", "max_reach", "plot_region", "view_region"]
