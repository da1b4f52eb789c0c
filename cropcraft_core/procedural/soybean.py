"""Procedural soybean (Glycine max), after mCanopy (Song et al. 2020) as the CropCraft paper
parameterises it (supplementary "Additional Procedural Model Details").

Five parameters: ``leaf_length`` (× leaflet length and width), ``petiole_length`` (× petiole
length), ``petiole_angle`` (× petiole angle from vertical), ``internode_length`` (× internode
length) and ``num_nodes`` (main-stem trifoliate nodes, 1–14, fractional).

A plant is a vertical main stem of trifoliate nodes whose sizes follow the measured profile
(``data/soybean_main_stem.csv``, node 1 at the bottom) times the multipliers. A fractional node
count N is rounded up and the last node scaled down linearly by the remainder (its internode,
petiole and leaflets). Each node sits on the side opposite the previous one, plus azimuth noise
N(0, 60°); each petiole angle gets noise N(0, 5°) and is kept within [2°, 120°] from vertical
(multipliers up to 4 would otherwise fold petioles back under the plant), and a drooping
petiole is held at the angle where its leaflet rests just above the ground. Branches: with every
main-stem node from the 8th on, one branch starts, at main-stem nodes 1, 2, … from the bottom, at
most 6; each has 1 or 2 nodes (P(2) = 0.6: Song et al.'s distribution is not public here, this is
a documented default); the newest branch is scaled by the same remainder as the last main node.
Branch nodes share fixed sizes (internode 40 mm, petiole 120 mm, leaflets 80 × 45 mm, petiole
angle 35°) times the multipliers.

A trifoliate: the petiole leaves the stem at its node; at its tip the three leaflets are coplanar
(the paper's simplification), in the plane that contains the petiole and the horizontal direction
across it — so a leaflet's inclination follows its petiole's angle. The centre leaflet sits on a
short petiolule (10 % of its length) in line with the petiole; the laterals are 0.9 × its size,
at ±55° from it. Stems, petioles and petiolules are thin triangular prisms labelled stem/petiole.
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

PROFILE = "soybean_main_stem"
MAX_MAIN_NODES = 14
MAX_BRANCHES = 6
MAX_BRANCH_NODES = 2
FIRST_BRANCHING_NODE = 8
P_TWO_BRANCH_NODES = 0.6
LEAFLETS_PER_NODE = 3

BASE_STEM_M = 0.06  # stem below the profile's first internode (hypocotyl, epicotyl, unifoliate)
BRANCH = {
    "internode_m": 0.040,
    "petiole_m": 0.120,
    "leaflet_l_m": 0.080,
    "leaflet_w_m": 0.045,
    "angle_deg": 35.0,
    "zenith_deg": 40.0,
}
PETIOLE_ANGLE_LIMITS_DEG = (2.0, 120.0)
PETIOLE_ANGLE_NOISE_DEG = 5.0
GROUND_CLEARANCE_M = 0.005
AZIMUTH_NOISE_DEG = 60.0
BRANCH_AZIMUTH_NOISE_DEG = 20.0
LATERAL_ANGLE_DEG = 55.0
LATERAL_SCALE = 0.9
PETIOLULE_FRACTION = 0.10
RADIUS_M = {
    "stem_base": 0.004,
    "stem_top": 0.002,
    "branch": 0.002,
    "petiole": 0.0012,
    "petiolule": 0.0008,
}

# Layout of each plant's random numbers (uniforms; normals through the inverse CDF).
SLOT_MAIN_AZ = slice(0, 14)
SLOT_MAIN_ANGLE = slice(14, 28)
SLOT_BRANCH_COUNT = slice(28, 34)
SLOT_BRANCH_AZ = slice(34, 40)
SLOT_BRANCH_NODE_AZ = slice(40, 52)
SLOT_BRANCH_NODE_ANGLE = slice(52, 64)
N_SLOTS = 64


def node_counts(num_nodes: float) -> tuple[int, float, int]:
    """(main-stem nodes, scale of the last one, number of branches) for a node-count parameter."""
    n_main = max(1, math.ceil(num_nodes - 1e-9))
    frac = float(num_nodes - (n_main - 1))
    n_branch = int(np.clip(n_main - FIRST_BRANCHING_NODE + 1, 0, MAX_BRANCHES))
    return n_main, frac, n_branch


def build(
    params: dict[str, float],
    base: np.ndarray,
    azimuth0: np.ndarray,
    u: np.ndarray,
    plant_ids: np.ndarray,
    out: MeshBuilder,
) -> NodeRecords:
    """Build P plants into ``out``.

    base (P, 3) stem bases; azimuth0 (P,) radians; u (P, N_SLOTS) uniforms; plant_ids (P,).
    Returns the node records of all plants.
    """
    from cropcraft_core.procedural.randomness import normals_from_uniforms

    p = len(base)
    g = normals_from_uniforms(u)
    m_leaf, m_pet = params["leaf_length"], params["petiole_length"]
    m_ang, m_int = params["petiole_angle"], params["internode_length"]
    n_main, frac, n_branch = node_counts(params["num_nodes"])
    lo, hi = np.radians(PETIOLE_ANGLE_LIMITS_DEG)

    # ---- main stem (P, n_main)
    ranks = np.arange(1, n_main + 1, dtype=np.float64)
    scale = np.ones(n_main)
    scale[-1] = frac
    internode = at_nodes(PROFILE, "internode_mm", ranks) * 1e-3 * m_int * scale
    z = BASE_STEM_M * m_int + np.cumsum(internode)
    main_xyz = base[:, None, :] + np.stack([np.zeros(n_main), np.zeros(n_main), z], axis=-1)[None]
    main_az = (
        azimuth0[:, None]
        + np.pi * np.arange(n_main)[None]
        + np.radians(AZIMUTH_NOISE_DEG) * g[:, SLOT_MAIN_AZ][:, :n_main]
    )
    angle = np.radians(at_nodes(PROFILE, "petiole_angle_deg", ranks))[None] * m_ang
    angle = np.clip(
        angle + np.radians(PETIOLE_ANGLE_NOISE_DEG) * g[:, SLOT_MAIN_ANGLE][:, :n_main], lo, hi
    )
    pet_len = at_nodes(PROFILE, "petiole_length_mm", ranks) * 1e-3 * m_pet * scale
    leaf_l = at_nodes(PROFILE, "leaflet_length_mm", ranks) * 1e-3 * m_leaf * scale
    leaf_w = at_nodes(PROFILE, "leaflet_width_mm", ranks) * 1e-3 * m_leaf * scale

    # stem segments: ground → node 1 → … → node n
    seg_start = np.concatenate([base[:, None, :], main_xyz[:, :-1]], axis=1).reshape(-1, 3)
    seg_end = main_xyz.reshape(-1, 3)
    frac_h = np.arange(n_main + 1) / max(n_main, 1)
    radius = RADIUS_M["stem_base"] + (RADIUS_M["stem_top"] - RADIUS_M["stem_base"]) * frac_h
    r0 = np.tile(radius[:-1], p)
    r1 = np.tile(radius[1:], p)
    main_ids = np.tile(np.arange(n_main), p)
    out.add_prisms(seg_start, seg_end, r0, r1, Organ.STEM, np.repeat(plant_ids, n_main), main_ids)

    nodes_plant = [np.repeat(plant_ids, n_main)]
    nodes_id = [main_ids]
    nodes_stem = [np.full(p * n_main, -1, np.int16)]
    nodes_xyz = [main_xyz.reshape(-1, 3)]
    nodes_internode = [np.tile(internode, p)]
    petioles = {
        "xyz": [main_xyz.reshape(-1, 3)],
        "az": [main_az.reshape(-1)],
        "angle": [angle.reshape(-1)],
        "len": [np.tile(pet_len, p)],
        "leaf_l": [np.tile(leaf_l, p)],
        "leaf_w": [np.tile(leaf_w, p)],
        "plant": [np.repeat(plant_ids, n_main)],
        "node": [main_ids],
    }

    # ---- branches (P, n_branch, ≤2)
    if n_branch:
        bscale = np.ones(n_branch)
        if n_main - FIRST_BRANCHING_NODE + 1 <= MAX_BRANCHES:
            bscale[-1] = frac
        count = np.where(u[:, SLOT_BRANCH_COUNT][:, :n_branch] < P_TWO_BRANCH_NODES, 2, 1)
        b_az = (
            main_az[:, :n_branch]
            + np.radians(BRANCH_AZIMUTH_NOISE_DEG) * g[:, SLOT_BRANCH_AZ][:, :n_branch]
        )
        b_dir = unit(b_az, np.full_like(b_az, np.radians(BRANCH["zenith_deg"])))
        b_int = BRANCH["internode_m"] * m_int * bscale  # (n_branch,)
        j = np.arange(MAX_BRANCH_NODES)
        # node positions (P, n_branch, 2, 3)
        b_xyz = main_xyz[:, :n_branch, None, :] + (
            b_dir[:, :, None, :] * (b_int[None, :, None, None] * (j[None, None, :, None] + 1))
        )
        valid = j[None, None, :] < count[:, :, None]
        node_az = (
            b_az[:, :, None]
            + np.pi * (j[None, None, :] + 1)
            + np.radians(AZIMUTH_NOISE_DEG)
            * g[:, SLOT_BRANCH_NODE_AZ].reshape(p, MAX_BRANCHES, 2)[:, :n_branch]
        )
        node_angle = np.clip(
            np.radians(BRANCH["angle_deg"]) * m_ang
            + np.radians(PETIOLE_ANGLE_NOISE_DEG)
            * g[:, SLOT_BRANCH_NODE_ANGLE].reshape(p, MAX_BRANCHES, 2)[:, :n_branch],
            lo,
            hi,
        )
        shape = valid.shape
        plant_b = np.broadcast_to(plant_ids[:, None, None], shape)[valid]
        node_b = np.broadcast_to(
            n_main + MAX_BRANCH_NODES * np.arange(n_branch)[None, :, None] + j[None, None, :], shape
        )[valid]
        s_b = np.broadcast_to(bscale[None, :, None], shape)[valid]
        xyz_b = b_xyz[valid]
        prev = np.concatenate([main_xyz[:, :n_branch, None, :], b_xyz[:, :, :-1]], axis=2)[valid]
        out.add_prisms(
            prev,
            xyz_b,
            np.full(len(xyz_b), RADIUS_M["branch"]),
            np.full(len(xyz_b), RADIUS_M["branch"] * 0.8),
            Organ.STEM,
            plant_b,
            node_b,
        )
        nodes_plant.append(plant_b)
        nodes_id.append(node_b)
        nodes_stem.append(
            np.broadcast_to(np.arange(n_branch)[None, :, None], shape)[valid].astype(np.int16)
        )
        nodes_xyz.append(xyz_b)
        nodes_internode.append(np.broadcast_to(b_int[None, :, None], shape)[valid])
        petioles["xyz"].append(xyz_b)
        petioles["az"].append(node_az[valid])
        petioles["angle"].append(node_angle[valid])
        petioles["len"].append(BRANCH["petiole_m"] * m_pet * s_b)
        petioles["leaf_l"].append(BRANCH["leaflet_l_m"] * m_leaf * s_b)
        petioles["leaf_w"].append(BRANCH["leaflet_w_m"] * m_leaf * s_b)
        petioles["plant"].append(plant_b)
        petioles["node"].append(node_b)

    pt = {k: np.concatenate(v) for k, v in petioles.items()}
    _trifoliates(pt, out)
    return NodeRecords(
        plant=np.concatenate(nodes_plant).astype(np.int32),
        node_id=np.concatenate(nodes_id).astype(np.int32),
        stem=np.concatenate(nodes_stem).astype(np.int16),
        xyz=np.concatenate(nodes_xyz),
        internode=np.concatenate(nodes_internode).astype(np.float64),
    )


def _trifoliates(pt: dict[str, np.ndarray], out: MeshBuilder) -> None:
    """Petiole, petiolule and three coplanar leaflets for every node record in ``pt``."""
    n = len(pt["xyz"])
    # A drooping petiole (angle > 90°) near the ground is held up by the soil: limit the angle so
    # that petiole, petiolule and centre leaflet end at least GROUND_CLEARANCE_M above z = 0.
    reach = pt["len"] + (1 + PETIOLULE_FRACTION) * pt["leaf_l"]
    cos_min = (GROUND_CLEARANCE_M - pt["xyz"][:, 2]) / np.maximum(reach, 1e-9)
    angle = np.minimum(pt["angle"], np.arccos(np.clip(cos_min, -1.0, 1.0)))
    d = unit(pt["az"], angle)  # petiole direction, also the centre leaflet's axis
    side = horizontal_side(pt["az"])  # in the leaf plane, across the petiole
    tip = pt["xyz"] + d * pt["len"][:, None]
    r_pet, r_pl = np.full(n, RADIUS_M["petiole"]), np.full(n, RADIUS_M["petiolule"])
    out.add_prisms(pt["xyz"], tip, r_pet, r_pet, Organ.PETIOLE, pt["plant"], pt["node"])
    petiolule_end = tip + d * (PETIOLULE_FRACTION * pt["leaf_l"])[:, None]
    out.add_prisms(tip, petiolule_end, r_pl, r_pl, Organ.PETIOLE, pt["plant"], pt["node"])

    ca, sa = math.cos(math.radians(LATERAL_ANGLE_DEG)), math.sin(math.radians(LATERAL_ANGLE_DEG))
    base = np.concatenate([petiolule_end, tip, tip])
    axis = np.concatenate([d, ca * d + sa * side, ca * d - sa * side])
    across = np.concatenate([side, ca * side - sa * d, ca * side + sa * d])
    length = np.concatenate(
        [pt["leaf_l"], LATERAL_SCALE * pt["leaf_l"], LATERAL_SCALE * pt["leaf_l"]]
    )
    width = np.concatenate(
        [pt["leaf_w"], LATERAL_SCALE * pt["leaf_w"], LATERAL_SCALE * pt["leaf_w"]]
    )
    plant, node = np.tile(pt["plant"], 3), np.tile(pt["node"], 3)
    out.add_leaflets(base, axis, across, length, width, Organ.LEAF, plant, node)
