"""Row fitting on point clouds sampled from real procedural canopies (area-weighted on the faces,
green) plus noisy brown soil on z = 0, moved into a random similarity frame like an SfM scene."""

import math
import re

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cropcraft_core.config.layout import default_layout
from cropcraft_core.errors import ConfigError, CropCraftError, InputError
from cropcraft_core.procedural.canopy import generate_canopy
from cropcraft_core.rowfit import (
    Row,
    RowFitError,
    estimate_scale_from_rows,
    fit_ground_and_rows,
    fit_rows_with_scale,
    preset,
    srgb_to_lab,
)
from cropcraft_core.rowfit.truth import register_to_truth, row_fit_errors

GREEN = np.array([0.20, 0.42, 0.12])  # L* 41, a* -30: leaf
BROWN = np.array([0.45, 0.34, 0.24])  # L* 39, a* +6, b* +16: soil
YOUNG_SOY = {"leaf_length": 0.6, "num_nodes": 4.0}
BIG_SOY = {"leaf_length": 1.3, "num_nodes": 10.0}
MAIZE_REGION = (-3.5, 3.5, -3.5, 3.5)


def sample_faces(mesh, density, rng):
    """(n, 3) points uniformly on the mesh faces, ``density`` points per m² of face area."""
    tri, area = mesh.triangles(), mesh.face_areas()
    n = rng.poisson(area.sum() * density)
    f = rng.choice(len(area), n, p=area / area.sum())
    u, v = rng.random(n), rng.random(n)
    flip = u + v > 1
    u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
    t = tri[f]
    return t[:, 0] + u[:, None] * (t[:, 1] - t[:, 0]) + v[:, None] * (t[:, 2] - t[:, 0])


def make_cloud(crop, params=None, az=0.0, seed=0, half=1.4, density=3000, region=None, soil=True):
    """Metric cloud (ground z = 0): ((n, 3) points, (n, 3) sRGB in [0, 1], layout)."""
    rng = np.random.default_rng(seed)
    lay = default_layout(crop, row_azimuth_deg=az)
    p = sample_faces(
        generate_canopy(crop, params, lay, seed=seed, region=region).mesh, density, rng
    )
    p = p[(np.abs(p[:, 0]) <= half) & (np.abs(p[:, 1]) <= half)]
    col = [GREEN + rng.normal(0, 0.03, (len(p), 3))]
    pts = [p]
    if soil:
        ns = rng.poisson((2 * half) ** 2 * density)
        s = np.column_stack(
            [rng.uniform(-half, half, ns), rng.uniform(-half, half, ns), rng.normal(0, 0.005, ns)]
        )
        pts.append(s)
        col.append(BROWN + rng.normal(0, 0.03, (ns, 3)))
    return np.vstack(pts), np.clip(np.vstack(col), 0, 1), lay


def to_scene(pts, seed, scale=0.37):
    """A random similarity (rotation, translation, ``scale`` scene units per metre)."""
    rot = Rotation.random(random_state=seed).as_matrix()
    t = np.random.default_rng(seed + 100).normal(0, 2, 3)
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = scale * rot, t
    return pts @ m[:3, :3].T + t, m


def errors(fit, scene_from_true, lay):
    """Row direction error (deg), lateral offset of the camera from the nearest true row (m),
    relative camera-height error and ground-normal error (deg), all in the true metric frame."""
    # the camera's image x axis lies along the fitted row, looking straight down
    cam = fit.camera.cam_to_world
    assert np.allclose(cam[:3, 0], [*fit.best_row.direction, 0.0])
    assert np.allclose(cam[:3, 2], [0, 0, -1])
    e = row_fit_errors(fit, scene_from_true, lay)
    return e.direction_deg, e.lateral_m, e.height_rel, e.ground_normal_deg


# --------------------------------------------------------------------------- LAB
def test_lab_known_colours_and_opencv_float_agreement():
    assert np.allclose(srgb_to_lab(np.array([1.0, 1.0, 1.0])), [100, 0, 0], atol=1e-3)
    assert np.allclose(srgb_to_lab(np.array([0, 0, 0], np.uint8)), [0, 0, 0], atol=1e-6)
    rng = np.random.default_rng(0)
    rgb = rng.random((500, 3)).astype(np.float32)
    ref = cv2.cvtColor(rgb[None], cv2.COLOR_RGB2Lab)[0]
    assert np.abs(srgb_to_lab(rgb) - ref).max() < 0.5  # OpenCV interpolates a table
    u8 = (rgb * 255).round().astype(np.uint8)
    assert np.allclose(srgb_to_lab(u8), srgb_to_lab(u8.astype(float) / 255))
    assert srgb_to_lab(GREEN)[1] < -20 and srgb_to_lab(BROWN)[1] > 2  # leaf green, soil red


def test_presets_hold_the_papers_numbers():
    s, m = preset("soybean"), preset("maize")
    assert (s.sample_count, s.voxel_size, s.ground_threshold, s.ground_iterations) == (
        100_000,
        0.01,
        0.05,
        1000,
    )
    assert (s.remove_l_below, s.remove_b_below, s.plant_a_below) == (0, 1, 2)
    assert (s.height_percentile, s.line_threshold, s.stop_min_points, s.stop_min_fraction) == (
        50,
        0.20,
        1000,
        0.2,
    )
    assert (s.render_height, s.dense_plant_fraction) == (1.0, 0.75)
    d = s.dense()
    assert (d.height_percentile, d.line_threshold, d.render_height) == (70, 0.25, 1.25)
    assert s.box_center == (0, 0, -1.5) and s.box_size == (2, 2, 3) and s.roi_radius is None
    assert (m.sample_count, m.ground_threshold, m.render_height, m.roi_radius) == (
        5_000_000,
        0.10,
        5.0,
        2.0,
    )
    assert (m.remove_l_below, m.remove_b_below, m.plant_a_below) == (32, 0, 0)
    assert preset("maize", sample_count=1000).sample_count == 1000
    assert preset("soybean", box_size=None).box_center is None
    with pytest.raises(ConfigError):
        preset("soybean", line_treshold=0.2)
    with pytest.raises(ConfigError):
        preset("wheat")


# --------------------------------------------------------------------------- accuracy
CASES = [
    ("soybean", YOUNG_SOY, 0.0, 1, {}),
    ("soybean", YOUNG_SOY, 30.0, 2, {}),
    ("maize", None, 0.0, 3, dict(half=2.5, density=1000, region=MAIZE_REGION)),
    ("maize", None, 30.0, 4, dict(half=2.5, density=1000, region=MAIZE_REGION)),
]


@pytest.mark.parametrize("crop,params,az,seed,kw", CASES)
def test_rows_ground_and_camera_meet_targets(crop, params, az, seed, kw):
    pts, col, lay = make_cloud(crop, params, az, seed, **kw)
    scene, m = to_scene(pts, seed)
    fit = fit_ground_and_rows(
        scene,
        col,
        crop,
        preset(crop, box_size=None),
        rng=seed,
        scale=1 / 0.37,
        scale_source="user_hint",
    )
    dir_err, lateral, height, normal_err = errors(fit, m, lay)
    assert dir_err <= 2.0
    assert lateral <= 0.03
    assert height <= 0.03
    assert normal_err <= 0.5
    assert fit.scale_source == "user_hint" and not fit.dense
    assert fit.render_height == preset(crop).render_height
    d = fit.diagnostics
    assert d["n_ground"] + d["n_plant"] + d["n_removed"] == d["n_voxels"]
    assert 0 < d["plant_fraction"] < 0.75
    # the world frame is a similarity with the fit's scale; the ground maps to z = 0
    w = fit.world_from_scene
    assert np.allclose(w[:3, :3].T @ w[:3, :3], fit.scale**2 * np.eye(3))
    soil = scene[col[:, 0] > 0.35]
    assert np.percentile(np.abs(fit.to_world(soil)[:, 2]), 95) < 0.02
    # the scene-frame camera renders the same view
    cs = fit.camera_in_scene()
    assert np.allclose(fit.to_world(cs.center[None])[0], fit.camera.center)


