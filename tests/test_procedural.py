"""Invariants of the procedural models, over both crops and random parameter draws."""

import numpy as np
import pytest

from cropcraft_core.config import default_layout, param_space, resolve_params
from cropcraft_core.errors import ConfigError
from cropcraft_core.geometry import Organ, PinholeCamera
from cropcraft_core.procedural import generate_canopy, max_reach, plot_region, view_region
from cropcraft_core.procedural.primitives import LEAFLET_AREA_FACTOR, LEAFLET_FACES, LEAFLET_VERTS
from cropcraft_core.procedural.soybean import node_counts

CROPS = ["soybean", "maize"]


def draws(crop, n, seed):
    rng = np.random.default_rng(seed)
    specs = param_space(crop)
    out = [{s.name: s.low for s in specs}, {s.name: s.high for s in specs}]
    for _ in range(n):
        out.append({s.name: float(rng.uniform(s.low, s.high)) for s in specs})
    return out


def small(crop, params, seed=0, **kw):
    lay = default_layout(crop, plot_length=1.0, plot_width=1.6, **kw)
    return generate_canopy(crop, params, lay, seed=seed, region=plot_region(lay, 0.3))


def leaf_area(c):
    m = c.mesh
    keep = (m.organ == Organ.LEAF) & c.plant_in_plot[m.plant]
    return float(m.face_areas()[keep].sum())


@pytest.mark.parametrize("crop", CROPS)
@pytest.mark.parametrize("i", range(6))
def test_invariants(crop, i):
    params = draws(crop, 4, seed=42)[i]
    c = small(crop, params, seed=i)
    m = c.mesh
    m.validate()  # finite, in range, no degenerate faces, known organs
    assert m.n_faces > 0
    assert set(np.unique(m.organ)) <= {int(o) for o in Organ}
    assert (m.organ == Organ.LEAF).any() and (m.organ == Organ.STEM).any()
    assert m.plant.min() >= 0 and m.plant.max() < len(c.plant_in_plot)
    # every face's (plant, node) is a real node of that plant
    nodes = set(zip(c.node_plant.tolist(), c.node_id.tolist(), strict=True))
    assert set(zip(m.plant.tolist(), m.node.tolist(), strict=True)) <= nodes
    assert m.vertices[:, 2].min() >= -1e-9  # nothing below the ground
    assert c.ground_area > 0 and c.n_plants > 0
    assert np.all(c.node_internode > 0)


def test_leaflet_template_faces_all_turn_counter_clockwise():
    """Every face of the soybean leaflet template faces +z, the tip's too (its winding was once
    reversed: OBJ/PLY viewers culled that face, and normals read from the files flipped)."""
    t = LEAFLET_VERTS[LEAFLET_FACES]
    a, b = t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]
    assert np.all(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0] > 0)


@pytest.mark.parametrize("crop", CROPS)
def test_every_organ_is_wound_consistently(crop):
    """No directed edge is used twice: faces that share an edge agree on which side is their
    front, so exported meshes read with consistent normals (trimesh's winding check)."""
    m = small(crop, draws(crop, 1, seed=3)[2], seed=1).mesh
    f = m.faces.astype(np.int64)
    directed = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    assert len(np.unique(directed, axis=0)) == len(directed)


@pytest.mark.parametrize("crop", CROPS)
def test_deterministic_per_seed_and_seeds_differ(crop):
    p = draws(crop, 1, seed=3)[2]
    a, b, other = small(crop, p, seed=7), small(crop, p, seed=7), small(crop, p, seed=8)
    assert np.array_equal(a.mesh.vertices, b.mesh.vertices)
    assert np.array_equal(a.mesh.faces, b.mesh.faces)
    assert np.array_equal(a.mesh.organ, b.mesh.organ)
    assert a.mesh.vertices.shape != other.mesh.vertices.shape or not np.allclose(
        a.mesh.vertices, other.mesh.vertices
    )


