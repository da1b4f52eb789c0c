"""Observation, histogram statistics and loss: hand-computed cases on analytic depth maps.

The row camera looks straight down from the render height H, so a horizontal plane at height h
has z-depth H - h at every pixel, and pixel row v sees the lateral offset
|y| = |v + 0.5 - cy| / fy * depth.
"""

from __future__ import annotations

import functools
import io
import json
import math

import cv2
import numpy as np
import pytest

from cropcraft_core.config.params import resolve_params
from cropcraft_core.errors import ConfigError, CropCraftError, InputError
from cropcraft_core.geometry.camera import PinholeCamera
from cropcraft_core.observe import (
    HistogramStats,
    LossPreset,
    Observation,
    bin_edges,
    blur_depth,
    compute_stats,
    loss,
    observation_mask,
    predicted_mask,
    preset,
    soybean_render_height,
    with_overrides,
)
from cropcraft_core.observe.histograms import sobel_magnitude

SOY = preset("soybean")
MAIZE = preset("maize")
CAM = SOY.row_camera()  # 994 × 738, 50°, 1 m
N = CAM.width * CAM.height
F = 0.5 * 738 / math.tan(math.radians(25))  # focal length in pixels


def plane(depth: float, cam: PinholeCamera = CAM, dtype=np.float64) -> np.ndarray:
    return np.full((cam.height, cam.width), depth, dtype=dtype)


def full(cam: PinholeCamera = CAM) -> np.ndarray:
    return np.ones((cam.height, cam.width), bool)


def canopy(h_render: float = 1.0, cam: PinholeCamera = CAM, seed: int = 0) -> np.ndarray:
    """Tilted elliptical 'leaves' over a NaN background (float32, like a render)."""
    return _canopy(h_render, cam, seed).copy()