def test_dense_canopy_switch():
    pts, col, lay = make_cloud("soybean", BIG_SOY, 0.0, seed=5)
    scene, m = to_scene(pts, 5, scale=1.0)
    fit = fit_ground_and_rows(scene, col, "soybean", preset("soybean", box_size=None), rng=5)
    assert fit.diagnostics["plant_fraction"] > 0.75 and fit.dense
    assert fit.render_height == 1.25 and fit.preset.height_percentile == 70
    assert fit.preset.line_threshold == 0.25
    dir_err, lateral, height, _ = errors(fit, m, lay)
    assert dir_err <= 2.0 and height <= 0.03
    # lateral offset on this nearly closed, flat-topped canopy is looser (measured 6 cm)
    assert lateral <= 0.38 / 2


def test_paper_scene_box_crop():
    pts, col, lay = make_cloud("soybean", YOUNG_SOY, 0.0, seed=6)
    pts = pts + [0.0, 0.0, -2.5]  # ground inside the paper box (0, 0, -1.5) ± (1, 1, 1.5)
    shift = np.eye(4)
    shift[2, 3] = -2.5
    fit = fit_ground_and_rows(pts, col, "soybean", rng=6, scale=1.0, scale_source="metric_poses")
    assert fit.diagnostics["n_in_box"] < len(pts)
    assert fit.scale_source == "metric_poses"
    dir_err, lateral, height, _ = errors(fit, shift, lay)
    assert dir_err <= 2.0 and lateral <= 0.03
    assert abs(fit.to_world(np.array([[0.0, 0.0, -2.5]]))[0, 2]) < 0.01


def test_deterministic_given_seed():
    pts, col, _ = make_cloud("soybean", YOUNG_SOY, 10.0, seed=7, density=1500)
    p = preset("soybean", box_size=None)
    a = fit_ground_and_rows(pts, col, "soybean", p, rng=np.random.default_rng(11))
    b = fit_ground_and_rows(pts, col, "soybean", p, rng=np.random.default_rng(11))
    assert np.array_equal(a.camera.cam_to_world, b.camera.cam_to_world)
    assert [r.n_inliers for r in a.rows] == [r.n_inliers for r in b.rows]


def test_a_point_with_a_non_finite_colour_is_dropped_without_rescaling_the_others():
    """Colours over 1 mean a 0-255 scale; one inf colour (dropped with its point) made every
    other colour read 255 times too dark, and then no soil was found."""
    pts, col, _ = make_cloud("soybean", YOUNG_SOY, 10.0, seed=7, density=1500)
    p = preset("soybean", box_size=None)
    bad = col.copy()
    bad[0] = [np.inf, 0.3, 0.2]
    a = fit_ground_and_rows(pts, bad, "soybean", p, rng=11)
    b = fit_ground_and_rows(pts[1:], col[1:], "soybean", p, rng=11)
    assert a.diagnostics["n_finite"] == b.diagnostics["n_finite"] == len(pts) - 1
    assert np.array_equal(a.camera.cam_to_world, b.camera.cam_to_world)


# --------------------------------------------------------------------------- scale
@pytest.mark.parametrize(
    "crop,params,kw",
    [
        ("soybean", YOUNG_SOY, {}),
        # a closed canopy: the leaves between rows flatten the lateral profile (high-pass needed)
        ("soybean", BIG_SOY, {}),
        ("maize", None, {}),
    ],
)
def test_scale_from_row_spacing(crop, params, kw):
    if crop == "maize":
        kw = dict(half=2.5, density=1000, region=MAIZE_REGION)
    pts, col, lay = make_cloud(crop, params, 20.0, seed=8, **kw)
    true_scale = 1 / 1.15  # metres per scene unit
    scene, _ = to_scene(pts, 8, scale=1.15)
    p = preset(crop, box_size=None)
    fit = fit_ground_and_rows(scene, col, crop, p, rng=8)  # assumed metric: 15 % off
    assert fit.scale_source == "assumed_metric"
    est = estimate_scale_from_rows(fit, lay.row_spacing)
    assert est.method == "profile_autocorrelation"
    assert abs(est.factor * fit.scale / true_scale - 1) <= 0.03
    auto = fit_rows_with_scale(scene, col, crop, p, rng=8, known_row_spacing=lay.row_spacing)
    assert auto.scale_source == "row_spacing"
    assert abs(auto.scale / true_scale - 1) <= 0.03
    hinted = fit_rows_with_scale(scene, col, crop, p, rng=8, scale_hint=true_scale)
    assert hinted.scale_source == "user_hint" and hinted.scale == true_scale


def test_the_scale_profile_reaches_past_the_row_roi():
    """Maize's rows are fitted within 2 m of the centre, its row-spacing profile takes plant
    points within 3 m (five rows' scattered centres measured the scale up to 4 % off)."""
    pts, col, lay = make_cloud(
        "maize", None, 20.0, seed=8, half=3.4, density=1000, region=MAIZE_REGION
    )
    wide = fit_ground_and_rows(pts, col, "maize", preset("maize", box_size=None), rng=8)
    r = np.hypot(*wide.plant_xy.T)
    assert 2.9 < r.max() <= 3.0 and r.max() > np.hypot(*wide.row_points.T).max() + 0.5
    narrow = fit_ground_and_rows(
        pts, col, "maize", preset("maize", box_size=None, scale_radius=2.0), rng=8
    )
    assert np.hypot(*narrow.plant_xy.T).max() <= 2.0
    est = estimate_scale_from_rows(wide, lay.row_spacing)
    assert est.method == "profile_autocorrelation" and abs(est.factor - 1) < 0.01
    with pytest.raises(ConfigError, match="scale_radius"):
        preset("maize", scale_radius=-1.0)


def test_camera_height_scale_is_measured_above_the_fitted_ground():
    """A drone over a closed maize canopy: SfM saw no soil, so the levelled frame's ground lies
    on the leaves (here 1.5 m up) and the hinted 13 m camera height scaled it 13 / 11.5 too
    large. The scale from the cameras' height above the fitted ground plane is the true one."""
    pts, col, lay = make_cloud(
        "maize", None, 20.0, seed=8, half=2.5, density=1000, region=MAIZE_REGION
    )
    xy = np.stack(np.meshgrid(np.linspace(-4, 4, 5), np.linspace(-4, 4, 4)), -1).reshape(-1, 2)
    centres = np.column_stack([xy, np.full(len(xy), 13.0)])
    h0, hint = 1.5, 13.0
    k = hint / (13.0 - h0)  # scene units per metre in the mislevelled frame
    shift = np.array([0.0, 0.0, h0])
    scene, cams = (pts - shift) * k, (centres - shift) * k
    p = preset("maize", box_size=None)
    fit = fit_rows_with_scale(scene, col, "maize", p, rng=8, camera_height=(cams, hint))
    assert fit.scale_source == "camera_height"
    assert fit.scale == pytest.approx(1 / k, rel=0.005)
    assert len(fit.diagnostics["scale_factors"]) >= 2
    d, lat, hrel, _ = errors(fit, np.diag([k, k, k, 1.0]) @ _translate(-shift), lay)
    assert d < 1.0 and lat < 0.03 and hrel < 0.01
    # without it the hint's scale stands, 13 % off
    kept = fit_rows_with_scale(scene, col, "maize", p, rng=8, metric_scale=1.0)
    assert kept.scale == 1.0
    with pytest.raises(CropCraftError, match="not above the fitted ground"):
        fit_rows_with_scale(scene, col, "maize", p, rng=8, camera_height=(-cams, hint))
    with pytest.raises(CropCraftError, match="camera centres"):
        fit_rows_with_scale(scene, col, "maize", p, rng=8, camera_height=(cams[:, :2], hint))
    with pytest.raises(CropCraftError, match="positive number of metres"):
        fit_rows_with_scale(scene, col, "maize", p, rng=8, camera_height=(cams, -1.0))