@pytest.mark.parametrize("crop", CROPS)
def test_plants_do_not_depend_on_region(crop):
    """The plot's plants are identical whether a small or a large border is built."""
    lay = default_layout(crop, plot_length=1.0, plot_width=1.6)
    a = generate_canopy(crop, None, lay, seed=5, region=plot_region(lay, 0.0))
    b = generate_canopy(crop, None, lay, seed=5, region=plot_region(lay, 1.0))
    xy_a = a.plant_xy[a.plant_in_plot]
    xy_b = b.plant_xy[b.plant_in_plot]
    assert np.allclose(np.sort(xy_a, axis=0), np.sort(xy_b, axis=0))
    assert leaf_area(a) == pytest.approx(leaf_area(b), rel=1e-9)


@pytest.mark.parametrize("crop", CROPS)
def test_longer_leaves_larger_lai(crop):
    spec = next(s for s in param_space(crop) if s.name == "leaf_length")
    areas = [
        leaf_area(small(crop, {"leaf_length": v}, seed=1))
        for v in np.linspace(spec.low, spec.high, 4)
    ]
    assert np.all(np.diff(areas) > 0)


@pytest.mark.parametrize("crop", CROPS)
def test_more_nodes_more_nodes(crop):
    hi = param_space(crop)[-1].high
    counts = []
    for n in np.linspace(1, hi, 6):
        c = small(crop, {"num_nodes": float(n)}, seed=2)
        per_plant = np.bincount(c.node_plant)[c.plant_in_plot]
        counts.append(per_plant.mean())
    assert np.all(np.diff(counts) > 0)


def test_leaf_angle_follows_petiole_angle():
    """Soybean leaflets lie in the plane of their petiole: larger petiole angles (from vertical)
    give flatter leaves."""

    def mean_incl(mult):
        c = small("soybean", {"petiole_angle": mult, "num_nodes": 6}, seed=4)
        n = c.mesh.face_normals()[c.mesh.organ == Organ.LEAF]
        return np.degrees(np.arccos(np.abs(n[:, 2]))).mean()

    # below 90° from vertical (multipliers ≤ 1.5 on the profile's ≤ 59°)
    assert mean_incl(0.5) > mean_incl(1.0) > mean_incl(1.5)


def test_fractional_nodes_scale_last_node():
    n_main, frac, n_branch = node_counts(5.25)
    assert (n_main, n_branch) == (6, 0) and frac == pytest.approx(0.25)
    assert node_counts(8.0)[2] == 1 and node_counts(14.0)[2] == 6
    whole = leaf_area(small("soybean", {"num_nodes": 5.0}, seed=0))
    part = leaf_area(small("soybean", {"num_nodes": 5.5}, seed=0))
    full = leaf_area(small("soybean", {"num_nodes": 6.0}, seed=0))
    assert whole < part < full


def test_soybean_trifoliate_area_matches_profile():
    """One plant with one node: leaf area = 0.59-ish · L · W · (1 + 2 · 0.9²)."""
    lay = default_layout("soybean", plot_length=0.05, plot_width=0.76, density=27.5)
    c = generate_canopy(
        "soybean", {"num_nodes": 1, "leaf_length": 1.0}, lay, seed=0, region=plot_region(lay, 0.0)
    )
    per_plant = leaf_area(c) / c.n_plants
    expect = LEAFLET_AREA_FACTOR * 0.052 * 0.036 * (1 + 2 * 0.9**2)
    assert per_plant == pytest.approx(expect, rel=1e-9)
    assert LEAFLET_AREA_FACTOR == pytest.approx(0.59, abs=0.01)


def test_maize_blade_area_is_three_quarters():
    lay = default_layout("maize", plot_length=0.16, plot_width=0.76)
    c = generate_canopy(
        "maize", {"num_nodes": 1, "leaf_length": 1.0}, lay, seed=0, region=plot_region(lay, 0.0)
    )
    assert leaf_area(c) / c.n_plants == pytest.approx(0.75 * 0.100 * 0.020, rel=0.02)


def test_rows_and_density():
    lay = default_layout(
        "soybean",
        plot_length=2.0,
        plot_width=2.0,
        row_spacing=0.76,
        density=27.5,
        jitter_along=0,
        jitter_across=0,
    )
    c = generate_canopy("soybean", None, lay, seed=0, region=plot_region(lay, 0.0))
    xy = c.plant_xy[c.plant_in_plot]
    assert sorted(set(np.round(xy[:, 1], 6))) == pytest.approx([-0.76, 0.0, 0.76])
    assert c.n_plants / c.ground_area == pytest.approx(27.5, rel=1e-6)