@functools.lru_cache(maxsize=4)
def _canopy(h_render: float, cam: PinholeCamera, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    depth = np.full((cam.height, cam.width), np.nan, np.float32)
    vv, uu = np.mgrid[0 : cam.height, 0 : cam.width].astype(np.float64)
    s = cam.width / 994
    for _ in range(120):
        cx, cy = rng.uniform(0, cam.width), rng.normal(cam.height / 2, cam.height / 5)
        m = np.zeros(depth.shape, np.uint8)
        axes = (int(rng.uniform(15, 60) * s) + 1, int(rng.uniform(8, 30) * s) + 1)
        cv2.ellipse(m, (int(cx), int(cy)), axes, rng.uniform(0, 180), 0, 360, 1, -1)
        gx, gy = rng.normal(0, 4e-4 / s, 2)
        dz = h_render - rng.uniform(0.1, 0.7) * h_render + gx * (uu - cx) + gy * (vv - cy)
        sel = (m > 0) & ~(depth < dz)
        depth[sel] = dz[sel]
    return depth


# --------------------------------------------------------------------------- presets
def test_paper_presets():
    assert SOY.render_height == 1.0 and MAIZE.render_height == 5.0
    assert (SOY.image_width, SOY.image_height, SOY.vfov_deg) == (994, 738, 50.0)
    assert SOY.depth_range == (0.1, 1.0, 20) and MAIZE.depth_range == (2.0, 5.0, 10)
    assert SOY.lateral_range == (0.0, 0.5, 10) and MAIZE.lateral_range == (0.0, 2.5, 10)
    assert SOY.sobel_range == (0.0, 0.004, 10) == MAIZE.sobel_range
    assert (SOY.loss.blur_kernel, MAIZE.loss.blur_kernel) == (25, 55)
    lam = lambda p: (p.loss.lambda_lateral, p.loss.lambda_sobel, p.loss.lambda_mask)  # noqa: E731
    assert lam(SOY) == (2.0, 4.0, 1.0) and lam(MAIZE) == (1.0, 0.0, 1.0)
    assert (SOY.mask_top_band, SOY.mask_max_lateral, SOY.mask_l_min) == (0.25, 0.5, None)
    assert (MAIZE.mask_top_band, MAIZE.mask_max_lateral, MAIZE.mask_l_min) == (2.0, 3.0, 40.0)
    assert SOY.mask_a_max == MAIZE.mask_a_max == -8.0
    assert SOY.mask_min_height == MAIZE.mask_min_height == 0.1
    assert soybean_render_height(0.8) == 1.25 and soybean_render_height(0.75) == 1.0


def test_preset_overrides_move_derived_ranges_and_round_trip():
    p = preset("soybean", render_height=1.25, lambda_sobel=0, depth_bins="40")
    assert p.depth_range == (0.1, 1.25, 40) and p.lateral_range == (0.0, 0.625, 10)
    assert p.loss.lambda_sobel == 0.0 and p.loss.lambda_lateral == 2.0
    assert type(p.loss.depth_bins) is int
    assert preset("soybean", depth_max=0.9).depth_range == (0.1, 0.9, 20)
    assert type(p).from_dict(json.loads(json.dumps(p.to_dict()))) == p
    assert with_overrides(p, lambda_mask=3).loss.lambda_mask == 3.0


@pytest.mark.parametrize(
    "crop, kw, words",
    [
        ("wheat", {}, "unknown crop"),
        ("soybean", {"lamda_sobel": 1}, "lamda_sobel"),
        ("soybean", {"blur_kernel": 24}, "odd"),
        ("soybean", {"lambda_mask": -1}, "lambda_mask"),
        ("soybean", {"normalisation": "pixels"}, "normalisation"),
        ("soybean", {"depth_min": 2.0}, "empty"),
        ("maize", {"render_height": 0}, "render_height"),
        ("maize", {"sobel_bins": 2.5}, "integer"),
        ("maize", {"vfov_deg": float("nan")}, "vfov_deg"),
        ("soybean", {"views_along": 2}, "odd"),
        ("soybean", {"views_along": 1.5}, "integer"),
        ("soybean", {"views_across": -1}, "non-negative"),
        ("soybean", {"view_step": 0}, "positive"),
        ("soybean", {"prediction_blur_m": -0.001}, "prediction_blur_m"),
        ("soybean", {"prediction_blur_m": float("inf")}, "prediction_blur_m"),
    ],
)
def test_bad_presets_raise_config_error(crop, kw, words):
    with pytest.raises(ConfigError, match=words):
        preset(crop, **kw)


def test_pooled_row_cameras_offsets_and_records():
    """The cameras an observation pools (``views_along``, ``view_step``, ``views_across``):
    the row camera first, then along the row, then each neighbouring row; the record keeps
    them, and one written before the fields existed reads as the single row camera."""
    assert SOY.n_views == 1 and SOY.view_offsets() == [(0.0, 0.0)]
    p = preset("soybean", views_along=3, view_step=0.4)
    assert p.n_views == 3 and p.view_offsets() == [(0.0, 0.0), (-0.4, 0.0), (0.4, 0.0)]
    q = preset("soybean", views_along=3, views_across=1)
    assert q.n_views == 9 and q.view_offsets(0.7)[3:6] == [(0.0, -0.7), (-0.5, -0.7), (0.5, -0.7)]
    with pytest.raises(ConfigError, match="row spacing"):
        q.view_offsets()
    assert type(q).from_dict(q.to_dict()) == q
    old = SOY.to_dict()
    for k in ("views_along", "views_across", "view_step"):
        del old[k]
    assert type(SOY).from_dict(old) == SOY
    # a camera moves along its own image axes: along the row, then across it
    cam = SOY.row_camera(center_xy=(1.0, 2.0), row_direction=(0.0, 1.0)).shifted(0.5, 0.2)
    np.testing.assert_allclose(cam.center, [1.2, 2.5, 1.0], atol=1e-12)


def test_pooled_statistics_are_required_and_share_one_spec():
    """A preset that pools several cameras cannot be filled from the row camera's depth map
    alone (that would be one camera's statistics under a many-camera name); statistics of
    different presets are not averaged."""
    from cropcraft_core.observe import mean_stats

    cam = CAM.scaled(0.25)
    small = {"image_width": cam.width, "image_height": cam.height}
    p = preset("soybean", **small, views_along=3)
    with pytest.raises(ConfigError, match="pools 3 row cameras"):
        Observation("soybean", cam, plane(0.6, cam), full(cam), preset=p)
    one = Observation("soybean", cam, plane(0.6, cam), full(cam), preset=preset("soybean", **small))
    pooled = Observation("soybean", cam, plane(0.6, cam), full(cam), stats=one.stats, preset=p)
    assert pooled.stats.equals(one.stats) and mean_stats([one.stats]) is one.stats
    other = Observation(
        "soybean", cam, plane(0.6, cam), full(cam), preset=preset("soybean", **small, depth_bins=10)
    )
    with pytest.raises(ConfigError, match="different presets"):
        mean_stats([one.stats, other.stats])
    with pytest.raises(ConfigError, match="at least one"):
        mean_stats([])


def test_depth_range_over_the_canopy_is_resolved_by_the_observation(tmp_path):
    # a 0.5 m maize "canopy" (a plane at z-depth 4.5 m under the 5 m camera) fills one of the
    # paper's 0.3 m bins; with depth_top_margin 0.25 the bins start a quarter of the canopy's
    # height above its top: [4.375, 5] m, 6.25 cm each, the plane in bin (4.5 - 4.375) / 0.0625
    cam = MAIZE.row_camera().scaled(0.25)
    p = preset("maize", depth_top_margin=0.25, image_width=cam.width, image_height=cam.height)
    assert p.depth_range == (2.0, 5.0, 10)  # unresolved until it sees a canopy
    o = Observation("maize", cam, plane(4.5, cam), full(cam), preset=p)
    assert o.preset.depth_range == (4.375, 5.0, 10) and o.preset.loss.depth_top_margin is None
    expected = np.zeros(10)
    expected[2] = 1.0
    np.testing.assert_array_equal(o.stats.depth, expected)
    assert o.loss_of(plane(4.5, cam)).total == 0.0
    # a taller prediction leaves the histogram (the mask area still counts it): a loss
    assert o.loss_of(plane(4.3, cam)).depth == pytest.approx(1.0)
    # the resolved preset round-trips as a fixed range, so a reload does not move it
    o.save(tmp_path / "o")
    back = Observation.load(tmp_path / "o")
    assert back.equals(o) and back.preset.depth_range == (4.375, 5.0, 10)
    # a canopy reaching above the paper's edge keeps it; a 0.5th-percentile top ignores a few
    # stray pixels above the canopy
    tall = Observation("maize", cam, plane(2.2, cam), full(cam), preset=p)
    assert tall.preset.depth_range == (2.0, 5.0, 10)
    d = plane(4.5, cam)
    d.flat[:: d.size // 50] = 2.5  # 50 pixels (0.14 %) high above the canopy
    assert Observation("maize", cam, d, full(cam), preset=p).preset.depth_range[0] == 4.375
    # the paper's fixed range (soybean's default) moves nothing; maize's default is this margin
    paper = with_overrides(p, depth_top_margin=None)
    assert Observation("maize", cam, plane(4.5, cam), full(cam), preset=paper).preset == paper
    assert MAIZE.loss.depth_top_margin == 0.25 and SOY.loss.depth_top_margin is None
    # a maize observation stored before the option existed reloads with the range it was made
    # with, not re-binned by today's default
    old = Observation("maize", cam, plane(4.5, cam), full(cam), preset=paper)
    old.save(tmp_path / "old")
    rec = json.loads((tmp_path / "old" / "observation.json").read_text())
    del rec["preset"]["depth_top_margin"]
    (tmp_path / "old" / "observation.json").write_text(json.dumps(rec))
    assert Observation.load(tmp_path / "old").equals(old)
    with pytest.raises(ConfigError, match="depth_top_margin"):
        preset("maize", depth_top_margin=-0.1)


def test_parameter_box_violation_is_a_config_error():
    with pytest.raises(ConfigError, match="outside its range"):
        resolve_params("soybean", {"num_nodes": 30})


# --------------------------------------------------------------------------- depth histogram
def test_flat_plane_fills_exactly_one_depth_bin():
    # plane 0.3 m above the ground: z-depth 0.7 m, bin (0.7 - 0.1) / 0.045 = 13.3 → bin 13
    s = compute_stats(plane(0.7), CAM, full(), SOY)
    expected = np.zeros(20)
    expected[13] = 1.0
    np.testing.assert_array_equal(s.depth, expected)
    assert s.mask_area == 1.0 and s.n_foreground == N and s.n_pixels == N
    # half the image masked: image normalisation halves the bin, foreground normalisation not
    m = full()
    m[:, : CAM.width // 2] = False
    assert compute_stats(plane(0.7), CAM, m, SOY).depth[13] == 0.5
    fg = preset("soybean", normalisation="foreground")
    assert compute_stats(plane(0.7), CAM, m, fg).depth[13] == 1.0


def test_maize_plane_and_numpy_edge_rules():
    cam = MAIZE.row_camera().scaled(0.25)
    s = compute_stats(plane(3.5, cam), cam, full(cam), MAIZE)  # (3.5 - 2) / 0.3 = 5.0 → bin 5
    assert s.depth[5] == 1.0 and s.depth.sum() == 1.0
    # exact edges: the render height lands in the last bin, 0.1 m in the first, 0.0999 nowhere
    for d, k in ((1.0, 19), (0.1, 0), (0.0999, None), (1.0001, None)):
        h = compute_stats(plane(d), CAM, full(), SOY).depth
        assert (h.sum() == 0.0) if k is None else (h[k] == 1.0), d


def test_depth_histogram_matches_numpy_on_a_canopy():
    d = canopy()
    m = predicted_mask(d)
    s = compute_stats(d, CAM, m, SOY)
    ref, _ = np.histogram(d[m].astype(np.float64), bins=20, range=(0.1, 1.0))
    np.testing.assert_array_equal(s.depth, ref / N)
    assert s.mask_area == m.mean()


@pytest.mark.parametrize("crop_preset", [SOY, MAIZE], ids=["soybean", "maize"])
def test_binning_by_computed_edges_counts_what_the_edge_arrays_count(crop_preset):
    """The vectorised binning computes each bin's edges as ``k * step + lo``; it must count
    exactly what binning against ``numpy.linspace``'s edge arrays counts, values exactly on
    an edge (and on ``hi``) included, and edges it cannot compute must be refused."""
    from cropcraft_core.observe import histograms as H

    e = bin_edges(crop_preset)
    linear = [H._linear_edges(e[k]) for k in ("depth", "lateral", "sobel")]
    assert all(par is not None for par in linear)
    cam = crop_preset.row_camera().scaled(0.25)
    rng = np.random.default_rng(7)
    d = rng.uniform(0.0, crop_preset.render_height * 1.05, (cam.height, cam.width))
    d.flat[: len(e["depth"])] = e["depth"]  # every depth edge exactly
    m = rng.random(d.shape) < 0.7
    d[~m] = np.nan
    dx = rng.uniform(-0.003, 0.003, d.shape).astype(np.float32)
    dy = rng.uniform(-0.003, 0.003, d.shape).astype(np.float32)
    dx.flat[: len(e["sobel"])] = e["sobel"]  # every sobel edge exactly (dy 0 there)
    dy.flat[: len(e["sobel"])] = 0.0
    yfac = H.lateral_factor(cam)
    for with_sobel in (True, False):
        got = H._histograms(d, m, yfac, dx, dy, *linear, with_sobel)
        ref = H._histograms_by_edges(
            d, m, yfac, dx, dy, e["depth"], e["lateral"], e["sobel"], with_sobel
        )
        for a, b in zip(got, ref, strict=True):
            np.testing.assert_array_equal(a, b)
    ref_depth, _ = np.histogram(d[m], bins=e["depth"])
    np.testing.assert_array_equal(got[0], ref_depth)
    bent = e["depth"].copy()
    bent[3] = np.nextafter(bent[3], 1.0)
    assert H._linear_edges(bent) is None


# --------------------------------------------------------------------------- lateral histogram
def test_lateral_histogram_of_a_known_strip():
    # plane at depth 0.8: row v sees |y| = |v + 0.5 - 369| * 0.8 / F, F = 791.32 px. The strip
    # |y| in [0.11, 0.14] m is |v + 0.5 - 369| in [108.77, 138.48] px: offsets 109.5 ... 137.5,
    # 29 rows each side, all in lateral bin 2 = [0.10, 0.15) m.
    t = np.abs(np.arange(738) + 0.5 - 369.0)
    rows = (t * 0.8 / F >= 0.11) & (t * 0.8 / F <= 0.14)
    assert rows.sum() == 58
    m = np.zeros((738, 994), bool)
    m[rows] = True
    s = compute_stats(plane(0.8), CAM, m, SOY)
    expected = np.zeros(10)
    expected[2] = 58 * 994 / N
    np.testing.assert_allclose(s.lateral, expected, rtol=0, atol=1e-15)


def test_lateral_is_metres_from_the_row_line():
    # ground-level plane (depth 1 m): |y| reaches tan(25°) = 0.466 m at the image edge; the last
    # bin [0.45, 0.5] holds rows with |v + 0.5 - 369| >= 0.45 F = 356.1 → 13 rows per side
    s = compute_stats(plane(1.0), CAM, full(), SOY)
    assert s.lateral.sum() == pytest.approx(1.0)
    assert s.lateral[9] == 26 * 994 / N
    # the same through camera.unproject → camera coordinates, on a canopy
    d = canopy()
    m = predicted_mask(d)
    pts = CAM.unproject(d.astype(np.float64))[m]
    y_cam = np.abs(CAM.to_camera(pts)[:, 1])
    ref, _ = np.histogram(y_cam, bins=10, range=(0.0, 0.5))
    got = compute_stats(d, CAM, m, SOY).lateral * N
    assert np.abs(got - ref).sum() <= 2  # identical up to rounding exactly at an edge


# --------------------------------------------------------------------------- sobel histogram
def test_sobel_of_a_flat_plane_is_zero():
    s = compute_stats(plane(0.7), CAM, full(), SOY)
    assert s.sobel[0] == 1.0 and s.sobel[1:].sum() == 0.0
    # exactly zero up to float32 rounding in OpenCV's blur (a few ulps of the depth)
    assert sobel_magnitude(plane(0.7), full(), SOY).max() < 1e-6


@pytest.mark.parametrize("axis", ["x", "y", "xy"])
def test_sobel_of_a_ramp_lands_in_the_known_bin(axis):
    # depth changes by s metres per pixel; the unnormalised 3×3 Sobel gives 8 s per axis and
    # the Gaussian blur leaves a linear ramp unchanged (away from the image border):
    # 8 s = 0.0014 → bin 3 = [0.0012, 0.0016)
    s = 0.0014 / 8 / (2 if axis == "xy" else 1)
    vv, uu = np.mgrid[0:738, 0:994].astype(np.float64)
    d = 0.6 + s * ((uu - 497) * ("x" in axis) + (vv - 369) * ("y" in axis))
    mag = sobel_magnitude(d, full(), SOY)
    r = SOY.loss.blur_kernel // 2 + 2
    np.testing.assert_allclose(mag[r:-r, r:-r], 0.0014, atol=1e-6)
    st = compute_stats(d, CAM, full(), SOY)
    interior = (738 - 2 * r) * (994 - 2 * r)
    assert st.sobel[3] * N >= interior
    assert st.sobel[4:].sum() == 0.0  # the border, where the ramp flattens, only goes lower
    assert st.sobel.sum() == pytest.approx(1.0)


def test_sobel_background_is_filled_with_the_ground():
    # a square leaf at depth 0.5 over no background: inside, far from the edge, derivatives
    # vanish; at its edge the blurred step to the ground depth (1 m) is steep (> 0.004)
    d = plane(np.nan)
    d[200:500, 300:700] = 0.5
    m = predicted_mask(d)
    mag = sobel_magnitude(d, m, SOY)
    assert mag[350, 500] < 1e-6 and mag[200, 500] > 0.004 and np.isfinite(mag).all()
    s = compute_stats(d, CAM, m, SOY)
    assert s.sobel[0] > 0 and s.sobel.sum() < s.mask_area  # steep edge pixels fall outside


def test_sobel_matches_an_independent_cv2_reference():
    d = canopy()
    m = predicted_mask(d)
    filled = np.where(m, d.astype(np.float64) - 1.0, 0.0).astype(np.float32)
    b = cv2.GaussianBlur(filled, (25, 25), 0, borderType=cv2.BORDER_REPLICATE)
    dx = cv2.Sobel(b, cv2.CV_32F, 1, 0, ksize=3, borderType=cv2.BORDER_REPLICATE)
    dy = cv2.Sobel(b, cv2.CV_32F, 0, 1, ksize=3, borderType=cv2.BORDER_REPLICATE)
    mag = np.abs(dx[m].astype(np.float64)) + np.abs(dy[m].astype(np.float64))
    ref, _ = np.histogram(mag, bins=10, range=(0.0, 0.004))
    np.testing.assert_array_equal(compute_stats(d, CAM, m, SOY).sobel, ref / N)


def test_maize_skips_sobel_by_default_because_its_weight_is_zero():
    cam = MAIZE.row_camera().scaled(0.25)
    d = plane(3.5, cam)
    s = compute_stats(d, cam, full(cam), MAIZE)
    assert not s.has_sobel and s.sobel.sum() == 0.0
    assert compute_stats(d, cam, full(cam), MAIZE, sobel=True).sobel[0] == 1.0
    # an observation always keeps it; a prediction without it still compares (λ_sobel = 0)
    obs = Observation.from_depth("maize", d, cam)
    assert obs.stats.has_sobel and obs.mask.all()
    got = obs.loss_of(plane(3.8, cam))  # (3.8 - 2) / 0.3 = 6.0 → bin 6
    assert got.depth == 2.0 and got.sobel == 0.0 and got.mask == 0.0


def test_empty_prediction_gives_zero_histograms():
    d = plane(np.nan)
    s = compute_stats(d, CAM, predicted_mask(d), SOY)
    assert s.mask_area == 0.0 and s.depth.sum() == s.lateral.sum() == s.sobel.sum() == 0.0
    fg = compute_stats(d, CAM, predicted_mask(d), preset("soybean", normalisation="foreground"))
    assert fg.depth.sum() == 0.0


def test_bin_edges_are_numpy_linspace():
    e = bin_edges(SOY)
    np.testing.assert_array_equal(e["depth"], np.linspace(0.1, 1.0, 21))
    np.testing.assert_array_equal(e["lateral"], np.linspace(0.0, 0.5, 11))
    np.testing.assert_array_equal(e["sobel"], np.linspace(0.0, 0.004, 11))


# --------------------------------------------------------------------------- loss
def test_identical_depth_maps_give_zero_loss():
    d = canopy()
    a = compute_stats(d, CAM, predicted_mask(d), SOY)
    b = compute_stats(d.copy(), CAM, predicted_mask(d), SOY)
    assert loss(a, b, SOY) == type(loss(a, b, SOY))(0.0, 0.0, 0.0, 0.0, 0.0)


def _stats(depth, lateral, sobel, area, p=SOY):
    return HistogramStats(
        np.asarray(depth, float),
        np.asarray(lateral, float),
        np.asarray(sobel, float),
        area,
        0,
        N,
        p.stats_spec(),
    )


def test_loss_weights_are_applied_as_documented():
    z20, z10 = np.zeros(20), np.zeros(10)
    obs = _stats(np.r_[0.5, 0.1, z20[2:]], z10, z10, 0.6)
    pred = _stats(np.r_[0.2, 0.3, z20[2:]], np.r_[0.1, z10[1:]], np.r_[0.0, 0.2, z10[2:]], 0.5)
    l_depth = 0.3**2 + 0.2**2  # 0.13
    l_lateral = 0.1**2  # 0.01
    l_sobel = 0.2**2  # 0.04
    l_mask = 0.1**2  # 0.01
    got = loss(obs, pred, SOY)
    assert got.depth == pytest.approx(l_depth) and got.lateral == pytest.approx(l_lateral)
    assert got.sobel == pytest.approx(l_sobel) and got.mask == pytest.approx(l_mask)
    assert got.total == pytest.approx(l_depth + 2 * l_lateral + 4 * l_sobel + 1 * l_mask)
    lp = LossPreset(depth_bins=20, depth_min=0.1, lambda_lateral=1, lambda_sobel=0)
    assert loss(obs, pred, lp).total == pytest.approx(l_depth + l_lateral + l_mask)
    assert set(got.to_dict()) == {"total", "depth", "lateral", "sobel", "mask"}


def test_loss_of_two_planes_by_hand():
    # obs plane depth 0.7 (bin 13), pred plane depth 0.8 (bin 15), both fill the image:
    # L_depth = 1² + 1² = 2; mask areas equal; both flat → sobel identical
    a = compute_stats(plane(0.7), CAM, full(), SOY)
    b = compute_stats(plane(0.8), CAM, full(), SOY)
    got = loss(a, b, SOY)
    assert got.depth == 2.0 and got.mask == 0.0 and got.sobel == 0.0
    # lateral: row v of a plane at depth d sees |y| = |v + 0.5 - 369| d / F, each row 994
    # pixels of the N, binned over [0, 0.5] m in 0.05 m bins
    t = np.abs(np.arange(738) + 0.5 - 369.0)

    def lateral(d: float) -> np.ndarray:
        counts, _ = np.histogram(t * d / F, bins=np.linspace(0.0, 0.5, 11))
        return counts * 994 / N

    by_hand = float(np.sum((lateral(0.7) - lateral(0.8)) ** 2))
    assert by_hand > 0.005  # the two planes' lateral histograms differ
    assert got.lateral == pytest.approx(by_hand, rel=1e-9)
    assert got.total == pytest.approx(2.0 + 2 * by_hand)


def test_loss_rejects_statistics_of_another_preset():
    cam = MAIZE.row_camera().scaled(0.25)
    soy = compute_stats(plane(0.7), CAM, full(), SOY)
    maize = compute_stats(plane(3.5, cam), cam, full(cam), MAIZE)
    with pytest.raises(ConfigError, match="different presets"):
        loss(soy, maize, SOY.loss)
    with pytest.raises(ConfigError, match="different preset"):
        loss(maize, maize, SOY)
    no_sobel = compute_stats(plane(0.7), CAM, full(), SOY, sobel=False)
    with pytest.raises(ConfigError, match="lambda_sobel"):
        loss(soy, no_sobel, SOY)
    assert loss(maize, maize, MAIZE).total == 0.0


# --------------------------------------------------------------------------- masks
def _img(cam, depth):
    d = np.full((cam.height, cam.width), depth, np.float64)
    rgb = np.zeros((cam.height, cam.width, 3), np.uint8)
    rgb[:] = (150, 100, 60)  # soil brown: a* = +16
    return d, rgb


def test_soybean_observation_mask_rules():
    cam = SOY.row_camera().scaled(0.25)
    d, rgb = _img(cam, 0.5)  # height 0.5 m
    green, brown = (0, 200, 0), (150, 100, 60)  # a* = -72, +16
    d[10, 10], rgb[10, 10] = 0.1, green  # 0.9 m high and green → background (colour clause)
    d[10, 11], rgb[10, 11] = 0.1, brown  # 0.9 m high, not green → foreground
    d[10, 12], rgb[10, 12] = 0.3, green  # 0.7 m: below the top band (0.75 m) → foreground
    d[10, 13] = 0.95  # 0.05 m above the ground → background
    d[10, 14] = 0.89  # 0.11 m above the ground → foreground
    d[10, 15] = np.nan  # nothing seen → background
    m = observation_mask(d, rgb, cam, SOY)
    assert m[10, 10:16].tolist() == [False, True, True, False, True, False]
    assert m.sum() == m.size - 3
    # without RGB the colour clause never fires
    assert observation_mask(d, None, cam, SOY)[10, 10]
    # float RGB in [0, 1] gives the same mask
    assert np.array_equal(observation_mask(d, rgb / 255.0, cam, SOY), m)


def test_lateral_mask_rule_uses_metres():
    # with a 0.3 m lateral limit a plane at depth 0.8 keeps rows with |v + .5 - cy| * 0.8 / f
    # < 0.3, i.e. |v + 0.5 - 369| < 296.7 px at full size
    p = preset("soybean", mask_max_lateral=0.3)
    m = observation_mask(plane(0.8), None, CAM, p)
    t = np.abs(np.arange(738) + 0.5 - 369.0)
    assert np.array_equal(m.all(axis=1), t < 0.3 * F / 0.8)
    assert m.all(axis=1).sum() == 2 * 297 and np.array_equal(m.any(axis=1), m.all(axis=1))
    # the same box on the predicted side, on request
    assert np.array_equal(predicted_mask(plane(0.8), CAM, p), m)


def test_maize_observation_mask_rules():
    cam = MAIZE.row_camera().scaled(0.25)
    d, rgb = _img(cam, 4.0)  # height 1 m
    d[5, 5], rgb[5, 5] = 1.5, (0, 200, 0)  # 3.5 m high, bright green (L* 70) → background
    d[5, 6], rgb[5, 6] = 1.5, (0, 60, 0)  # 3.5 m, dark green (L* 21 < 40) → foreground
    d[5, 7], rgb[5, 7] = 3.0, (0, 200, 0)  # 2 m high: not above 5 - 2 = 3 m → foreground
    d[5, 8] = 4.95  # 5 cm → background
    m = observation_mask(d, rgb, cam, MAIZE)
    assert m[5, 5:9].tolist() == [False, True, True, False]


def test_predicted_mask_is_finite_depth():
    d = plane(0.5)
    d[0, 0], d[0, 1], d[0, 2] = np.nan, np.inf, 0.0
    m = predicted_mask(d)
    assert m.sum() == m.size - 3 and not m[0, :3].any()
    with pytest.raises(ConfigError):
        predicted_mask(d, CAM)


# --------------------------------------------------------------------------- observation
@pytest.fixture(scope="module")
def obs() -> Observation:
    d = canopy()
    rgb = np.zeros((*d.shape, 3), np.uint8)
    rgb[:] = (40, 140, 40)
    return Observation.from_depth("soybean", d, CAM, rgb=rgb, meta={"scene": "t", "n": [1, 2]})


def test_observation_from_depth(obs):
    assert obs.preset == SOY and obs.depth.dtype == np.float32
    # all pixels are green (a* < -8), so the colour clause removes those above 0.75 m
    expected = predicted_mask(obs.depth, CAM, SOY) & ~(1.0 - obs.depth.astype(float) > 0.75)
    assert np.array_equal(obs.mask, expected) and 0 < obs.mask.sum() < expected.size
    assert obs.stats.equals(compute_stats(obs.depth, CAM, obs.mask, SOY))
    assert not obs.depth.flags.writeable and not obs.mask.flags.writeable
    # its own depth as a prediction (same mask) scores zero
    assert obs.loss_of(obs.depth, obs.mask).total == 0.0
    assert obs.loss_of(np.where(obs.mask, obs.depth, np.nan)).total == 0.0


def test_a_prediction_is_cut_by_the_box_the_observation_was_cut_by():
    """Leaves under ``mask_min_height`` that the observation's mask drops are dropped from a
    prediction too: the scene itself, rendered as a prediction, scores zero. Uncut, it would
    not, and a fit tilts the leaves to hide the low ones (the demo's leaf angle read 24° for
    15°)."""
    d = canopy()
    scene = np.where(np.isfinite(d), d, plane(0.95)).astype(np.float32)  # + a 5 cm-high layer
    o = Observation.from_depth("soybean", scene, CAM)
    assert o.box_mask and not o.mask[np.isnan(d)].any()
    assert o.loss_of(scene).total == 0.0
    uncut = o.predicted_stats(scene, predicted_mask(scene))
    assert loss(o.stats, uncut, o.preset).total > 1e-3
    paper = Observation.from_depth(
        "soybean", scene, CAM, preset=preset("soybean", mask_predictions=False)
    )
    assert paper.predicted_stats(scene).equals(uncut)
    with pytest.raises(ConfigError, match="mask_predictions must be true or false"):
        preset("soybean", mask_predictions=1)
    # a render without background, masked by its finite depth: no box on either side
    s = Observation("soybean", CAM, scene, np.isfinite(scene), box_mask=False)
    assert s.loss_of(scene).total == 0.0
    assert s.predicted_stats(scene).equals(compute_stats(scene, CAM, np.isfinite(scene), SOY))


def test_blur_depth_averages_finite_pixels_only():
    """A step between two overlapping leaves becomes a ramp over a few sigma; a leaf's edge
    over the background keeps its depth (the background never enters the mean), NaN stays
    NaN, and a constant leaf stays constant."""
    d = np.full((60, 80), np.nan, np.float32)
    d[10:50, 10:40] = 0.5  # upper leaf
    d[10:50, 40:70] = 0.7  # lower leaf, touching it at column 40
    b = blur_depth(d, 3.0)
    assert np.array_equal(np.isnan(b), np.isnan(d)) and b.dtype == np.float32
    row = b[30, 10:70]
    assert np.all(np.diff(row) >= -1e-6)  # a monotone ramp from 0.5 to 0.7
    assert 0.55 < b[30, 39] < 0.6 < b[30, 40] < 0.65  # the step's two sides meet half-way
    assert np.allclose(b[30, 10:25], 0.5, atol=1e-6)  # 15 px = 5 sigma from the step
    assert np.allclose(b[30, 56:70], 0.7, atol=1e-6)
    assert np.allclose(b[10:50, 12], 0.5, atol=1e-6)  # edge over the background: unchanged
    flat = np.where(np.isfinite(d), np.float32(0.6), np.nan)
    assert np.allclose(blur_depth(flat, 5.0)[np.isfinite(d)], 0.6, atol=1e-6)
    assert np.array_equal(blur_depth(d, 0), d, equal_nan=True)
    for bad in (-1.0, float("nan")):
        with pytest.raises(ConfigError, match="blur sigma"):
            blur_depth(d, bad)


def test_prediction_blur_is_applied_to_predictions_only(tmp_path):
    """``prediction_blur_m``: the observation's own statistics are unchanged; a prediction's
    are those of its depth blurred by the metres' pixels at the observed canopy's median
    depth, over the mask of the unblurred depth; it is saved with the preset, and records
    written before it read as no blur."""
    d = canopy()
    sharp = Observation.from_depth("soybean", d, CAM)
    soft = Observation.from_depth(
        "soybean", d, CAM, preset=preset("soybean", prediction_blur_m=0.005)
    )
    assert soft.stats.equals(sharp.stats) and sharp.prediction_blur_px == 0.0
    z = float(np.median(d[soft.mask]))
    assert soft.prediction_blur_px == pytest.approx(0.005 * CAM.fy / z)
    pred = canopy(seed=1)
    expected = compute_stats(
        blur_depth(pred, soft.prediction_blur_px), CAM, predicted_mask(pred, CAM, SOY), SOY
    )
    assert soft.predicted_stats(pred).equals(expected)
    assert not soft.predicted_stats(pred).equals(sharp.predicted_stats(pred))
    # the blur moves the derivatives (steps between leaves soften) far more than the mask
    assert soft.predicted_stats(pred).mask_area == sharp.predicted_stats(pred).mask_area
    soft.save(tmp_path / "soft")
    back = Observation.load(tmp_path / "soft")
    assert back.preset.prediction_blur_m == 0.005 and back.predicted_stats(pred).equals(expected)
    sharp.save(tmp_path / "old")
    rec = json.loads((tmp_path / "old" / "observation.json").read_text())
    del rec["preset"]["prediction_blur_m"]  # as written before the field existed
    (tmp_path / "old" / "observation.json").write_text(json.dumps(rec))
    assert Observation.load(tmp_path / "old").preset.prediction_blur_m == 0.0


def test_box_mask_round_trips_and_records_without_it_read_as_cut(tmp_path):
    d = canopy()
    s = Observation("soybean", CAM, d, np.isfinite(d), box_mask=False)
    s.save(tmp_path / "s")
    back = Observation.load(tmp_path / "s")
    assert back.box_mask is False and back.equals(s)
    assert not back.equals(Observation("soybean", CAM, d, np.isfinite(d)))
    rec = json.loads((tmp_path / "s" / "observation.json").read_text())
    del rec["box_mask"]  # as written before the field existed, by observation_mask's callers
    (tmp_path / "s" / "observation.json").write_text(json.dumps(rec))
    assert Observation.load(tmp_path / "s").box_mask is True
    with pytest.raises(ConfigError, match="box_mask"):
        Observation("soybean", CAM, d, np.isfinite(d), box_mask="no")


def test_save_load_round_trip_is_exact(obs, tmp_path):
    obs.save(tmp_path / "o")
    assert {p.name for p in (tmp_path / "o").iterdir()} == {"observation.npz", "observation.json"}
    rec = json.loads((tmp_path / "o" / "observation.json").read_text())
    assert rec["crop"] == "soybean" and rec["preset"]["render_height"] == 1.0
    back = Observation.load(tmp_path / "o")
    assert back.equals(obs) and back.stats.equals(obs.stats)
    obs.save(tmp_path / "single.npz")
    assert Observation.load(tmp_path / "single.npz").equals(obs)
    buf = io.BytesIO()
    obs.save(buf)
    buf.seek(0)
    assert Observation.load(buf).equals(obs)
    data = buf.getvalue()
    for damaged in (data[: len(data) // 2], data[:30] + b"\x00" * 8 + data[38:]):
        with pytest.raises(InputError, match="cannot read observation npz"):
            Observation.load(io.BytesIO(damaged))


def test_a_directory_save_stopped_between_its_files_loads_the_new_observation_whole(obs, tmp_path):
    """A save into a directory writes the npz, then the json: stopped between the two, the
    new arrays stood beside the old record, loaded as one with the old statistics (a loss of
    5.0 of the observation against its own depth). The npz holds its record too, read where
    the json's digest is of other arrays."""
    obs.save(tmp_path)
    old_json = (tmp_path / "observation.json").read_text()
    other = Observation.from_depth(
        "soybean", np.clip(obs.depth * 0.9, 0.0, None), obs.camera, preset=obs.preset
    )
    other.save(tmp_path)
    (tmp_path / "observation.json").write_text(old_json)  # as the stopped save left it
    back = Observation.load(tmp_path)
    assert back.equals(other) and back.stats.equals(other.stats)
    assert back.loss_of(other.depth).total == 0.0


def test_load_recomputes_stats_when_the_stored_preset_was_edited(obs, tmp_path):
    obs.save(tmp_path)
    rec = json.loads((tmp_path / "observation.json").read_text())
    rec["preset"]["depth_bins"] = 10
    (tmp_path / "observation.json").write_text(json.dumps(rec))
    back = Observation.load(tmp_path)
    assert back.stats.depth.shape == (10,) and back.preset.loss.depth_bins == 10


def test_bad_observations_raise_named_errors(tmp_path):
    d = plane(0.5)
    cases = [
        (lambda: Observation.from_depth("soybean", plane(np.nan)), InputError, "no finite"),
        (lambda: Observation("soybean", CAM, d, ~full()), InputError, "mask is empty"),
        (lambda: Observation("soybean", CAM, d[:10], full()[:10]), InputError, "camera is"),
        (lambda: Observation("soybean", CAM, d, full()[:10]), InputError, "shape"),
        (
            lambda: Observation("soybean", CAM, np.where(full(), np.nan, d), full()),
            InputError,
            "no finite",
        ),
        (lambda: Observation.from_depth("soybean", d, rgb=np.zeros((5, 5, 3))), InputError, "rgb"),
        (lambda: Observation("wheat", CAM, d, full()), ConfigError, "unknown crop"),
        (lambda: Observation("soybean", CAM, d, full(), preset=MAIZE), ConfigError, "maize"),
        (lambda: Observation.from_depth("maize", d, CAM), ConfigError, "render height"),
        (
            lambda: Observation("soybean", CAM, d, full(), meta={"x": object()}),
            InputError,
            "meta",
        ),
        (lambda: Observation.load(tmp_path / "missing"), InputError, "no observation"),
    ]
    for make, err, words in cases:
        with pytest.raises(err, match=words):
            make()
    nan_in_mask = d.copy()
    nan_in_mask[3, 3] = np.nan
    with pytest.raises(InputError, match="not"):
        compute_stats(nan_in_mask, CAM, full(), SOY)
    with pytest.raises(InputError, match="not"):
        Observation("soybean", CAM, nan_in_mask, full())
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(InputError):
        Observation.load(tmp_path / "junk.npz")
    tilted = PinholeCamera.from_vfov(994, 738, 50.0, np.eye(4))
    with pytest.raises(ConfigError, match="straight down"):
        Observation("soybean", tilted, d, full())
    assert issubclass(InputError, CropCraftError)


def test_render_height_is_raised_only_over_a_canopy_that_reaches_the_depth_range():
    from cropcraft_core.observe import clear_render_height, observed_clearance

    assert clear_render_height("soybean", 1.0, 0.6) == 1.0
    assert clear_render_height("soybean", 1.0, 0.9) == 1.0  # exactly at the 0.1 m edge
    assert clear_render_height("soybean", 1.0, 1.44) == pytest.approx(1.55)
    assert clear_render_height("soybean", 1.25, 1.2) == pytest.approx(1.3)
    assert clear_render_height("maize", 5.0, 3.0) == 5.0  # maize's depth bins start at 2 m
    assert clear_render_height("maize", 5.0, 3.21) == pytest.approx(5.25)
    # an observed canopy also clears the mask's colour band (green leaves in it are dropped)
    assert observed_clearance("soybean") == 0.25 and observed_clearance("maize") == 2.0
    assert clear_render_height("soybean", 1.0, 0.8, observed_clearance("soybean")) == 1.05
    assert clear_render_height("soybean", 1.0, 0.75, observed_clearance("soybean")) == 1.0
    with pytest.raises(ConfigError, match="clearance"):
        clear_render_height("soybean", 1.0, 0.5, -0.1)
    with pytest.raises(ConfigError):
        clear_render_height("wheat", 1.0, 0.5)


def test_no_surface_fraction_and_its_warning():
    from cropcraft_core.observe import NO_SURFACE_WARN, coverage_warning, no_surface_fraction

    d = np.ones((4, 10))
    d[0, :3] = np.nan
    d[1, 0] = np.inf
    assert no_surface_fraction(d) == pytest.approx(4 / 40)
    assert no_surface_fraction(np.zeros((0, 0))) == 0.0
    assert coverage_warning(0.10) is None
    assert coverage_warning(NO_SURFACE_WARN) is None  # the threshold itself passes
    msg = coverage_warning(0.235)
    assert msg is not None and "23.5 % of the row camera's view" in msg and "LAI" in msg
    assert coverage_warning(0.18004).startswith("18.0 % of the row camera's view")  # not "18 %"
    assert "synthetic soybean" in msg and "soybean" not in coverage_warning(0.235, "maize")


def test_a_row_view_the_surfaces_hardly_cover_is_refused():
    """A maize walk round a 1.8 m canopy (tsdf backend) left 97.9 % of the row camera's view
    without a surface, read LAI 0.069 for 1.79 and finished "done" with only the coverage
    warning (session 96's capture audit): over 90 % the observe stage refuses, naming the
    share and the capture."""
    from cropcraft_core.observe import NO_SURFACE_REFUSE, check_coverage
    from cropcraft_core.surfaces.base import SurfacesError

    check_coverage(0.5)
    check_coverage(NO_SURFACE_REFUSE)  # the threshold itself passes
    with pytest.raises(SurfacesError, match=r"covers only 2.1 % of the row camera's view \(97.9 %"):
        check_coverage(0.979)
    with pytest.raises(SurfacesError, match="from a drone"):
        check_coverage(0.95)
