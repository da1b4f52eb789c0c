"""Canopy traits measured on a generated canopy, each with its unit and definition.

Every measured number is a ``Trait(name, value, unit, method)`` record (PlantCV style), so the flat
dictionary that ends up in ``metrics.json`` can carry a ``definitions`` block saying what each
number is and how it was obtained. Only plants planted in the measured plot
(``Canopy.plant_in_plot``: by row and in-row slot) count; the others are planted border.
Lengths and areas are SI (m, m²) throughout; angles are radians inside and degrees only in the
output dictionary.

Leaf inclination θ of a leaf face is the angle between its normal and the vertical,
θ = arccos |n_z| (0° for a horizontal leaf, 90° for a vertical one); statistics over faces are
weighted by face area, so they describe the canopy's leaf *area*, not its triangle count.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from cropcraft_core.errors import ConfigError, GeometryError, InputError
from cropcraft_core.geometry.mesh import CanopyMesh, Organ
from cropcraft_core.metrics.gap_fraction import SensorRegion, canopy_gap_fraction
from cropcraft_core.procedural.structure import Canopy

LEAFLETS_PER_NODE: dict[str, int] = {"soybean": 3, "maize": 1}
"""Leaves carried by one leaf-bearing node: a soybean trifoliate has three leaflets, maize one."""

REFERENCE_DISTRIBUTIONS: dict[str, tuple[float, float]] = {
    "planophile": (26.8, 18.5),
    "erectophile": (63.2, 18.5),
    "plagiophile": (45.0, 16.3),
    "extremophile": (45.0, 32.9),
    "uniform": (45.0, 26.0),
    "spherical": (57.3, 21.6),
}
"""de Wit's classical leaf-angle distributions: (mean, SD) of the inclination in degrees."""

ANGLE_BIN_DEG = 5.0
"""Width of the leaf-angle histogram bins (degrees); the bins cover 0–90°."""


#: The traits a person looks at first (CLI summaries, stage records); metrics.json has them all.
HEADLINE_TRAITS = (
    "lai",
    "lai_gap_fraction",
    "leaf_angle_mean_deg",
    "leaf_angle_std_deg",
    "node_count",
    "internode_mean_m",
    "plant_height_m",
    "n_plants",
)


#: The headline traits' units and meaning in a word, for console summaries (metrics.json's
#: ``definitions`` have them all in full).
HEADLINE_UNITS = {
    "lai": "m2/m2 (one-sided leaf area per ground area)",
    "lai_gap_fraction": "m2/m2 (as an LAI-2200 would read it)",
    "leaf_angle_mean_deg": "deg from horizontal",
    "leaf_angle_std_deg": "deg",
    "node_count": "nodes per plant, main stem and branches (not num_nodes)",
    "internode_mean_m": "m",
    "plant_height_m": "m",
    "n_plants": "plants in the plot",
    "lai_seeds_min": "m2/m2 (lowest of the seeds' answers)",
    "lai_seeds_max": "m2/m2 (highest of the seeds' answers)",
}


@dataclass(frozen=True)
class Trait:
    """One measured quantity: ``value`` in ``unit``, obtained as ``method`` says.

    ``value`` is JSON-ready: a Python float/int/str/bool, a list of them, or ``None`` where the
    trait is undefined for this canopy (e.g. leaf-angle statistics of a canopy without leaves).
    """

    name: str
    value: Any
    unit: str
    method: str


# ---------------------------------------------------------------------------------------------
# leaf angles


def leaf_inclinations(mesh: CanopyMesh) -> tuple[np.ndarray, np.ndarray]:
    """Inclination and area of every non-degenerate leaf face of ``mesh``.

    Returns ``(theta, area)``: theta (k,) float64 radians in [0, π/2], θ = arccos |n_z|;
    area (k,) float64 m². Faces of other organs and zero-area faces are left out.
    """
    leaf = mesh.organ == Organ.LEAF
    if not leaf.any():
        return np.zeros(0), np.zeros(0)
    sub = mesh.select(leaf)
    area = sub.face_areas()
    normals = sub.face_normals()
    keep = area > 0
    nz = np.clip(np.abs(normals[keep, 2]), 0.0, 1.0)
    return np.arccos(nz), area[keep]


