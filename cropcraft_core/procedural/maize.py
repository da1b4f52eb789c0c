"""Procedural maize (Zea mays), after the coupled maize model (Qian et al. 2023) as the CropCraft
paper parameterises it.

Four parameters: ``leaf_length`` (× leaf length and width), ``leaf_order_shift`` (added to every
leaf's order in the bending law), ``internode_length`` (× internode length) and ``num_nodes``
(leaves on the main stem, 1–18, fractional: the last one scaled by the remainder).

One vertical stem with one leaf per node; sizes by node follow ``data/maize_main_stem.csv``
(bottom to top). Leaves alternate sides (phyllotaxy 180°) plus azimuth noise N(0, 60°).

Bending (Qian et al.'s polynomial coefficients are not public; this is our documented smooth law):
with the leaf's effective order o = rank + shift and its relative position q = clip((o − 1)/17,
0, 1) (0 = lowest leaf, 1 = top), the midrib's angle from vertical along the normalised length s is

    θ(s) = θ₀(q) + Δ(q) · s²,   θ₀(q) = 18° + 32° (1 − q)^1.5,   Δ(q) = 25° + 85° (1 − q),

so upper leaves are erect with little droop, lower (older) leaves start flatter and their tips
hang down. A positive shift makes every leaf behave like a higher (more erect) one. Each blade is
10 trapezoidal segments; its width follows r(s) = a s² + b s + c with a = −2.3 (domain-facts.md:
0.73 at the base, widest at s ≈ 0.34, zero at the tip; area ≈ 0.75 · L · W), and the blade's
width direction is horizontal, across the midrib. Drooping tips of low leaves lie on the soil
(midrib z ≥ 5 mm) rather than passing through it.
"""

from __future__ import annotations

import math

import numpy as np

from cropcraft_core.geometry.mesh import Organ
from cropcraft_core.procedural.builder import MeshBuilder, NodeRecords
from cropcraft_core.procedural.primitives import (
    horizontal_side,
    unit,
)
from cropcraft_core.procedural.profiles import at_nodes

PROFILE = "maize_main_stem"
MAX_NODES = 18
LEAFLETS_PER_NODE = 1
N_SEGMENTS = 10
BASE_STEM_M = 0.03
GROUND_CLEARANCE_M = 0.005
AZIMUTH_NOISE_DEG = 60.0
RADIUS_M = {"stem_base": 0.012, "stem_top": 0.007}
WIDTH_A = -2.3
WIDTH_B = -2.0 * (WIDTH_A + math.sqrt(-WIDTH_A))
WIDTH_C = 2.0 * math.sqrt(-WIDTH_A) + WIDTH_A

SLOT_AZ = slice(0, 18)
N_SLOTS = 18


def blade_width(s: np.ndarray) -> np.ndarray:
    """Relative blade width r(s) along the normalised length s ∈ [0, 1]."""
    return np.clip(WIDTH_A * s**2 + WIDTH_B * s + WIDTH_C, 0.0, None)


def bending(order: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(θ₀, Δ) in radians for effective leaf orders (see the module docstring)."""
    q = np.clip((order - 1.0) / (MAX_NODES - 1.0), 0.0, 1.0)
    theta0 = np.radians(18.0 + 32.0 * (1.0 - q) ** 1.5)
    delta = np.radians(25.0 + 85.0 * (1.0 - q))
    return theta0, delta


def node_counts(num_nodes: float) -> tuple[int, float]:
    n = max(1, math.ceil(num_nodes - 1e-9))
    return n, float(num_nodes - (n - 1))


def build(
    params: dict[str, float],
    base: np.ndarray,
    azimuth0: np.ndarray,
    u: np.ndarray,
    plant_ids: np.ndarray,
    out: MeshBuilder,
) -> NodeRecords:
    """Build P plants into ``out``. base (P, 3); azimuth0 (P,); u (P, N_SLOTS); plant_ids (P,)."""
    from cropcraft_core.procedural.randomness import normals_from_uniforms

    p = len(base)
    g = normals_from_uniforms(u)
    n, frac = node_counts(params["num_nodes"])
    ranks = np.arange(1, n + 1, dtype=np.float64)
    scale = np.ones(n)
    scale[-1] = frac
    m_leaf, m_int = params["leaf_length"], params["internode_length"]
    internode = at_nodes(PROFILE, "internode_mm", ranks) * 1e-3 * m_int * scale
    length = at_nodes(PROFILE, "leaf_length_mm", ranks) * 1e-3 * m_leaf * scale
    width = at_nodes(PROFILE, "leaf_width_mm", ranks) * 1e-3 * m_leaf * scale
    z = BASE_STEM_M * m_int + np.cumsum(internode)
    node_xyz = base[:, None, :] + np.stack([np.zeros(n), np.zeros(n), z], -1)[None]
    az = (
        azimuth0[:, None]
        + np.pi * np.arange(n)[None]
        + np.radians(AZIMUTH_NOISE_DEG) * g[:, SLOT_AZ][:, :n]
    )

    # stem
    frac_h = np.arange(n + 1) / n
    radius = RADIUS_M["stem_base"] + (RADIUS_M["stem_top"] - RADIUS_M["stem_base"]) * frac_h
    seg_start = np.concatenate([base[:, None, :], node_xyz[:, :-1]], axis=1).reshape(-1, 3)
    node_ids = np.tile(np.arange(n), p)
    plant_n = np.repeat(plant_ids, n)
    out.add_prisms(
        seg_start,
        node_xyz.reshape(-1, 3),
        np.tile(radius[:-1], p),
        np.tile(radius[1:], p),
        Organ.STEM,
        plant_n,
        node_ids,
    )

    # blades (P·n leaves, N_SEGMENTS + 1 stations)
    theta0, delta = bending(ranks + params["leaf_order_shift"])
    s_mid = (np.arange(N_SEGMENTS) + 0.5) / N_SEGMENTS
    theta = theta0[:, None] + delta[:, None] * s_mid[None] ** 2  # (n, segments)
    azf = az.reshape(-1)
    seg_dir = unit(azf[:, None], np.tile(theta, (p, 1)))  # (P·n, segments, 3)
    seg_len = np.tile(length, p) / N_SEGMENTS
    r_stem = np.tile(radius[1:], p)
    start = node_xyz.reshape(-1, 3) + unit(azf, np.full_like(azf, np.pi / 2)) * r_stem[:, None]
    steps = np.cumsum(seg_dir * seg_len[:, None, None], axis=1)
    midrib = np.concatenate([start[:, None], start[:, None] + steps], axis=1)
    # drooping tips of low leaves lie on the soil instead of passing through it
    midrib[..., 2] = np.maximum(midrib[..., 2], GROUND_CLEARANCE_M)
    s_st = np.arange(N_SEGMENTS + 1) / N_SEGMENTS
    half = 0.5 * np.tile(width, p)[:, None] * blade_width(s_st)[None]
    out.add_blades(midrib, horizontal_side(azf), half, Organ.LEAF, plant_n, node_ids)

    return NodeRecords(
        plant=plant_n.astype(np.int32),
        node_id=node_ids.astype(np.int32),
        stem=np.full(p * n, -1, np.int16),
        xyz=node_xyz.reshape(-1, 3),
        internode=np.tile(internode, p),
    )