def test_the_rows_found_are_the_lines_along_the_best_one():
    """Sequential RANSAC also fits lines through leaves across the rows (the report counted
    them as rows found); the rows are the lines within 10° of the best row: all three of a
    young canopy's, one of a dense canopy's five (the others at 54° and -33°)."""
    import dataclasses

    pts, col, _ = make_cloud("soybean", YOUNG_SOY, 0.0, seed=6)
    p = preset("soybean", box_size=None)
    young = fit_ground_and_rows(pts, col, "soybean", p, rng=6, scale=1.0)
    assert young.parallel_rows() == len(young.rows) == 3
    a = math.radians(40.0)
    across = Row(np.array([math.cos(a), math.sin(a)]), np.zeros(2), 10)
    assert dataclasses.replace(young, rows=[*young.rows, across]).parallel_rows() == 3
    pts, col, _ = make_cloud("soybean", BIG_SOY, 0.0, seed=5)
    scene, _ = to_scene(pts, 5, scale=1.0)
    dense = fit_ground_and_rows(scene, col, "soybean", p, rng=5)
    assert dense.parallel_rows() == 1 and len(dense.rows) == 5


def test_a_camera_height_the_rows_contradict_is_named():
    """A 1.4 m camera height given for 13 m drone photos scaled the scene 9x too small and the
    run read LAI 0.018 against 1.79 with nothing said. Where the hint lies far from the crop's
    usual height, the rows are asked: their period puts the cameras 13 m up, and the fit says
    so. A right hint, near the usual height or far from it (40 m), raises nothing."""
    pts, col, lay = make_cloud(
        "maize", None, 20.0, seed=8, half=2.5, density=1000, region=MAIZE_REGION
    )
    xy = np.stack(np.meshgrid(np.linspace(-4, 4, 5), np.linspace(-4, 4, 4)), -1).reshape(-1, 2)
    p = preset("maize", box_size=None)

    def fitted(true_height: float, hint: float):
        cams = np.column_stack([xy, np.full(len(xy), true_height)])
        k = hint / true_height  # scene units per metre: SfM levelled by the hint
        return fit_rows_with_scale(
            pts * k, col, "maize", p, rng=8, camera_height=(cams * k, hint),
            known_row_spacing=lay.row_spacing,
        )  # fmt: skip

    wrong = fitted(13.0, 1.4)
    assert wrong.scale_source == "camera_height" and wrong.scale == pytest.approx(1.0, rel=0.01)
    warning = wrong.diagnostics["scale_warning"]
    assert "camera height given (1.4 m) and the rows disagree" in warning
    up = float(warning.split("the rows put the cameras ")[1].split(" m up")[0])
    assert up == pytest.approx(13.0, rel=0.05)
    assert "scale_warning" not in fitted(13.0, 13.0).diagnostics
    assert "scale_warning" not in fitted(40.0, 40.0).diagnostics
    # a camera distance in feet taken as metres (the scene 3.3x too large): its cameras' height
    # is put to the rows alike
    cams = np.column_stack([xy, np.full(len(xy), 13.0)])
    feet = fit_rows_with_scale(
        pts, col, "maize", p, rng=8, metric_scale=3.28, metric_source="camera_distance",
        known_row_spacing=lay.row_spacing, cameras=cams,
    )  # fmt: skip
    warning = feet.diagnostics["scale_warning"]
    assert warning.startswith("the camera distance given (it puts the cameras 42.6 m up)")
    up = float(warning.split("the rows put the cameras ")[1].split(" m up")[0])
    assert up == pytest.approx(13.0, rel=0.05)
    right = fit_rows_with_scale(
        pts, col, "maize", p, rng=8, metric_scale=1.0, metric_source="camera_distance",
        known_row_spacing=lay.row_spacing, cameras=cams,
    )  # fmt: skip
    assert "scale_warning" not in right.diagnostics


def test_imported_poses_read_as_metres_that_the_rows_contradict_are_named():
    """A transforms.json read as an AR capture's metres but 2.7 units a metre (an older
    ns-process-data Metashape export) read LAI 0.48 against 1.06 with nothing said: its
    cameras' height is put to the rows as a hint's is (audit 95)."""
    pts, col, lay = make_cloud("soybean", None, 0.0, seed=8)
    xy = np.stack(np.meshgrid(np.linspace(-2, 2, 5), np.linspace(-2, 2, 4)), -1).reshape(-1, 2)
    cams = np.column_stack([xy, np.full(len(xy), 1.4)])
    p = preset("soybean", box_size=None)

    def fitted(units_per_metre: float):
        return fit_rows_with_scale(
            pts * units_per_metre, col, "soybean", p, rng=8, metric_scale=1.0,
            metric_source="metric_poses", known_row_spacing=lay.row_spacing,
            cameras=cams * units_per_metre,
        )  # fmt: skip

    warning = fitted(2.7).diagnostics["scale_warning"]
    assert warning.startswith("the imported poses, read as metres (they put the cameras 3.78 m up)")
    assert "poses.imported_metric=false" in warning
    up = float(warning.split("the rows put the cameras ")[1].split(" m up")[0])
    assert up == pytest.approx(1.4, rel=0.05)
    assert "scale_warning" not in fitted(1.0).diagnostics
    # a phone walked round maize stands a hand-held height up, not the drone's 13 m: not asked
    maize, mcol, mlay = make_cloud(
        "maize", None, 20.0, seed=8, half=2.5, density=1000, region=MAIZE_REGION
    )
    walk = fit_rows_with_scale(
        maize, mcol, "maize", preset("maize", box_size=None), rng=8, metric_scale=1.0,
        metric_source="metric_poses", known_row_spacing=mlay.row_spacing, cameras=cams,
    )  # fmt: skip
    assert "scale_warning" not in walk.diagnostics