def weighted_angle_stats(theta: np.ndarray, weights: np.ndarray) -> tuple[float, float]:
    """Weighted mean and (population) standard deviation of angles.

    theta (k,) radians, weights (k,) ≥ 0 (face areas). Returns ``(mean, sd)`` in radians,
    sd = sqrt(Σ w (θ − mean)² / Σ w); both NaN when the weights sum to zero.
    """
    theta = np.asarray(theta, dtype=np.float64)
    weights = np.asarray(weights, dtype=np.float64)
    if theta.shape != weights.shape:
        raise InputError(f"angles {theta.shape} and weights {weights.shape} differ in shape")
    total = weights.sum()
    if not total > 0:
        return math.nan, math.nan
    mean = float(np.sum(weights * theta) / total)
    var = float(np.sum(weights * (theta - mean) ** 2) / total)
    return mean, math.sqrt(max(var, 0.0))


def leaf_angle_histogram(
    theta: np.ndarray, weights: np.ndarray, bin_deg: float = ANGLE_BIN_DEG
) -> tuple[np.ndarray, np.ndarray]:
    """Area-weighted inclination histogram.

    theta (k,) radians, weights (k,). Returns ``(fractions, edges_deg)``: fractions (b,) summing
    to 1 (all zeros when there is no leaf area), edges_deg (b + 1,) from 0 to 90 in ``bin_deg``
    steps; a 90° leaf falls into the last bin.
    """
    if not (isinstance(bin_deg, int | float) and math.isfinite(bin_deg) and bin_deg > 0):
        raise ConfigError(
            f"leaf-angle bin width must be a positive number of degrees, got {bin_deg!r}"
        )
    n_bins = round(90.0 / bin_deg)
    if n_bins < 1 or not math.isclose(n_bins * bin_deg, 90.0):
        raise ConfigError(f"leaf-angle bin width {bin_deg!r}° must divide 90° evenly")
    edges = np.linspace(0.0, 90.0, n_bins + 1)
    hist, _ = np.histogram(np.degrees(theta), bins=edges, weights=weights)
    total = hist.sum()
    return (hist / total if total > 0 else hist.astype(np.float64)), edges


def beta_fit(mean_deg: float, sd_deg: float) -> tuple[float, float] | None:
    """Two-parameter beta distribution of t = 2θ/π with the given inclination mean and SD.

    Goel & Strebel (1984), as in domain-facts: with t̄ = 2θ̄/π and σ_t = 2σ/π,
    ν = t̄ (t̄(1 − t̄)/σ_t² − 1) and μ = (1 − t̄)(t̄(1 − t̄)/σ_t² − 1); the density is
    f(t) ∝ t^(ν−1) (1 − t)^(μ−1). Returns ``(nu, mu)``, or ``None`` where no beta distribution has
    these moments (SD zero or too large for the mean, or mean outside (0°, 90°)).
    """
    if not (math.isfinite(mean_deg) and math.isfinite(sd_deg)):
        return None
    t = mean_deg / 90.0
    var_t = (sd_deg / 90.0) ** 2
    if not (0.0 < t < 1.0) or var_t <= 0.0 or var_t >= t * (1.0 - t):
        return None
    common = t * (1.0 - t) / var_t - 1.0
    return t * common, (1.0 - t) * common


def nearest_reference_distribution(mean_deg: float, sd_deg: float) -> str | None:
    """Name of the classical distribution (``REFERENCE_DISTRIBUTIONS``) nearest in (mean, SD).

    Distance is Euclidean in degrees over (mean, SD); ``None`` for non-finite input.
    """
    if not (math.isfinite(mean_deg) and math.isfinite(sd_deg)):
        return None
    return min(
        REFERENCE_DISTRIBUTIONS,
        key=lambda k: math.hypot(
            mean_deg - REFERENCE_DISTRIBUTIONS[k][0], sd_deg - REFERENCE_DISTRIBUTIONS[k][1]
        ),
    )


# ---------------------------------------------------------------------------------------------
# the canopy


