"""Measured node profiles (CSV files under ``data/``, units in the column names)."""

from __future__ import annotations

import csv
from functools import cache
from importlib import resources

import numpy as np


@cache
def load_profile(name: str) -> dict[str, np.ndarray]:
    """Columns of ``data/<name>.csv`` as float arrays (lines starting with # are comments)."""
    text = resources.files("cropcraft_core.procedural").joinpath(f"data/{name}.csv").read_text()
    rows = [line for line in text.splitlines() if line.strip() and not line.startswith("#")]
    reader = csv.DictReader(rows)
    cols: dict[str, list[float]] = {k: [] for k in reader.fieldnames or []}
    for row in reader:
        for k, v in row.items():
            cols[k].append(float(v))
    return {k: np.asarray(v) for k, v in cols.items()}


def at_nodes(name: str, column: str, ranks: np.ndarray) -> np.ndarray:
    """Linear interpolation of ``column`` at node ranks (1 = lowest node); held constant beyond
    the listed nodes."""
    prof = load_profile(name)
    return np.interp(ranks, prof["node"], prof[column])