def test_row_azimuth_rotates_canopy():
    lay0 = default_layout("maize", plot_length=1.0, plot_width=1.6)
    lay90 = lay0.with_(row_azimuth_deg=90.0)
    a = generate_canopy("maize", None, lay0, seed=1, region=plot_region(lay0, 0))
    b = generate_canopy("maize", None, lay90, seed=1, region=plot_region(lay90, 0))
    rot = np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1.0]])
    assert np.allclose(a.mesh.vertices @ rot.T, b.mesh.vertices, atol=1e-12)


def test_view_region_covers_camera_footprint():
    lay = default_layout("soybean")
    cam = PinholeCamera.look_down(height_m=1.0)
    reach = max_reach("soybean", resolve_params("soybean"))
    x0, x1, y0, y1 = view_region(cam, lay, reach)
    fp = cam.ground_footprint()
    assert x0 < fp[:, 0].min() - 0.3 and x1 > fp[:, 0].max() + 0.3
    assert y0 < fp[:, 1].min() - 0.3 and y1 > fp[:, 1].max() + 0.3


@pytest.mark.parametrize(
    "crop,params,match",
    [
        ("wheat", {}, "unknown crop"),
        ("soybean", {"leaf_width": 1.0}, "unknown soybean parameter"),
        ("soybean", {"num_nodes": 15}, "outside its range"),
        ("maize", {"leaf_order_shift": float("nan")}, "outside its range"),
        ("soybean", "num_nodes=6", "soybean parameters must map names to values"),
    ],
)
def test_bad_parameters(crop, params, match):
    with pytest.raises(ConfigError, match=match):
        generate_canopy(crop, params)


def test_bad_layout():
    with pytest.raises(ConfigError, match="row spacing must be a positive"):
        default_layout("soybean", row_spacing=0.0)
    with pytest.raises(ConfigError, match="plot width"):
        default_layout("soybean", plot_width=0.5)
    for bad in (float("nan"), float("inf"), "x"):  # NaN built a canopy of NaN vertices
        with pytest.raises(ConfigError, match="row azimuth must be a number of degrees"):
            default_layout("soybean", row_azimuth_deg=bad)
    with pytest.raises(ConfigError, match="plot length 0.03 m holds no plant"):
        default_layout("soybean", plot_length=0.03)  # its ground area was 0


def test_a_canopy_seed_is_32_bits():
    """The plants' random streams take 32 bits of the seed: a larger one (or a negative one)
    would build another seed's canopy under its own name."""
    for bad in (2**32, -1, 1.5, True):
        with pytest.raises(ConfigError, match="canopy seed must be a whole number"):
            generate_canopy("soybean", seed=bad)


@pytest.mark.parametrize("crop,height", [("soybean", 1.25), ("maize", 5.0)])
def test_default_border_hides_the_canopy_edge_from_the_row_camera(crop, height):
    """Every plant that could appear in the row camera's view over the plot centre is planted
    by default, for the largest plants: the camera sees no artificial edge."""
    lay = default_layout(crop)
    biggest = {s.name: s.high for s in param_space(crop)}
    cam = PinholeCamera.look_down(height_m=height)
    needed = view_region(cam, lay, max_reach(crop, biggest))
    built = plot_region(lay)
    assert built[0] <= needed[0] and built[1] >= needed[1]
    assert built[2] <= needed[2] and built[3] >= needed[3]


def _tilted(cam: PinholeCamera, deg: float) -> PinholeCamera:
    """``cam`` turned by ``deg`` about its own image x axis (an oblique view)."""
    a = np.radians(deg)
    turn = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    m = cam.cam_to_world.copy()
    m[:3, :3] = m[:3, :3] @ turn
    return PinholeCamera(cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy, m)