def test_a_canopy_far_below_cameras_scaled_by_the_rows_is_named():
    """A soybean drone flight (13 m) through SfM took the hand-held 1.4 m prior, and the rows
    "confirmed" a scale 14x off: LAI 0.09 for 1.26 with nothing said of the scale (session
    96's capture audit). Where the rows set the scale (or it is assumed), a canopy standing
    under 6 % of the cameras' height above its ground is named with both heights at that
    scale, for the user to judge; a walk's cameras are not."""
    pts, col, lay = make_cloud("soybean", None, 0.0, seed=8)
    xy = np.stack(np.meshgrid(np.linspace(-2, 2, 5), np.linspace(-2, 2, 4)), -1).reshape(-1, 2)
    p = preset("soybean", box_size=None)

    def fitted(height_m: float, units_per_metre: float = 1.0):
        cams = np.column_stack([xy * height_m / 1.4, np.full(len(xy), height_m)])
        return fit_rows_with_scale(
            pts * units_per_metre, col, "soybean", p, rng=8,
            known_row_spacing=lay.row_spacing, cameras=cams * units_per_metre,
        )  # fmt: skip

    walk = fitted(1.4, 0.8)
    assert walk.scale_source == "row_spacing" and "scale_warning" not in walk.diagnostics
    drone = fitted(13.0, 0.8)
    assert drone.scale_source == "row_spacing"
    assert drone.scale == pytest.approx(walk.scale)  # the rows' answer itself stands
    warning = drone.diagnostics["scale_warning"]
    assert warning.startswith("the cameras stand ")
    assert "(a drone's view?) and the scale is the rows' alone" in warning
    assert "--camera-height" in warning
    up = float(warning.split("the cameras are ")[1].split(" m up")[0])
    assert up == pytest.approx(13.0, rel=0.05)
    # cameras on the far side of the fitted ground (at a scale far off it can lie in the
    # canopy, the plants below it): a drone flight read LAI 0.32 for 1.26 unwarned
    assert "a drone's view?" in fitted(-13.0, 0.8).diagnostics["scale_warning"]


def test_nadir_photos_at_a_hand_held_scale_that_a_drone_could_have_taken_are_refused():
    """Nadir SfM photos of soybean take the hand-held prior (1.4 m) whether a phone held over
    the plot or a drone took them: soybean flights at 8, 13 and 20 m then read LAI 0.09 for
    1.26, their rows "confirming" scales 7-14x off, or stopped later on an empty mask
    (sessions 96-97). Where the photos look straight down, the scale is the rows' or assumed
    at a hand-held height and the canopy stands under 15 % of the cameras' height (a drone
    could show it so), the row fit stops and asks for the height; a walk's photos, a
    canopy too tall for a drone's view and a drone's own prior pass."""
    pts, col, lay = make_cloud("soybean", None, 0.0, seed=8)
    xy = np.stack(np.meshgrid(np.linspace(-2, 2, 5), np.linspace(-2, 2, 4)), -1).reshape(-1, 2)
    p = preset("soybean", box_size=None)

    def fitted(height_m: float, prior_m: float, nadir: bool = True, **kw):
        cams = np.column_stack([xy * height_m / 1.4, np.full(len(xy), height_m)])
        k = prior_m / height_m  # the frame the poses stage scaled by its prior
        return fit_rows_with_scale(
            pts * k, col, "soybean", p, rng=8, known_row_spacing=lay.row_spacing,
            cameras=cams * k, nadir=nadir, **kw,
        )  # fmt: skip

    with pytest.raises(RowFitError, match="the scale cannot be measured") as err:
        fitted(13.0, 1.4)
    assert "--camera-height M" in str(err.value) and "look straight down" in str(err.value)
    # the canopy's height at 1.4 m and at 13 m, for the user to judge
    assert re.search(
        r"1\.4 m up the canopy would be [\d.]+ cm tall, 13 m up [\d.]+ cm", str(err.value)
    )
    with pytest.raises(RowFitError, match="the scale cannot be measured"):
        fitted(8.0, 1.4)
    # photos whose GPS positions could not set the scale: why, said with the refusal
    why = "the photos' GPS positions spread 3.3 m and lie 0.6 m (RMS) from their cameras"
    with pytest.raises(RowFitError, match=r"GPS positions could not set it: the photos' GPS"):
        fitted(13.0, 1.4, gps_reason=why)
    # ... which the far-above warning (6 %) does not reach: a walk's photos say nothing there
    assert "scale_warning" not in fitted(8.0, 1.4, nadir=False).diagnostics
    # the same cloud from a walk (45-70 degrees down): the far-above warning, as before
    assert "a drone's view?" in fitted(13.0, 1.4, nadir=False).diagnostics["scale_warning"]
    # a phone held over a grown canopy: no drone 8 m up could show it so tall
    held = fitted(1.4, 1.4)
    assert held.scale == pytest.approx(1.0, rel=0.03) and "scale_warning" not in held.diagnostics
    # a drone's prior (maize's 13 m, here given to soybean): the rows' answer stands, warned
    assert "a drone's view?" in fitted(13.0, 13.0).diagnostics["scale_warning"]


def test_a_scale_from_the_photos_gps_is_kept_and_the_rows_period_at_it_recorded():
    """Nadir soybean photos 13 m up whose GPS set the poses' scale (the poses stage's
    ``gps``): not refused, no rows' check from the hand-held prior (whose rows "confirm" a
    scale 7-14x off on such flights), and the rows' period at the GPS scale recorded."""
    pts, col, lay = make_cloud("soybean", None, 0.0, seed=8)
    xy = np.stack(np.meshgrid(np.linspace(-4, 4, 5), np.linspace(-4, 4, 4)), -1).reshape(-1, 2)
    cams = np.column_stack([xy, np.full(len(xy), 13.0)])
    fit = fit_rows_with_scale(
        pts, col, "soybean", preset("soybean", box_size=None), rng=8, metric_scale=1.0,
        metric_source="gps", known_row_spacing=lay.row_spacing, cameras=cams, nadir=True,
    )  # fmt: skip
    assert fit.scale_source == "gps" and fit.scale == 1.0
    assert fit.diagnostics["rows_factor"] == pytest.approx(1.0, abs=0.03)
    assert "scale_warning" not in fit.diagnostics


def _translate(t):
    m = np.eye(4)
    m[:3, 3] = t
    return m


def test_a_ground_plane_on_the_canopys_soil_coloured_top_moves_down_to_the_soil():
    """From a drone 25 m up the fused surface of a maize canopy holds more soil-coloured leaf
    points in a layer at its top than it holds soil seen between the plants: the RANSAC plane
    lay on the top (a 25 m flight's 0.78 m up its 1.13 m canopy, which then read 0.31 m tall).
    Maize's ``lower_ground_share`` (0.5) takes the parallel plane below holding at least half
    as many soil points: the soil. A cloud without such a layer fits as before, to the bit."""
    pts, col, _ = make_cloud("maize", None, 0.0, seed=3, half=2.5, density=1000,
                             region=MAIZE_REGION, soil=False)  # fmt: skip
    rng = np.random.default_rng(3)
    soil = np.column_stack([rng.uniform(-2.5, 2.5, (3000, 2)), rng.normal(0, 0.01, 3000)])
    top = float(np.percentile(pts[:, 2], 99.5))
    layer = np.column_stack([rng.uniform(-2.5, 2.5, (5000, 2)), rng.normal(top - 0.4, 0.02, 5000)])
    brown = BROWN + rng.normal(0, 0.03, (8000, 3))
    cloud = np.vstack([pts, soil, layer]), np.clip(np.vstack([col, brown]), 0, 1)
    paper = fit_ground_and_rows(
        *cloud, "maize", preset("maize", box_size=None, lower_ground_share=None), 0
    )
    assert abs(paper.ground_offset) == pytest.approx(top - 0.4, abs=0.05)  # in the canopy
    fit = fit_ground_and_rows(*cloud, "maize", preset("maize", box_size=None), 0)
    assert fit.diagnostics["ground_moved_down_from"] > fit.ground_inliers >= 2500
    assert abs(fit.ground_offset) < 0.02 and fit.ground_normal[2] > 0.999
    assert fit.diagnostics["canopy_top"] == pytest.approx(top, abs=0.05)
    plain = make_cloud("maize", None, 0.0, seed=3, half=2.5, density=1000, region=MAIZE_REGION)
    a = fit_ground_and_rows(*plain[:2], "maize", preset("maize", box_size=None), 0)
    b = fit_ground_and_rows(
        *plain[:2], "maize", preset("maize", box_size=None, lower_ground_share=None), 0
    )
    assert a.to_dict() == b.to_dict() and "ground_moved_down_from" not in a.diagnostics
    with pytest.raises(ConfigError, match="lower_ground_share"):
        preset("maize", lower_ground_share=0)