def _check_canopy(canopy: Canopy) -> None:
    mesh = canopy.mesh
    p = len(canopy.plant_in_plot)
    if canopy.plant_in_plot.shape != (p,) or canopy.plant_in_plot.dtype != np.bool_:
        raise InputError("canopy.plant_in_plot must be a (p,) bool array")
    if mesh.n_faces and (mesh.plant.min() < 0 or mesh.plant.max() >= p):
        raise InputError(
            f"mesh faces carry plant ids outside 0..{p - 1} (the canopy has {p} plant records)"
        )
    k = len(canopy.node_plant)
    for name in ("node_id", "node_stem", "node_internode"):
        if getattr(canopy, name).shape != (k,):
            raise InputError(f"canopy.{name} must have one entry per node ({k})")
    if k and (canopy.node_plant.min() < 0 or canopy.node_plant.max() >= p):
        raise InputError(f"canopy.node_plant holds plant ids outside 0..{p - 1}")
    if not (math.isfinite(canopy.ground_area) and canopy.ground_area > 0):
        raise GeometryError(f"canopy ground area must be positive, got {canopy.ground_area!r}")
    if mesh.n_faces and not np.isfinite(mesh.vertices).all():  # NaN area would drop silently
        raise GeometryError("canopy mesh has non-finite vertices")


def _leaflets_per_node(crop: str, leaflets_per_node: int | None) -> int:
    if leaflets_per_node is not None:
        if leaflets_per_node < 1:
            raise ConfigError(f"leaflets per node must be ≥ 1, got {leaflets_per_node}")
        return int(leaflets_per_node)
    if crop not in LEAFLETS_PER_NODE:
        raise ConfigError(
            f"no leaflets-per-node count for crop {crop!r}: choose one of "
            f"{', '.join(LEAFLETS_PER_NODE)} or pass leaflets_per_node"
        )
    return LEAFLETS_PER_NODE[crop]


def _none_if_nan(x: float) -> float | None:
    return None if not math.isfinite(x) else float(x)