@pytest.mark.parametrize("crop", CROPS)
def test_a_canopy_built_for_a_view_renders_the_same_depth_to_the_bit(crop):
    """Leaving out the organs a camera cannot see (the fit's canopies) changes nothing that
    camera renders, for straight-down and oblique views, off-centre, over rows at an azimuth;
    it does leave out most of a soybean canopy's faces seen from the 1 m row camera."""
    from cropcraft_core.render import render_depth

    height = 1.0 if crop == "soybean" else 4.0
    straight = PinholeCamera.look_down((0.3, -0.2), height, row_direction=(1.0, 0.4))
    cameras = [PinholeCamera.look_down(height_m=height), straight, _tilted(straight, 35.0)]
    for i, params in enumerate(draws(crop, 2, seed=7)):
        for lay in (default_layout(crop), default_layout(crop, row_azimuth_deg=30.0)):
            for cam in cameras:
                full = generate_canopy(crop, params, lay, seed=i)
                seen = generate_canopy(crop, params, lay, seed=i, view=cam)
                a = render_depth(full.mesh.vertices, full.mesh.faces, cam).depth
                b = render_depth(seen.mesh.vertices, seen.mesh.faces, cam).depth
                assert np.array_equal(a, b, equal_nan=True)
                assert np.isfinite(a).sum() > 1000  # the view does see plants
                assert seen.mesh.n_faces < full.mesh.n_faces
                assert np.array_equal(seen.node_xyz, full.node_xyz)  # the records stay whole
    top = generate_canopy(crop, None, seed=0, view=cameras[0])
    if crop == "soybean":
        assert top.mesh.n_faces < 0.5 * generate_canopy(crop, None, seed=0).mesh.n_faces


def test_sees_spheres_is_false_only_wholly_outside_the_view():
    cam = PinholeCamera.look_down(height_m=1.0)  # footprint at z = 0: |x| ≤ 0.62, |y| ≤ 0.47
    x_edge = cam.ground_footprint()[:, 0].max()
    centres = np.array(
        [[0, 0, 0.5], [x_edge + 0.05, 0, 0], [x_edge + 0.2, 0, 0], [0, 0, 2.0], [0, 0, 1.5]]
    )
    seen = cam.sees_spheres(centres, np.array([0.01, 0.1, 0.1, 0.1, 0.6]))
    # inside; reaching in; wholly outside; behind the camera; behind it but reaching round
    assert seen.tolist() == [True, True, False, False, True]


@pytest.mark.parametrize(
    "layout, hint",
    [
        (dict(plot_length=200.0, plot_width=200.0), "1,118,830 plants (202 × 202 m"),  # cm as m
        (dict(density=275000.0), "4,180,000 plants"),  # plants per hectare as per m²
    ],
)
def test_a_layout_in_other_units_is_named_before_any_plant_is_built(layout, hint):
    """A plot typed in centimetres or a density per hectare planned millions of plants and
    ended in numpy's bare MemoryError (or hours of swapping): refused by its plant count."""
    import re

    with pytest.raises(ConfigError, match=f"would hold {re.escape(hint)}.*a plot is metres across"):
        generate_canopy("soybean", layout=default_layout("soybean", **layout))


def test_layout_and_parameters_take_numpy_numbers_and_refuse_bools_and_bad_regions():
    """numpy's numbers were refused as "not a positive number" and ``True`` taken as 1 m (a
    ``true`` margin in a settings file) or as parameter value 1.0; a bad crop or region gave
    a bare TypeError / OverflowError / ValueError."""
    import json

    layout = default_layout("maize", density=np.float32(8), plot_length=np.int64(3))
    assert layout.density == 8.0 and layout.plot_length == 3.0
    assert json.loads(json.dumps(layout.to_dict()))["plot_length"] == 3.0
    assert default_layout("soybean", plot_length=3).to_dict()["plot_length"] == 3  # as given
    for field in ("margin", "plot_length", "row_azimuth_deg", "jitter_along"):
        with pytest.raises(ConfigError, match="got True"):
            default_layout("soybean", **{field: True})
    with pytest.raises(ConfigError, match="num_nodes=True is not a number"):
        resolve_params("soybean", {"num_nodes": True})
    with pytest.raises(ConfigError, match="unknown crop"):
        generate_canopy(["soybean"])
    for region, message in (
        ((-np.inf, 1, -1, 1), "four finite numbers"),
        ((0, 1, 2), r"four numbers \(xmin, xmax, ymin, ymax\)"),
    ):
        with pytest.raises(ConfigError, match=message):
            generate_canopy("soybean", region=region)