def test_scale_fallback_with_a_single_row():
    lay = default_layout("soybean", plot_width=0.8)
    rng = np.random.default_rng(9)
    can = generate_canopy("soybean", YOUNG_SOY, lay, seed=9, region=(-1.4, 1.4, -0.1, 0.1))
    p = sample_faces(can.mesh, 3000, rng)
    ns = 20000
    soil = np.column_stack([rng.uniform(-1.4, 1.4, (ns, 2)), rng.normal(0, 0.005, ns)])
    pts = np.vstack([p, soil])
    col = np.vstack([np.tile(GREEN, (len(p), 1)), np.tile(BROWN, (ns, 1))])
    fit = fit_ground_and_rows(pts, col, "soybean", preset("soybean", box_size=None), rng=9)
    est = estimate_scale_from_rows(fit, lay.row_spacing)
    assert est.method == "fallback_unchanged" and est.factor == 1.0
    # no period to match: the direction comes from the sharpest lateral profile
    assert errors(fit, np.eye(4), lay)[0] <= 2.0


# --------------------------------------------------------------------------- errors
def test_named_errors():
    p = preset("soybean", box_size=None)
    pts, col, _ = make_cloud("soybean", YOUNG_SOY, 0.0, seed=10, soil=False)
    with pytest.raises(RowFitError, match="no ground found"):
        fit_ground_and_rows(pts, col, "soybean", p, rng=0)
    # enough ground-coloured points, but scattered through the canopy, on no plane (a closed
    # canopy's reconstruction: nerfacto on a 1.1 m canopy, benchmarks/RESULTS.md#nerfacto-dense)
    rng = np.random.default_rng(1)
    specks = np.column_stack([rng.uniform(-1, 1, (80, 2)), rng.uniform(0.1, 0.9, 80)])
    brown = np.vstack([col, np.tile(BROWN, (80, 1))])
    with pytest.raises(
        RowFitError, match=r"best plane holds \d+ of \d+ ground-coloured.*closed canopy"
    ):
        fit_ground_and_rows(np.vstack([pts, specks]), brown, "soybean", p, rng=0)
    rng = np.random.default_rng(0)
    soil = np.column_stack([rng.uniform(-1, 1, (30000, 2)), rng.normal(0, 0.005, 30000)])
    scol = np.tile(BROWN, (30000, 1))
    scol[:200] = GREEN  # a few scattered green specks: no row
    with pytest.raises(RowFitError, match="no rows found"):
        fit_ground_and_rows(soil, scol, "soybean", p, rng=0)
    with pytest.raises(RowFitError, match="too few points"):
        fit_ground_and_rows(soil[:50], scol[:50], "soybean", p, rng=0)
    with pytest.raises(RowFitError, match="too few points"):  # everything outside the box
        fit_ground_and_rows(soil + [0, 0, 1.0], scol, "soybean", rng=0)
    with pytest.raises(ConfigError, match="box_center and box_size must be three numbers"):
        preset("soybean", box_size=2.0, box_center=0.0)
    with pytest.raises(ConfigError, match="must be a positive number"):
        fit_ground_and_rows(soil, scol, "soybean", p, scale=True)
    rows, rcol, _ = rows_cloud()
    fit_ground_and_rows(rows, rcol, "soybean", p, scale=np.float32(1.0), rng=0)  # numpy's scale
    assert issubclass(RowFitError, CropCraftError)


@pytest.mark.parametrize("crop, params", [("soybean", BIG_SOY), ("maize", None)])
def test_a_canopy_whose_leaves_are_not_green_is_refused_not_read_as_soil(crop, params):
    """Senescent (yellow-brown) leaves are soil to the colour split: where most of what stands
    above the ground is soil-coloured the run stops with a named error instead of fitting rows
    on the few green points left (an LAI 0.24 answer for a 1.26 canopy, audit 95)."""
    p = preset(crop, box_size=None)
    kw = dict(half=2.5, density=1000, region=MAIZE_REGION) if crop == "maize" else {}
    pts, col, _ = make_cloud(crop, params, seed=3, **kw)
    rng = np.random.default_rng(0)
    leaf = pts[:, 2] > 0.02
    turned = leaf & (rng.random(len(pts)) < 0.95)  # 5 % of the leaf points stay green
    brown = col.copy()
    dry = np.array([0.55, 0.42, 0.22])  # L* 47, a* +5, b* +25: a dry leaf
    brown[turned] = np.clip(dry + rng.normal(0, 0.03, (turned.sum(), 3)), 0, 1)
    with pytest.raises(RowFitError, match=r"soil-coloured.*(senescent|not green)"):
        fit_ground_and_rows(pts, brown, crop, p, rng=0)
    # the same canopy green, or with a tenth of its leaves turned, is fitted as before
    fit_ground_and_rows(pts, col, crop, p, rng=0)
    some = leaf & (rng.random(len(pts)) < 0.1)
    part = col.copy()
    part[some] = brown[some]
    fit = fit_ground_and_rows(pts, part, crop, p, rng=0)
    assert 0.05 < fit.diagnostics["soil_coloured_canopy"] < 0.25
    # the user may let it through
    off = preset(crop, box_size=None, max_soil_coloured_canopy=None)
    try:
        fit_ground_and_rows(pts, brown, crop, off, rng=0)
    except RowFitError as e:
        assert "soil-coloured" not in str(e)
    with pytest.raises(ConfigError, match="max_soil_coloured_canopy"):
        preset(crop, max_soil_coloured_canopy=1.5)