def canopy_traits(
    canopy: Canopy,
    gap_fraction: bool = True,
    rng: np.random.Generator | int | None = None,
    *,
    n_sensors: int = 64,
    n_azimuths: int = 64,
    leaflets_per_node: int | None = None,
    gap_region: SensorRegion | None = None,
    gap_canopy: Canopy | None = None,
) -> list[Trait]:
    """Measure ``canopy``; one ``Trait`` per number (see ``canopy_metrics`` for the list).

    ``gap_fraction``: also "measure" LAI the way an LAI-2200 would, by casting rays up from
    ``n_sensors`` ground points in the plot, ``n_azimuths`` per ring (``gap_fraction_lai``);
    ``rng`` seeds those sensor positions (a Generator, a seed, or ``None`` for
    ``canopy.seed``, so the same canopy always gives the same numbers).
    ``gap_region`` overrides where the sensors stand (default: the measured plot); a
    ``BorderWarning`` says when the planted border is narrower than canopy height × tan 68°.
    ``leaflets_per_node`` overrides the crop's count (``LEAFLETS_PER_NODE``). ``gap_canopy``:
    the canopy the rays cross instead (the same plants with a wider planted border,
    :func:`cropcraft_core.bundle.gap_fraction_canopy`); every other trait is ``canopy``'s.
    """
    _check_canopy(canopy)
    leaflets = _leaflets_per_node(canopy.crop, leaflets_per_node)
    mesh = canopy.mesh
    in_plot_face = canopy.plant_in_plot[mesh.plant] if mesh.n_faces else np.zeros(0, bool)
    plot = mesh.select(in_plot_face)
    n_plants = canopy.n_plants

    # leaf area and angles -------------------------------------------------------------------
    theta, area = leaf_inclinations(plot)
    leaf_area = float(area.sum())
    lai = leaf_area / canopy.ground_area
    mean, sd = weighted_angle_stats(theta, area)
    mean_deg, sd_deg = math.degrees(mean), math.degrees(sd)
    hist, edges = leaf_angle_histogram(theta, area)
    beta = beta_fit(mean_deg, sd_deg)
    reference = nearest_reference_distribution(mean_deg, sd_deg)

    # plants and nodes -----------------------------------------------------------------------
    node_in_plot = canopy.plant_in_plot[np.asarray(canopy.node_plant, dtype=np.intp)]
    node_count = float(node_in_plot.sum()) / n_plants if n_plants else math.nan
    main = node_in_plot & (canopy.node_stem == -1)
    internode = float(np.mean(canopy.node_internode[main])) if main.any() else math.nan

    leaf_faces = plot.organ == Organ.LEAF
    pairs = np.unique(np.stack([plot.plant[leaf_faces], plot.node[leaf_faces]], axis=1), axis=0)
    leaf_count = len(pairs) * leaflets / n_plants if n_plants else math.nan

    if plot.n_faces:
        top = np.full(len(canopy.plant_in_plot), -np.inf)
        np.maximum.at(top, plot.plant, plot.triangles()[:, :, 2].max(axis=1))
        tops = top[np.isfinite(top)]
        height = float(tops.mean())
    else:
        tops, height = np.zeros(0), math.nan

    traits = [
        Trait("n_plants", int(n_plants), "1", "plants planted in the measured plot (row, slot)"),
        Trait("n_faces", int(plot.n_faces), "1", "mesh faces (all organs) of the in-plot plants"),
        Trait(
            "n_faces_total", int(mesh.n_faces), "1", "mesh faces of the whole canopy incl. border"
        ),
        Trait(
            "ground_area_m2",
            float(canopy.ground_area),
            "m2",
            "ground the in-plot plants stand for: rows x row spacing x plants per row x "
            "in-row spacing",
        ),
        Trait(
            "leaf_area_m2",
            leaf_area,
            "m2",
            "one-sided area of the leaf faces (organ LEAF) of the in-plot plants",
        ),
        Trait("lai", lai, "m2 m-2", "leaf_area_m2 / ground_area_m2 (one-sided leaf area index)"),
        Trait(
            "leaf_angle_mean_deg",
            _none_if_nan(mean_deg),
            "deg",
            "leaf-area-weighted mean of the inclination arccos|n_z| of the in-plot leaf faces "
            "(0 = horizontal)",
        ),
        Trait(
            "leaf_angle_std_deg",
            _none_if_nan(sd_deg),
            "deg",
            "leaf-area-weighted (population) standard deviation of the leaf inclination",
        ),
        Trait(
            "leaf_angle_hist",
            [float(x) for x in hist],
            "1",
            f"fraction of in-plot leaf area per {ANGLE_BIN_DEG:g} deg inclination bin, 0-90 deg "
            "(edges in leaf_angle_hist_edges_deg; a 90 deg leaf counts in the last bin)",
        ),
        Trait(
            "leaf_angle_hist_edges_deg",
            [float(x) for x in edges],
            "deg",
            "bin edges of leaf_angle_hist",
        ),
        Trait(
            "leaf_angle_beta_nu",
            None if beta is None else float(beta[0]),
            "1",
            "beta fit of t = 2 theta/pi by moments (Goel & Strebel): f(t) ~ t^(nu-1)(1-t)^(mu-1), "
            "nu = tm(tm(1-tm)/st^2 - 1); null where no beta has these moments",
        ),
        Trait(
            "leaf_angle_beta_mu",
            None if beta is None else float(beta[1]),
            "1",
            "beta fit of t = 2 theta/pi by moments: mu = (1-tm)(tm(1-tm)/st^2 - 1)",
        ),
        Trait(
            "leaf_angle_class",
            reference,
            "",
            "classical distribution (planophile, erectophile, plagiophile, extremophile, uniform, "
            "spherical) nearest to the measured (mean, SD) in degrees, Euclidean",
        ),
        Trait(
            "node_count",
            _none_if_nan(node_count),
            "1",
            "mean number of nodes (main stem + branches) per in-plot plant, from the node records",
        ),
        Trait(
            "internode_mean_m",
            _none_if_nan(internode),
            "m",
            "mean length of the main-stem internodes of the in-plot plants (node_stem == -1; "
            "the crop profile's internode below each node, node 1's above the short base stem "
            "from the ground, which is not counted; branches' internodes are not counted)",
        ),
        Trait(
            "plant_height_m",
            _none_if_nan(height),
            "m",
            "mean over in-plot plants that have faces of the highest z of the plant's faces "
            "(ground z = 0)",
        ),
        Trait(
            "leaf_count",
            _none_if_nan(leaf_count),
            "1",
            f"mean leaves per in-plot plant: distinct (plant, node) pairs carrying leaf faces x "
            f"{leaflets} leaflet(s) per node",
        ),
    ]

    if gap_fraction:
        if rng is None:
            rng = canopy.seed
        gf = canopy_gap_fraction(
            canopy if gap_canopy is None else gap_canopy,
            rng=np.random.default_rng(rng),
            region=gap_region,
            n_sensors=n_sensors,
            n_azimuths=n_azimuths,
        )
        lai_gf: float | None = gf.lai
        rings = [float(t) for t in gf.transmittance]
        border, closed = gf.border_ok, gf.rings_closed
    else:
        lai_gf, rings, border, closed = None, None, None, None
    traits += [
        Trait(
            "lai_gap_fraction",
            lai_gf,
            "m2 m-2",
            "LAI-2200-style effective plant area index: rays cast up from ground sensors in the "
            "plot in rings at 7/23/38/53/68 deg zenith hit any face (all organs, border plants "
            "too); LAI = 2 sum(-ln T_i cos theta_i W_i); null when not computed",
        ),
        Trait(
            "lai_gap_fraction_rings_T",
            rings,
            "1",
            "gap fraction T_i per ring (7, 23, 38, 53, 68 deg), pooled over sensors and azimuths, "
            "clipped below at 1/(rays in the ring)",
        ),
        Trait(
            "lai_gap_fraction_border_ok",
            border,
            "",
            "true when the canopy reaches height x tan(68 deg) beyond the sensor region on every "
            "side, so the outer ring's rays cross canopy, not empty ground",
        ),
        Trait(
            "lai_gap_fraction_rings_closed",
            closed,
            "1",
            "rings (of 5) through which no ray escaped: their T is the clip floor, so where "
            "any is closed lai_gap_fraction is the floor's value, not a reading (an instrument "
            "under such a canopy reads no more)",
        ),
    ]
    return traits


def join_metrics(metrics: Mapping[str, Any], more: Mapping[str, Any]) -> dict[str, Any]:
    """``metrics`` (a :func:`canopy_metrics` dict) with ``more``'s entries added and its
    ``definitions`` joined to ``metrics``' own (e.g. the seeds' traits,
    :func:`cropcraft_core.metrics.seeds.seed_metrics`)."""
    extra = dict(more)
    defs = {**metrics.get("definitions", {}), **extra.pop("definitions", {})}
    return {**metrics, **extra, "definitions": defs}


def traits_to_dict(traits: list[Trait]) -> dict[str, Any]:
    """Flatten traits into ``{name: value, ..., "definitions": {name: {unit, method}}}``."""
    out: dict[str, Any] = {}
    for t in traits:
        if t.name in out or t.name == "definitions":
            raise InputError(f"trait name {t.name!r} appears twice")
        out[t.name] = t.value
    out["definitions"] = {t.name: {"unit": t.unit, "method": t.method} for t in traits}
    return out


def canopy_metrics(
    canopy: Canopy,
    gap_fraction: bool = True,
    rng: np.random.Generator | int | None = None,
    *,
    n_sensors: int = 64,
    n_azimuths: int = 64,
    leaflets_per_node: int | None = None,
    gap_region: SensorRegion | None = None,
    gap_canopy: Canopy | None = None,
) -> dict[str, Any]:
    """The canopy's traits as a flat, JSON-ready dict with a ``definitions`` block.

    Keys: n_plants, n_faces, n_faces_total, ground_area_m2, leaf_area_m2, lai,
    leaf_angle_mean_deg, leaf_angle_std_deg, leaf_angle_hist (18 area fractions),
    leaf_angle_hist_edges_deg (19 edges), leaf_angle_beta_nu, leaf_angle_beta_mu,
    leaf_angle_class, node_count, internode_mean_m, plant_height_m, leaf_count,
    lai_gap_fraction, lai_gap_fraction_rings_T, lai_gap_fraction_border_ok,
    lai_gap_fraction_rings_closed, and ``definitions = {name: {"unit": ..., "method":
    ...}}``. Undefined values are ``None`` (never NaN, so the dict is valid JSON).
    Arguments as in ``canopy_traits``.
    """
    return traits_to_dict(
        canopy_traits(
            canopy,
            gap_fraction,
            rng,
            n_sensors=n_sensors,
            n_azimuths=n_azimuths,
            leaflets_per_node=leaflets_per_node,
            gap_region=gap_region,
            gap_canopy=gap_canopy,
        )
    )