def rows_cloud(az_deg=0.0, n_rows=3, half=0.95, seed=0, density=20000, z0=0.0):
    """Leaf points in rows 0.76 m apart (0.5 m tall, 6 cm wide) over a soil plane at ``z0``,
    cut to a ``half``-wide square; colours as floats in [0, 1]. Returns (points, colours,
    number of leaf points)."""
    rng = np.random.default_rng(seed)
    a = math.radians(az_deg)
    along, across = np.array([math.cos(a), math.sin(a)]), np.array([-math.sin(a), math.cos(a)])
    leaves = []
    for k in range(-(n_rows // 2), n_rows // 2 + 1):
        m = int(0.3 * density)
        t, off, h = rng.uniform(-3, 3, m), rng.normal(0, 0.06, m), rng.uniform(0, 0.5, m)
        xy = t[:, None] * along + (0.76 * k + off)[:, None] * across
        leaves.append(np.column_stack([xy, z0 + h]))
    leaf = np.vstack(leaves)
    leaf = leaf[np.all(np.abs(leaf[:, :2]) <= half, axis=1)]
    xs, ys = rng.uniform(-half, half, density), rng.uniform(-half, half, density)
    soil = np.column_stack([xs, ys, z0 + rng.normal(0, 0.005, density)])
    col = np.vstack(
        [GREEN + rng.normal(0, 0.02, (len(leaf), 3)), BROWN + rng.normal(0, 0.02, (density, 3))]
    )
    return np.vstack([leaf, soil]), np.clip(col, 0, 1), len(leaf)


def test_colours_are_read_in_their_own_range():
    """A 0-1 cloud with one value a hair over 1 (an averaged, fused colour) was read as 0-255:
    every point black, no ground found; 16-bit colours were clipped to white."""
    pts, col, n_leaf = rows_cloud()
    p = preset("soybean", box_size=None)
    want = fit_ground_and_rows(pts, col, "soybean", p, rng=0).diagnostics
    over = col.copy()
    over[0, 1] = 1.0001
    got = fit_ground_and_rows(pts, over, "soybean", p, rng=0).diagnostics
    assert (got["n_plant"], got["n_ground"]) == (want["n_plant"], want["n_ground"])
    for c in (np.round(col * 65535).astype(np.uint16), np.round(col * 255).astype(np.uint8)):
        got = fit_ground_and_rows(pts, c, "soybean", p, rng=0).diagnostics  # rounded: a few
        assert got["n_plant"] == pytest.approx(want["n_plant"], rel=0.005)  # points on the line
    assert want["n_plant"] > 0.9 * n_leaf and want["n_ground"] > 10_000  # 20,000 soil points
    np.testing.assert_allclose(
        srgb_to_lab(np.array([[65535, 0, 0]], np.uint16)), srgb_to_lab(np.array([[1.0, 0, 0]]))
    )
    with pytest.raises(InputError, match="colour values reach 5332"):
        fit_ground_and_rows(pts, col * 1e6, "soybean", p, rng=0)


def test_far_floaters_leave_the_row_fit_as_it_was():
    """Thirty stray points 100,000 km away (no scene box to cut them): the lateral profile's
    1 cm bins reached across them, a 74 GiB allocation; now they are left out of it."""
    pts, col, _ = rows_cloud()
    p = preset("soybean", box_size=None)
    near = fit_ground_and_rows(pts, col, "soybean", p, rng=0)
    far = np.array([[1e8, 3e7, 0.3]]) + np.random.default_rng(1).normal(0, 0.01, (30, 3))
    fit = fit_ground_and_rows(
        np.vstack([pts, far]), np.vstack([col, np.tile(GREEN, (30, 1))]), "soybean", p, rng=0
    )
    assert fit.best_row.azimuth_deg == pytest.approx(near.best_row.azimuth_deg, abs=0.5)


def test_an_unconfirmed_row_spacing_scale_falls_back_to_the_assumed_one():
    """The first, wide estimate of the scale can take a wrong peak (here x0.648 of a true
    x0.8); the refit at that scale then finds no row period within 15 % of the spacing. That
    fit was returned labelled "row_spacing"; the scale-1 fit is, labelled "assumed_metric"."""
    pts, col, _ = rows_cloud(az_deg=45.0, n_rows=5, half=0.7, density=30000, z0=-1.5)
    fit = fit_rows_with_scale(
        pts * 1.25, col, "soybean", preset("soybean", box_size=None), rng=0,
        known_row_spacing=0.76,
    )  # fmt: skip
    factors = fit.diagnostics["scale_factors"]
    assert fit.scale == 1.0 and fit.scale_source == "assumed_metric"
    assert len(factors) == 2 and factors[0] != pytest.approx(1.0, abs=0.1)
    assert "not confirmed" in fit.diagnostics["scale_fallback"]


def test_the_direction_is_refined_within_its_span_of_the_ransac_row(monkeypatch):
    """``refine_direction_deg`` bounds the search: the 0.02° search ran 1° either side of the
    best 0.5° step (0.24° off at a span of 0.1°), and a span under 0.5° left one coarse angle,
    not the RANSAC row's own."""
    import cropcraft_core.rowfit.fit as rf

    seen = {}
    refine = rf._refine_row

    def spy(xy, row, p, **kw):
        out = refine(xy, row, p, **kw)
        seen["in"], seen["out"] = (math.atan2(*r.direction[1::-1]) for r in (row, out[0]))
        return out

    monkeypatch.setattr(rf, "_refine_row", spy)
    pts, col, _ = rows_cloud()
    for span in (0.1, 0.3):
        p = preset("soybean", refine_direction_deg=span, box_size=None)
        fit_ground_and_rows(pts, col, "soybean", p, rng=0)
        assert abs(math.degrees(seen["out"] - seen["in"])) <= span + 1e-9


def on_voxel_edges(pts, voxel, rng):
    """Each point with two of its three coordinates snapped to a ``voxel`` lattice: where
    marching cubes puts the vertices of a TSDF's surface (on the voxel edges)."""
    out = pts.copy()
    free = rng.integers(0, 3, len(pts))
    for k in range(3):
        out[free != k, k] = np.round(pts[free != k, k] / voxel) * voxel
    return out


@pytest.mark.parametrize("az", [8.0, 20.0])
def test_direction_ignores_the_box_axes_and_the_voxel_lattice(az):
    """A reconstruction of a closed canopy: twice as many leaf-coloured points again spread
    evenly over the axis-aligned scene box at the leaves' heights, every point on a 7.5 mm voxel
    lattice (TSDF vertices). The box's edges and the lattice line up along the scene axes; the
    raw sharpest-profile criterion picked the axis (errors 8.0° and 20.1° here, and 6.2° on
    an SfM scene); the row period does not line up there."""
    pts, col, lay = make_cloud("soybean", {"leaf_length": 1.0, "num_nodes": 7.0}, az, seed=5)
    rng = np.random.default_rng(0)
    leaf = col[:, 1] > 0.35
    n = 2 * int(leaf.sum())
    fill = np.column_stack([rng.uniform(-1.4, 1.4, (n, 2)), rng.choice(pts[leaf, 2], n)])
    pts = on_voxel_edges(np.vstack([pts, fill]), 0.0075, rng)
    col = np.vstack([col, np.clip(GREEN + rng.normal(0, 0.03, (n, 3)), 0, 1)])
    p = preset("soybean", box_size=None, row_spacing=lay.row_spacing)
    fit = fit_ground_and_rows(pts, col, "soybean", p, rng=0)
    assert errors(fit, np.eye(4), lay)[0] <= 1.0


@pytest.mark.parametrize("params,az,seed", [(None, 0.0, 7), (None, 30.0, 8), (BIG_SOY, 0.0, 5)])
def test_known_row_spacing_puts_camera_on_the_row(params, az, seed):
    """Mid-season and nearly closed soybean: with the known planting row spacing, the best row
    snaps to the periodic row pattern and the camera sits within 3 cm of a true row."""
    pts, col, lay = make_cloud("soybean", params, az, seed)
    scene, m = to_scene(pts, seed, scale=1.0)
    fit = fit_ground_and_rows(
        scene, col, "soybean", preset("soybean", box_size=None, row_spacing=0.76), rng=seed
    )
    dir_err, lateral, height, _ = errors(fit, m, lay)
    assert dir_err <= 2.0 and lateral <= 0.03 and height <= 0.03


def test_scale_from_rows_of_visible_surfaces_of_a_closed_canopy():
    """What a reconstruction sees of a closed soybean canopy: only the visible surfaces, leaves
    filling the space between rows. The lateral profile then has a strong envelope and a weak
    row period; the scale must still come out within 1 % (it drifted 36 % per pass before the
    profile was high-passed)."""
    from cropcraft_core.surfaces import SurfacesConfig, make_backend, resolve_bbox
    from cropcraft_core.synth import walk_trajectory

    lay = default_layout("soybean")
    mid = {"leaf_length": 1.0, "petiole_length": 1.25, "petiole_angle": 2.25}
    canopy = generate_canopy("soybean", {**mid, "internode_length": 1.25, "num_nodes": 7.5}, lay)
    cams = walk_trajectory(lay, 24, np.random.default_rng(0), canopy_top=0.6, size=(320, 240))
    truth = make_backend(SurfacesConfig(backend="truth"), mesh=canopy.mesh)
    images = [np.zeros((c.height, c.width, 3), np.uint8) for c in cams]
    truth.fit(images, cams, resolve_bbox("auto", "soybean"))
    pts, col = truth.point_cloud(100_000)
    # stereo fills the gaps between rows at canopy height (smoothing, mixed pixels): as many
    # leaf-coloured points again, spread evenly over the box at the leaves' heights
    rng = np.random.default_rng(3)
    leaf = col[:, 1] > col[:, 0]
    n = int(leaf.sum())
    fill = np.column_stack([rng.uniform(-1.3, 1.3, (n, 2)), rng.choice(pts[leaf, 2], n)])
    pts = np.vstack([pts, fill])
    col = np.vstack([col, col[leaf][rng.integers(0, n, n)]])
    scene, _ = to_scene(pts, 3, scale=1.2)
    p = preset("soybean", box_center=None, box_size=None, row_spacing=lay.row_spacing)
    fit = fit_rows_with_scale(scene, col, "soybean", p, rng=3, known_row_spacing=lay.row_spacing)
    assert fit.scale_source == "row_spacing"
    assert abs(fit.scale * 1.2 - 1) <= 0.01, fit.diagnostics


def test_camera_is_raised_over_a_tall_canopy():
    """A 1.4 m soybean canopy (the benchmark's tallest kind) would put the paper's 1.0 / 1.25 m
    camera among its leaves: the row fit raises it to 0.25 m over the canopy's top (clear of
    the depth histogram's lower edge, 0.1 m, and of the mask's colour band, 0.25 m, in which
    the observation drops green leaves), and says so; ``clear_canopy=False`` is the paper's
    fixed height."""
    tall = {"leaf_length": 1.2, "internode_length": 1.7, "num_nodes": 14.0}
    pts, col, lay = make_cloud("soybean", tall, 0.0, seed=8, density=1500)
    top = np.percentile(pts[:, 2], 99.5)
    assert top > 1.2
    scene, m = to_scene(pts, 8, scale=1.0)
    fit = fit_ground_and_rows(scene, col, "soybean", preset("soybean", box_size=None), rng=8)
    d = fit.diagnostics
    assert d["render_height_raised_from"] == (1.25 if fit.dense else 1.0)
    assert d["canopy_top"] + 0.25 <= fit.render_height < d["canopy_top"] + 0.3
    assert fit.camera.center[2] == pytest.approx(fit.render_height)
    assert fit.to_dict()["render_height"] == fit.render_height
    paper = fit_ground_and_rows(
        scene, col, "soybean", preset("soybean", box_size=None, clear_canopy=False), rng=8
    )
    assert paper.render_height == (1.25 if paper.dense else 1.0)
    assert "render_height_raised_from" not in paper.diagnostics
    with pytest.raises(ConfigError, match="clear_canopy"):
        preset("soybean", clear_canopy="yes")


def test_row_phase_follows_the_soil_where_leaves_pile_up_between_rows():
    """A closed canopy of wide plants: the leaves of neighbouring rows pile up between the rows
    (plant points weakly periodic at the inter-row), soil shows only there (strongly periodic):
    the row goes half a spacing from the soil's phase, onto the true row (y = 0), not onto the
    plants' pile. Where the soil is the weaker cue, the plants' phase stays the row."""
    from cropcraft_core.rowfit.fit import Row, _snap_to_row_pattern

    rng = np.random.default_rng(0)
    p = preset("soybean", row_spacing=0.76)

    def lines(n, centre, spread):  # points along x, y around centre + k·0.76
        k = rng.integers(-1, 2, n)
        return np.c_[rng.uniform(-0.8, 0.8, n), centre + 0.76 * k + rng.normal(0, spread, n)]

    between = 0.38
    plants = np.r_[lines(3000, between, 0.08), rng.uniform(-0.8, 0.8, (20000, 2))]
    soil = lines(1500, between, 0.05)
    start = Row(np.array([1.0, 0.0]), np.array([0.0, 0.3]), 0)
    row, _, cue = _snap_to_row_pattern(plants, plants, start, p, soil_xy=soil)
    assert cue == "soil" and abs(row.point[1]) < 0.01
    # without the soil (or with too few soil points) the plants' pile is taken for the row
    row, _, cue = _snap_to_row_pattern(plants, plants, start, p, soil_xy=soil[:50])
    assert cue == "plant" and abs(abs(row.point[1]) - between) < 0.01
    # rows of narrow plants: the plants are the stronger cue, soil everywhere is weak
    plants = lines(20000, 0.0, 0.06)
    soil = np.r_[lines(300, between, 0.1), rng.uniform(-0.8, 0.8, (3000, 2))]
    row, _, cue = _snap_to_row_pattern(plants, plants, start, p, soil_xy=soil)
    assert cue == "plant" and abs(row.point[1]) < 0.01


def test_row_direction_follows_the_soil_where_the_plants_show_no_period():
    """The plants of a closed canopy fill the plot with no visible row period; the soil shows
    in lines between the rows (here at 20°): the refined row runs along the soil's lines. Where
    the plants show the period too, their direction is kept unless the soil's is clearly the
    stronger."""
    from cropcraft_core.rowfit.fit import (
        SOIL_DIRECTION_MARGIN,
        Row,
        _direction_scores,
        _refine_row,
    )

    rng = np.random.default_rng(1)
    p = preset("soybean", row_spacing=0.76)
    a = np.radians(20.0)
    d, n = np.array([np.cos(a), np.sin(a)]), np.array([-np.sin(a), np.cos(a)])

    def lines(count, centre, spread):
        k = rng.integers(-1, 2, count)
        along = rng.uniform(-0.8, 0.8, count)
        across = centre + 0.76 * k + rng.normal(0, spread, count)
        return along[:, None] * d + across[:, None] * n

    plants = rng.uniform(-0.9, 0.9, (20000, 2))
    soil = lines(1500, 0.38, 0.05)
    start = Row(np.array([1.0, 0.0]), np.zeros(2), 0)
    row, _ = _refine_row(plants, start, p, direction_xy=plants, soil_xy=soil)
    assert abs(np.degrees(np.arctan2(row.direction[1], row.direction[0])) - 20.0) < 0.5
    # plant rows at 20° and soil lines at 0°, weaker: the plants' direction stays
    plants = lines(20000, 0.0, 0.06)
    soil = np.r_[
        np.c_[rng.uniform(-0.8, 0.8, 300), 0.38 + rng.normal(0, 0.1, 300)],
        rng.uniform(-0.9, 0.9, (3000, 2)),
    ]
    row, _ = _refine_row(plants, start, p, direction_xy=plants, soil_xy=soil)
    assert abs(np.degrees(np.arctan2(row.direction[1], row.direction[0])) - 20.0) < 0.5
    # both periodic, the soil's lines (at 14°) a little sharper than the plants' broad rows (at
    # 20°), by less than SOIL_DIRECTION_MARGIN: the plants, the more precise cue, keep theirs
    plants = lines(20000, 0.0, 0.2)
    b = np.radians(14.0)
    along, k = rng.uniform(-0.8, 0.8, 1500), rng.integers(-1, 2, 1500)
    across = 0.38 + 0.76 * k + rng.normal(0, 0.1, 1500)
    soil = along[:, None] * [np.cos(b), np.sin(b)] + across[:, None] * [-np.sin(b), np.cos(b)]
    coarse = np.radians(np.arange(-30.0, 30.01, 0.5))
    corr = [_direction_scores(x - x.mean(axis=0), coarse, 0.76)[1].max() for x in (plants, soil)]
    assert 0 < corr[1] - corr[0] < SOIL_DIRECTION_MARGIN
    row, _ = _refine_row(plants, start, p, direction_xy=plants, soil_xy=soil)
    assert abs(np.degrees(np.arctan2(row.direction[1], row.direction[0])) - 20.0) < 1.5


def test_registration_finds_how_far_a_model_sits_off_its_cameras():
    """A reconstruction whose surfaces sit 4 cm aside and 3 cm low of where the camera-centre
    similarity puts them (an SfM model's tilt): ICP onto the truth recovers that shift, and the
    row camera's lateral error is then measured against the reconstructed plants."""
    crop = "maize"
    truth, _, lay = make_cloud(crop, seed=3, half=2.0, density=1500)
    recon, colors, _ = make_cloud(crop, seed=3, half=2.0, density=400)  # other samples, same canopy
    rng = np.random.default_rng(1)
    recon = recon + rng.normal(0, 0.005, recon.shape)
    offset = np.array([0.0, -0.04, -0.03])
    s, r = 1.7, Rotation.from_euler("zyx", [40, 3, -2], degrees=True).as_matrix()
    scene_from_true = np.eye(4)
    scene_from_true[:3, :3], scene_from_true[:3, 3] = s * r, [0.3, -1.2, 5.0]
    points = (recon + offset) @ scene_from_true[:3, :3].T + scene_from_true[:3, 3]
    refined, reg = register_to_truth(points, scene_from_true, truth, (0.3, 0.1, 0.05))
    np.testing.assert_allclose(reg.shift_m, -offset, atol=0.005)
    assert reg.rotation_deg < 0.2 and reg.fitness > 0.9
    assert np.cbrt(np.linalg.det(refined[:3, :3])) == pytest.approx(s, rel=1e-9)
    # a row fit on the moved model: 4 cm off by the cameras, on the row by its own plants
    fit = fit_rows_with_scale(
        points,
        colors,
        crop,
        preset(crop, row_spacing=lay.row_spacing, box_center=None, box_size=None),
        rng=0,
        metric_scale=1 / s,
    )
    assert row_fit_errors(fit, scene_from_true, lay).lateral_m > 0.03
    assert row_fit_errors(fit, refined, lay).lateral_m < 0.01


def test_neighbour_row_cameras_move_across_the_rows_and_sit_over_a_fitted_row_nearby():
    """The k-th neighbour's camera is the best row's moved by k spacings along its image y
    (same height, heading and intrinsics); with ``snap_fraction`` it sits on a parallel fitted
    row within that fraction of a spacing of that place instead; rows at an angle are no
    neighbours; a camera rolled by 180° counts its own image y."""
    from cropcraft_core.geometry.camera import PinholeCamera
    from cropcraft_core.rowfit import Row, neighbour_row_views, row_label

    heading = np.radians(30.0)
    d = np.array([np.cos(heading), np.sin(heading)])
    right = np.array([d[1], -d[0]])  # image y of a look-down camera: right of the row
    cam = PinholeCamera.look_down((0.3, -0.2), 1.0, tuple(d))
    assert cam.cam_to_world[:2, 1] == pytest.approx(right)
    c = np.array([0.3, -0.2])
    along = 0.9 * d  # fitted rows' points lie elsewhere along them
    rows = [
        Row(d, c + 0.05 * d, 900),  # the best row itself
        Row(d, c + 0.70 * right + along, 400),  # +1, planted 6 cm closer than the spacing
        Row(d, c - 0.80 * right - along, 300),  # -1, 4 cm farther
        Row(np.array([d[1], -d[0]]), c + 1.5 * right, 500),  # across the rows: ignored
        Row(d, c + 1.20 * right, 100),  # 0.32 m from +2's place: too far to snap
    ]
    # by default on the row pattern: k spacings, whatever lines the row fit found there
    plain = neighbour_row_views(cam, rows, 0.76, max_side=2)
    assert [v.offset_m for v in plain] == pytest.approx([0.76, -0.76, 1.52, -1.52])
    assert not any(v.snapped for v in plain)
    views = neighbour_row_views(cam, rows, 0.76, max_side=2, snap_fraction=0.25)
    assert [v.index for v in views] == [1, -1, 2, -2]
    assert [v.label for v in views] == ["row_p1", "row_m1", "row_p2", "row_m2"]
    assert [v.offset_m for v in views] == pytest.approx([0.70, -0.80, 1.52, -1.52])
    assert [v.snapped for v in views] == [True, True, False, False]
    for v in views:
        m = v.camera.cam_to_world
        assert m[:3, :3] == pytest.approx(cam.cam_to_world[:3, :3])
        assert m[:2, 3] == pytest.approx(c + v.offset_m * right)
        assert m[2, 3] == pytest.approx(1.0)
        assert (v.camera.width, v.camera.fx, v.camera.cy) == (cam.width, cam.fx, cam.cy)
    assert row_label(0) == "row_0" and row_label(-3) == "row_m3"
    assert neighbour_row_views(cam, rows, 0.76, max_side=0) == []
    # rolled by 180° (image x against the row's direction, image y to its left)
    flip = cam.cam_to_world.copy()
    flip[:3, 0] *= -1
    flip[:3, 1] *= -1
    rolled = PinholeCamera(cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy, flip)
    views = neighbour_row_views(rolled, rows, 0.76, max_side=1, snap_fraction=0.25)
    assert [v.offset_m for v in views] == pytest.approx([0.80, -0.70])
    for bad in (0.0, -0.76, float("nan")):
        with pytest.raises(ConfigError, match="row spacing"):
            neighbour_row_views(cam, rows, bad)
    for bad in (0.0, 0.5, -0.1):
        with pytest.raises(ConfigError, match="snap_fraction"):
            neighbour_row_views(cam, rows, 0.76, snap_fraction=bad)


def test_the_profile_autocorrelation_is_numpys_at_the_lags_asked():
    """Only the lags the direction search and the scale estimate read, each the number
    ``np.correlate`` gives (a wide field's full correlation was quadratic in its width)."""
    from cropcraft_core.rowfit.fit import _autocorrelation

    rng = np.random.default_rng(0)
    for n in (5, 80, 3000):
        h = rng.normal(size=n)
        full = np.correlate(h, h, "full")[n - 1 :]
        for lo, hi in ((0, n - 1), (1, min(n - 1, 40)), (n // 2, n // 2)):
            assert np.array_equal(_autocorrelation(h, lo, hi), full[lo : hi + 1])


def test_a_row_fit_failing_at_a_given_scale_names_where_the_scale_came_from():
    """A camera distance 10x short read the canopy 3.7 cm tall and the run ended in "no rows
    found" alone; the error now says the scale was the user's."""
    pts, col, lay = make_cloud("soybean", YOUNG_SOY, 0.0, seed=6)
    p = preset("soybean", box_size=None)
    for kw, source in (
        ({"metric_scale": 0.05, "metric_source": "camera_distance"}, "the camera distance given"),
        ({"metric_scale": 0.05, "metric_source": "gps"}, "the photos' GPS positions"),
        ({"scale_hint": 0.05}, r"the scale given \(rowfit.scale\)"),
    ):
        with pytest.raises(RowFitError, match=f"; the scale came from {source}: if it is off"):
            fit_rows_with_scale(pts, col, "soybean", p, rng=6, **kw)
    with pytest.raises(RowFitError) as err:  # metric poses: the poses' own scale, not named
        fit_rows_with_scale(pts, col, "soybean", p, rng=6, metric_scale=0.05)
    assert "the scale came from" not in str(err.value)
