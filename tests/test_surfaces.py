"""Visible-surfaces stage: tsdf (CPU MVS + TSDF) and points (the same stereo, visibility-filtered
and splatted) on a small posed synthetic scene, truth backend,
save/load, config errors, nerfacto availability."""

from __future__ import annotations

import copy
import json
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from cropcraft_core.config.layout import CanopyLayout
from cropcraft_core.errors import ConfigError, InputError
from cropcraft_core.geometry.camera import PinholeCamera
from cropcraft_core.procedural.canopy import generate_canopy
from cropcraft_core.render.raster import render_depth
from cropcraft_core.surfaces import (
    SurfacesConfig,
    SurfacesError,
    load_surfaces,
    make_backend,
)


def _texture(p: np.ndarray, cell: float = 0.025) -> np.ndarray:
    """(n,) brightness in [0.6, 1.4] anchored to 3D points (n, 3): the same in every view."""
    k = np.floor(p / cell).astype(np.int64)
    x = (k[:, 0] * 73856093) ^ (k[:, 1] * 19349663) ^ (k[:, 2] * 83492791)
    x = (x ^ (x >> 13)) * 1274126177
    return 0.6 + 0.8 * ((x >> 8) & 1023) / 1023.0


def _view(mesh, cam: PinholeCamera) -> tuple[np.ndarray, np.ndarray]:
    """((H, W, 3) uint8 image, (H, W) float32 true depth incl. the ground z = 0)."""
    res = render_depth(mesh.vertices, mesh.faces, cam)
    depth = res.depth.astype(np.float64)
    d = cam.ray_directions(normalized=False)
    ground = ~np.isfinite(depth) & (d[..., 2] < 0)
    depth[ground] = (-cam.center[2] / d[..., 2])[ground]
    pts = cam.unproject(np.where(np.isfinite(depth), depth, 0.0)).reshape(-1, 3)
    leaf = np.isfinite(res.depth).reshape(-1)
    base = np.where(leaf[:, None], [60, 140, 45], [125, 88, 60]).astype(np.float64)
    rgb = base * _texture(pts)[:, None]
    rgb[~np.isfinite(depth).reshape(-1)] = [170, 190, 220]
    return np.clip(rgb, 0, 255).astype(np.uint8).reshape(*depth.shape, 3), depth


def _arc(
    n: int, radius: float, height: float, arc_deg: float = 135.0, size=(320, 240)
) -> list[PinholeCamera]:
    """n cameras on an arc of ``arc_deg`` around the plot, looking at its centre."""
    cams = []
    for i in range(n):
        a = math.radians(-90.0 - arc_deg / 2 + arc_deg * i / (n - 1))
        c = np.array([radius * math.cos(a), radius * math.sin(a), height])
        f = np.array([0.0, 0.0, 0.15]) - c
        f /= np.linalg.norm(f)
        r = np.cross(f, [0.0, 0.0, 1.0])
        r /= np.linalg.norm(r)
        m = np.eye(4)
        m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = r, np.cross(f, r), f, c
        cams.append(PinholeCamera.from_vfov(size[0], size[1], 55.0, m))
    return cams


@pytest.fixture(scope="module")
def scene():
    layout = CanopyLayout(plot_length=1.0, plot_width=1.0, margin=0.4)
    mesh = generate_canopy("soybean", {}, layout, seed=3).mesh
    cams = _arc(14, 1.1, 1.5)
    views = [_view(mesh, c) for c in cams]
    bbox = np.array([[-0.9, -0.9, -0.05], [0.9, 0.9, 1.2]])
    return mesh, cams, [v[0] for v in views], bbox


@pytest.fixture(scope="module")
def fitted(scene):
    mesh, cams, imgs, bbox = scene
    cfg = SurfacesConfig(n_depths=64, mvs_scale=0.5, voxel_size=0.01)
    b = make_backend(cfg)
    b.fit(imgs, cams, bbox)
    return b


def test_tsdf_renders_new_downward_view(scene, fitted):
    mesh, *_ = scene
    cam = PinholeCamera.look_down(height_m=1.2, size=(200, 150))
    depth, rgb = fitted.render(cam)
    truth = make_backend(SurfacesConfig(backend="truth"), mesh=mesh)
    d_true, _ = truth.render(cam)
    both = np.isfinite(depth) & np.isfinite(d_true)
    # measured (horizontal sweep, RGB, 5×5, voxel 7.5 mm): 63 % both hit, median error 16 mm
    assert both.mean() > 0.5, f"the fused surface covers only {both.mean():.0%} of the view"
    err = np.median(np.abs(depth[both] - d_true[both]))
    assert err < 0.025, f"median depth error {err:.3f} m"
    assert depth.dtype == np.float32 and rgb.dtype == np.uint8 and rgb.shape == (150, 200, 3)


@pytest.mark.parametrize("heights", [None, (-0.1, 0.9)])
def test_sweep_plane_homography_maps_plane_points(scene, heights):
    """Every plane hypothesis (fronto-parallel or horizontal z = h): a reference pixel's point on
    the plane (``plane_depth``) projects into the source where the plane's homography sends it."""
    from cropcraft_core.surfaces.tsdf import plane_depth, plane_homography, sweep_planes

    _, cams, _, _ = scene
    ref, src = cams[3], cams[5]
    normals, offsets, params = sweep_planes(ref, 9, 0.8, 3.0, heights)
    px = np.array([[10.5, 20.5], [160.5, 120.5], [300.5, 200.5]])  # PinholeCamera pixel coords
    for nv, o, q in zip(normals, offsets, params, strict=True):
        full = plane_depth(ref, np.full((ref.height, ref.width), q), heights is not None)
        d = full[px[:, 1].astype(int), px[:, 0].astype(int)]
        pts = ref.unproject(np.where(np.isfinite(full), full, 0.0))
        pts = pts[px[:, 1].astype(int), px[:, 0].astype(int)]
        if heights is not None:
            np.testing.assert_allclose(pts[np.isfinite(d), 2], q, atol=1e-5)  # float32 depth
        uv, _ = src.project(pts)
        hom = plane_homography(ref, src, nv, o)
        a = np.c_[px - 0.5, np.ones(3)] @ hom.T  # OpenCV index coordinates
        ok = np.isfinite(d)
        np.testing.assert_allclose((a[:, :2] / a[:, 2:] + 0.5)[ok], uv[ok], rtol=0, atol=1e-3)


def test_fewer_best_sources_match_what_most_sources_cannot_see(scene):
    """``best_sources``: a plane's score is the mean NCC of that many best sources. With three
    of four sources blind to the reference (noise images), the best half always averages one
    blind source in, so fewer true depths reach the NCC threshold than from the best one
    source; with every source seeing, the best one finds about as many as the best half.
    (Measured: 15 % against 26 % of the view with three blind, 45 % both with none.)"""
    from cropcraft_core.surfaces.tsdf import best_of, plane_sweep, to_grey

    assert [best_of(4, 0), best_of(3, 0), best_of(4, 1), best_of(2, 3), best_of(1, 0)] == [
        2,
        2,
        1,
        2,
        1,
    ]
    mesh, cams, imgs, bbox = scene
    ref, srcs = 6, [4, 5, 7, 8]
    small = [c.scaled(0.5) for c in cams]
    grey = [to_grey(im, c, 0.5) for im, c in zip(imgs, cams, strict=True)]
    _, d_true = _view(mesh, small[ref])
    found = {}
    for n_blind in (0, 3):
        rng = np.random.default_rng(0)
        views = [
            grey[j] if k >= n_blind else rng.random(grey[j].shape, np.float32)
            for k, j in enumerate(srcs)
        ]
        for best in (0, 1):
            depth, score = plane_sweep(
                grey[ref], small[ref], views, [small[j] for j in srcs], 0.5, 3.0, 64, 5,
                0.05, 0.3, (bbox[0, 2], bbox[1, 2]), best,
            )  # fmt: skip
            ok = (score >= 0.4) & (np.abs(depth - d_true) < 0.02 * d_true)
            found[n_blind, best] = float(ok.mean())
    assert found[3, 1] > 0.2 and found[3, 1] > 1.4 * found[3, 0], found
    assert found[0, 1] > 0.9 * found[0, 0], found


def test_shiftable_windows_find_more_true_depths_beside_depth_edges():
    """``shiftable``: a pixel's score is the best of the windows that contain it. On a dense
    canopy (LAI about 3.7: low leaves seen through small gaps), more pixels beside a depth jump
    (one of its 3 × 3 neighbours 10 % nearer or farther) get their true depth than with the
    centred window alone, and the view as a whole gains too. (Measured at 0.75 × 320×240, within
    2 % of the true depth: beside the jumps 0.28 → 0.33, the whole view 0.46 → 0.51.) The best of
    25 windows scores higher, so the NCC threshold drops less: 85 % of the view reaches 0.4
    without, 98 % with. What it costs, leaves fattened beside their own edges, shows in the
    fused row view and the fits (RESULTS, *Shiftable windows*), which is why it is off."""
    import cv2

    from cropcraft_core.surfaces.tsdf import plane_sweep, to_colour

    layout = CanopyLayout(plot_length=1.0, plot_width=1.0, margin=0.4)
    dense = {"leaf_length": 1.1, "internode_length": 1.5, "num_nodes": 11}
    mesh = generate_canopy("soybean", dense, layout, seed=4).mesh
    cams = _arc(14, 1.1, 1.5)
    ref, srcs = 6, [4, 5, 7, 8]
    small = {j: cams[j].scaled(0.75) for j in [ref, *srcs]}
    col = {j: to_colour(_view(mesh, cams[j])[0], cams[j], 0.75) for j in small}
    _, d_true = _view(mesh, small[ref])
    d32 = d_true.astype(np.float32)
    k = np.ones((3, 3), np.uint8)
    edge = (cv2.dilate(d32, k) - cv2.erode(d32, k)) > 0.1 * d32
    assert 0.3 < edge.mean() < 0.8  # measured 0.55
    good, kept = {}, {}
    for shift in (False, True):
        depth, score = plane_sweep(
            col[ref], small[ref], [col[j] for j in srcs], [small[j] for j in srcs], 0.5, 3.0,
            128, 5, 0.05, 0.3, (-0.05, 1.2), 0, shift,
        )  # fmt: skip
        ok = (score >= 0.25) & (np.abs(depth - d_true) < 0.02 * d_true)
        good[shift] = (float(ok[edge].mean()), float(ok.mean()))
        kept[shift] = float((score >= 0.4).mean())
    assert good[True][0] > 1.1 * good[False][0], good
    assert good[True][1] > 1.04 * good[False][1], good
    assert kept[True] > kept[False], kept


def test_a_photo_that_sees_the_box_but_not_the_canopys_slab_keeps_its_whole_box_depths():
    """The sweep cuts the box to the heights the scene occupies; a photo at the edge of a low
    nadir capture saw the whole box's soil but not that slab, and its depth limits stopped the
    run ("the camera at ... does not see the bounding box": a phone held 1.7 m over soybean,
    200 photos through SfM, session 97). It keeps its limits in the whole box; the others
    take the slab's."""
    from cropcraft_core.geometry.camera import PinholeCamera
    from cropcraft_core.surfaces.tsdf import cut_box_limits, depth_limits

    box = np.array([[-1.5, -1.5, -1.5], [1.5, 1.5, 1.5]])
    slab = box.copy()
    slab[:, 2] = (-0.28, 0.9)
    edge = PinholeCamera.look_down((-3.0, 0.0), 1.7, size=(64, 48), vfov_deg=50.0)
    inside = PinholeCamera.look_down((0.0, 0.0), 1.7, size=(64, 48), vfov_deg=50.0)
    before = [depth_limits(c, box, None) for c in (edge, inside)]
    with pytest.raises(InputError, match="does not see the bounding box"):
        depth_limits(edge, slab, None)
    limits = cut_box_limits([edge, inside], slab, None, before)
    assert limits[0] == before[0]
    assert limits[1] == depth_limits(inside, slab, None) != before[1]


def test_sweep_spans_the_heights_the_scene_occupies_not_the_box(scene, monkeypatch):
    """A box reaching 1.2 m below the ground (as soybean's does, for SfM that saw no soil): the
    coarse pass finds the soil and the canopy top, and the main pass's planes span about that,
    not the box; without a soil layer the range starts at the box's bottom."""
    from cropcraft_core.surfaces import tsdf
    from cropcraft_core.surfaces.tsdf import occupied_heights, select_neighbours, stereo_depth_maps

    mesh, cams, imgs, bbox = scene
    box = bbox.copy()
    box[0, 2] = -1.2
    cfg = SurfacesConfig(n_depths=64, mvs_scale=0.5, sweep_heights="auto")
    nbrs = select_neighbours(cams, cfg.neighbours, box)
    limits = [tsdf.depth_limits(c, box, None) for c in cams]
    lo, hi = occupied_heights(imgs, cams, nbrs, limits, box, cfg, lambda *_: None)
    top = float(mesh.vertices[:, 2].max())
    # 32 planes over 2.4 m in the pass: a margin of three spacings (0.23 m) below the soil
    assert -0.3 < lo < -0.1 and top < hi <= box[1, 2], (lo, hi, top)
    st = stereo_depth_maps(imgs, cams, box, cfg, lambda *_: None)
    assert st.heights == (lo, hi) and st.timings()["sweep_range"] > 0
    boxed = stereo_depth_maps(imgs, cams, box, replace(cfg, sweep_heights="box"), lambda *_: None)
    assert boxed.heights == (-1.2, box[1, 2])
    # the planes over the scene keep more consistent depths (measured: 0.46 against 0.40)
    assert st.timings()["valid_fraction"] > boxed.timings()["valid_fraction"]
    monkeypatch.setattr(tsdf, "SOIL_MIN_POINTS", 10**9)
    lo2, hi2 = occupied_heights(imgs, cams, nbrs, limits, box, cfg, lambda *_: None)
    assert lo2 == -1.2 and hi2 == hi


_SWEEP_ONCE = """
import sys
import numpy as np
from cropcraft_core.surfaces import tsdf
rng = np.random.default_rng(0)
h, w, n_s, n_d, n_c = 96, 128, 3, 16, 3
ref = rng.random((n_c, h, w), dtype=np.float32)
srcs = rng.random((n_s, n_c, h, w), dtype=np.float32)
jitter = np.array([[1, 1, 100], [1, 1, 100], [1e-3, 1e-3, 0]])
homs = np.eye(3) + rng.normal(0, 0.01, (n_d, n_s, 3, 3)) * jitter
out = np.empty((h, w, n_d), np.float32)
tsdf._sweep_ncc(ref, srcs, np.array([[h, w]] * n_s, np.int64), homs, 3, 0, 2, out)
np.save(sys.argv[1], out)
"""


def test_stereo_scores_are_the_same_compiled_fresh_or_loaded_from_the_cache(tmp_path):
    """A scene's first reconstruction on a machine compiles the stereo kernel; every later run
    loads it from numba's cache. Both must score to the bit alike, or the first night's answer
    differs from its reruns (with fastmath the two differed in the last bits; RESULTS
    #compile-state). Two processes share an empty cache folder: the first compiles, the second
    loads."""
    import os
    import subprocess
    import sys

    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "numba")}
    root = Path(__file__).resolve().parent.parent
    outs = []
    for run in ("fresh", "cached"):
        out = tmp_path / f"{run}.npy"
        subprocess.run([sys.executable, "-c", _SWEEP_ONCE, str(out)], env=env, cwd=root, check=True)
        outs.append(np.load(out))
    assert any((tmp_path / "numba").rglob("*_sweep_ncc*.nbc")), "the first run cached nothing"
    assert np.array_equal(outs[0], outs[1])


def _sweep_ncc_by_definition(ref, srcs, homs, half, m_best):
    """The plane sweep's matching score written out plainly (numpy, one plane, source, channel
    and window at a time): each source warped bilinearly where the plane's pixel maps inside it
    (0 elsewhere), the NCC of every clipped window, the channels' mean, -1 where the source does
    not see the pixel, and per pixel the mean of the best ``m_best`` sources."""
    n_c, h, w = ref.shape
    n_d, n_s = homs.shape[:2]
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    out = np.empty((h, w, n_d))
    for k in range(n_d):
        per_source = np.empty((n_s, h, w))
        for s in range(n_s):
            m = homs[k, s]
            hs, ws = srcs.shape[2:]
            pz = m[2, 0] * xs + m[2, 1] * ys + m[2, 2]
            u = (m[0, 0] * xs + m[0, 1] * ys + m[0, 2]) / pz
            v = (m[1, 0] * xs + m[1, 1] * ys + m[1, 2]) / pz
            seen = (pz > 1e-9) & (u >= 0) & (v >= 0) & (u <= ws - 1) & (v <= hs - 1)
            x0 = np.clip(np.where(seen, u, 0).astype(int), 0, ws - 2)
            y0 = np.clip(np.where(seen, v, 0).astype(int), 0, hs - 2)
            fx, fy = np.where(seen, u - x0, 0), np.where(seen, v - y0, 0)
            img = srcs[s].astype(np.float64)
            warped = (
                img[:, y0, x0] * (1 - fx) * (1 - fy) + img[:, y0, x0 + 1] * fx * (1 - fy)
                + img[:, y0 + 1, x0] * (1 - fx) * fy + img[:, y0 + 1, x0 + 1] * fx * fy
            ) * seen  # fmt: skip
            score = np.zeros((h, w))
            for y in range(h):
                for x in range(w):
                    win = np.s_[:, max(0, y - half) : y + half + 1, max(0, x - half) : x + half + 1]
                    r, q = ref[win].reshape(n_c, -1), warped[win].reshape(n_c, -1)
                    vr = np.maximum(r.var(axis=1) + 1e-5, 1e-5)
                    vq = np.maximum(q.var(axis=1) + 1e-5, 1e-5)
                    cov = (r * q).mean(axis=1) - r.mean(axis=1) * q.mean(axis=1)
                    score[y, x] = np.mean(cov / np.sqrt(vr * vq))
            per_source[s] = np.where(seen, score, -1.0)
        out[..., k] = np.sort(per_source, axis=0)[::-1][:m_best].mean(axis=0)
    return out


@pytest.mark.parametrize("n_c, h, w", [(3, 17, 23), (1, 9, 4)])
def test_sweep_scores_are_the_windowed_ncc_by_its_definition(n_c, h, w):
    """The streamed kernel (rows warped, column sums, running sums along the row) scores what
    its definition does, at the clipped windows of the border, where a source sees only part of
    a window, and on an image narrower than the window."""
    from cropcraft_core.surfaces import tsdf

    rng = np.random.default_rng(3)
    n_s, n_d, half, m_best = 3, 4, 2, 2
    ref = rng.random((n_c, h, w), dtype=np.float32)
    srcs = rng.random((n_s, n_c, h, w), dtype=np.float32)
    homs = np.tile(np.eye(3), (n_d, n_s, 1, 1))
    homs[..., 0, 2] = rng.uniform(-4, 4, (n_d, n_s))  # shifts: part of each view falls outside
    homs[..., 1, 2] = rng.uniform(-3, 3, (n_d, n_s))
    homs[..., :2, :2] += rng.normal(0, 0.03, (n_d, n_s, 2, 2))
    homs[..., 2, :2] = rng.normal(0, 0.002, (n_d, n_s, 2))
    for s in range(n_s):  # on plane 0 each source sees the reference moved by (s, 1) pixels
        srcs[s, :, 1:, s:] = ref[:, : h - 1, : w - s]
        homs[0, s] = [[1, 0, s], [0, 1, 1], [0, 0, 1]]
    out = np.empty((h, w, n_d), np.float32)
    tsdf._sweep_ncc(ref, srcs, np.array([[h, w]] * n_s, np.int64), homs, half, 0, m_best, out)
    want = _sweep_ncc_by_definition(ref, srcs, homs, half, m_best)
    assert (want == -1).any() and (want[..., 0] > 0.99).any()  # unseen pixels, true matches
    np.testing.assert_allclose(out, want, rtol=0, atol=2e-5)


def test_soil_height_is_the_layer_where_soil_points_pile_up_or_none():
    from cropcraft_core.surfaces.tsdf import soil_height

    rng = np.random.default_rng(0)
    tail = rng.uniform(-1.2, 1.0, 3000)  # wrong matches and brownish stems at every height
    ground = rng.normal(-0.40, 0.01, 600)  # a soil layer (levelling's ground on the leaves)
    assert soil_height(np.r_[tail, ground], -1.2, 1.2) == pytest.approx(-0.40, abs=0.02)
    assert soil_height(tail, -1.2, 1.2) is None  # no layer stands out
    assert soil_height(ground[:50], -1.2, 1.2) is None  # too few points
    # wrong matches dense enough that three bins hold SOIL_MIN_POINTS (the default canopy's
    # coarse pass: ~45 per 2 cm bin down to the box's bottom): the lowest bins have no bins
    # under them to stand out against, so they are not a layer (they once were: the sweep
    # then started at the box's bottom, 1.2 m under the soil)
    dense = rng.uniform(-1.2, 1.0, 5000)
    assert soil_height(np.r_[dense, ground], -1.2, 1.2) == pytest.approx(-0.40, abs=0.02)
    assert soil_height(dense, -1.2, 1.2) is None
    # a box whose bottom lies within SOIL_BELOW_M of the soil leaves no reference: no layer,
    # and the sweep starts at that (tight) bottom
    assert soil_height(np.r_[dense[dense > -0.5], ground], -0.5, 1.2) is None


def test_point_cloud_coloured(fitted):
    pts, cols = fitted.point_cloud(5000)
    assert 1000 <= len(pts) <= 5000 and cols.shape == pts.shape
    assert np.all((cols >= 0) & (cols <= 1))
    assert np.all((pts >= fitted.bbox[0] - 0.03) & (pts <= fitted.bbox[1] + 0.03))
    green = (cols[:, 1] > cols[:, 0]) & (cols[:, 1] > cols[:, 2])
    brown = (cols[:, 0] > cols[:, 1]) & (cols[:, 1] > cols[:, 2])
    assert green.mean() > 0.2 and brown.mean() > 0.05
    assert (green | brown).mean() > 0.85


def test_point_cloud_size_must_be_a_whole_number(fitted):
    for bad in (50.0, -1, True):
        with pytest.raises(ConfigError, match="n_max must be a whole number"):
            fitted.point_cloud(bad)


def test_save_load_round_trip(fitted, tmp_path):
    fitted.save(tmp_path / "s")
    again = load_surfaces(tmp_path / "s")
    cam = PinholeCamera.look_down(height_m=1.0, size=(120, 90))
    d0, c0 = fitted.render(cam)
    d1, c1 = again.render(cam)
    np.testing.assert_array_equal(d0, d1)
    np.testing.assert_array_equal(c0, c1)
    assert len(again.cameras) == len(fitted.cameras)
    assert len(again.fill_faces) == len(fitted.fill_faces) > 0


def test_a_damaged_saved_surface_is_named(fitted, tmp_path):
    """A saved surface whose surfaces.json or mesh was damaged is an InputError naming the
    file, not a raw KeyError or an empty surface that renders nothing."""
    import json

    from cropcraft_core.errors import InputError

    folder = fitted.save(tmp_path / "s")
    meta = json.loads((folder / "surfaces.json").read_text())
    for damaged, match in (
        ([1, 2], "surfaces.json is damaged: a list"),
        ({k: v for k, v in meta.items() if k != "cameras"}, "surfaces.json is damaged: KeyError"),
        ({**meta, "payload": None, "cameras": []}, "surfaces.json is damaged: it holds no"),
        ({**meta, "bbox": [[1, 1, 1], [0, 0, 0]]}, "surfaces.json is damaged: bbox"),
    ):
        (folder / "surfaces.json").write_text(json.dumps(damaged))
        with pytest.raises(InputError, match=match):
            load_surfaces(folder)
    (folder / "surfaces.json").write_text(json.dumps(meta))
    mesh = next(p for p in folder.iterdir() if p.suffix == ".ply")
    data = bytearray(mesh.read_bytes())
    data[-12:-8] = (10**8).to_bytes(4, "little")  # the last face's first vertex index
    mesh.write_bytes(bytes(data))
    with pytest.raises(InputError, match="surface files are not the ones surfaces.json records"):
        load_surfaces(folder)
    unhashed = {k: v for k, v in meta.items() if k != "files_sha256"}  # as saved before them
    (folder / "surfaces.json").write_text(json.dumps(unhashed))
    with pytest.raises(InputError, match="faces index vertices outside"):
        load_surfaces(folder)


def test_a_save_over_an_earlier_one_stopped_before_its_record_is_refused(scene, fitted, tmp_path):
    """Saved into a folder that holds another save, the mesh was replaced before surfaces.json:
    stopped between the two, the folder loaded as one save's mesh under the other's cameras,
    box and config."""
    from cropcraft_core.errors import InputError

    mesh, cams, imgs, bbox = scene
    folder = fitted.save(tmp_path / "s")
    first = (folder / "surfaces.json").read_text()
    other = make_backend(SurfacesConfig(n_depths=32, mvs_scale=0.5, voxel_size=0.01))
    other.fit(imgs[:4], cams[:4], bbox)
    other.save(folder)
    (folder / "surfaces.json").write_text(first)  # as the stopped save left it
    with pytest.raises(InputError, match="a save over an earlier one stopped"):
        load_surfaces(folder)
    other.save(folder)
    assert len(load_surfaces(folder).cameras) == 4


def test_a_failed_fit_leaves_no_fitted_surface(scene, tmp_path):
    """A fit that finds no surface raises and leaves the backend unfitted: nothing to save."""
    mesh, cams, imgs, bbox = scene
    b = make_backend(SurfacesConfig(n_depths=16, mvs_scale=0.25, weight_threshold=1e9))
    with pytest.raises(SurfacesError, match="found no consistent surface"):
        b.fit(imgs[:4], cams[:4], bbox)
    assert not b.fitted
    with pytest.raises(SurfacesError, match="not fitted"):
        b.save(tmp_path / "s")
    assert not (tmp_path / "s").exists()


def test_one_view_fill_closes_holes_behind_the_two_view_surface(scene, fitted):
    """The fill mesh holds only faces the two-view mesh lacks and is rendered only where that
    mesh (alone: ``render_supported``) leaves a ray empty; save/load keeps it
    (test_save_load_round_trip)."""
    import dataclasses

    from cropcraft_core.surfaces.tsdf import faces_shared

    assert len(fitted.fill_faces) > 0
    assert not faces_shared(
        fitted.fill_vertices, fitted.fill_faces, fitted.vertices, fitted.faces
    ).any()
    mesh, *_ = scene
    cam = PinholeCamera.look_down(height_m=1.2, size=(200, 150))
    depth, rgb = fitted.render(cam)
    plain = make_backend(dataclasses.replace(fitted.config, fill_one_view=False))
    plain.bbox, plain.cameras = fitted.bbox, fitted.cameras
    plain._set_mesh(fitted.vertices, fitted.faces, fitted.vertex_colors)
    d0, c0 = plain.render(cam)
    two = np.isfinite(d0)
    np.testing.assert_array_equal(fitted.render_supported(cam), d0)  # the coverage figure's
    np.testing.assert_array_equal(depth[two], d0[two])  # the two-view surface wins
    np.testing.assert_array_equal(rgb[two], c0[two])
    filled = np.isfinite(depth) & ~two
    assert filled.sum() > 0.01 * depth.size
    d_true, _ = make_backend(SurfacesConfig(backend="truth"), mesh=mesh).render(cam)
    # where the fill shows a surface above the ground, the true canopy has one (measured: 60 %
    # of those pixels; the rest are leaf edges' one-view skirts over soil)
    z = cam.unproject(np.where(filled, depth, 1.0))[..., 2]
    z_true = cam.unproject(np.where(np.isfinite(d_true), d_true, 1.0))[..., 2]
    raised = filled & (z >= 0.05)
    assert (raised & (z_true >= 0.05)).sum() > 0.5 * raised.sum()


def _quad(x0: float, x1: float, y0: float, y1: float, z: float) -> tuple[np.ndarray, np.ndarray]:
    v = np.array([[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]], np.float64)
    return v, np.array([[0, 1, 2], [0, 2, 3]], np.int64)


def _merge(*quads):
    vs, fs, n = [], [], 0
    for v, f in quads:
        vs.append(v)
        fs.append(f + n)
        n += len(v)
    return np.concatenate(vs), np.concatenate(fs)


def test_carving_removes_what_other_views_see_past_and_keeps_what_they_see():
    """Twelve views of the soil (z = 0) with a real plate at 0.3 m; three neighbouring views'
    depth maps also hold a phantom plate at 0.3 m over bare soil (a leaf edge stretched by the
    matching window) that the other nine see past. Fused as before, the phantom is a two-view
    surface and the row view shows it; with ``carve_free_space`` the others' free space removes
    it, and the real plate and the soil stay where they were."""
    soil = _quad(-1.5, 1.5, -1.5, 1.5, 0.0)
    plate = _quad(-0.35, -0.05, -0.15, 0.15, 0.3)
    phantom = _quad(0.1, 0.35, -0.15, 0.15, 0.3)
    cams = _arc(12, 1.1, 1.5, arc_deg=300.0)
    scene_v, scene_f = _merge(soil, plate)
    depths = [render_depth(scene_v, scene_f, c).depth for c in cams]
    ph_v, ph_f = _merge(soil, plate, phantom)
    for i in (0, 1, 2):  # neighbouring views fattened the same way: a two-view surface
        depths[i] = render_depth(ph_v, ph_f, cams[i]).depth
    grey = [np.full((c.height, c.width, 3), 128, np.uint8) for c in cams]
    box = np.array([[-0.8, -0.8, -0.05], [0.8, 0.8, 0.6]])
    limits = [(0.3, 4.0)] * len(cams)
    look = PinholeCamera.look_down(height_m=1.2, size=(160, 120))
    where = {"plate": (-0.2, 0.0), "phantom": (0.22, 0.0), "soil": (0.0, 0.35)}
    pix = {
        k: look.project(np.array([[x, y, 0.3]]))[0][0].astype(int) for k, (x, y) in where.items()
    }
    heights = {}
    for carve in (False, True):
        b = make_backend(SurfacesConfig(carve_free_space=carve))
        b.bbox, b.cameras = box, cams
        b._fuse(grey, cams, depths, limits)
        d, _ = b.render(look)
        z = look.unproject(np.where(np.isfinite(d), d, 0.0))[..., 2]
        heights[carve] = {k: z[v, u] for k, (u, v) in pix.items()}
    assert heights[False]["phantom"] == pytest.approx(0.3, abs=0.02)  # the fattened edge
    assert heights[True]["phantom"] == pytest.approx(0.0, abs=0.02)  # carved: the soil
    for carve in (False, True):
        assert heights[carve]["plate"] == pytest.approx(0.3, abs=0.02)
        assert heights[carve]["soil"] == pytest.approx(0.0, abs=0.02)


def test_surfaces_saved_before_the_fill_load_without_it(fitted, tmp_path):
    """A store's older surfaces (no fill in surfaces.json, no surface_fill.ply) load and render
    their one mesh, as they did when they were made."""
    import json

    folder = fitted.save(tmp_path / "old")
    meta = json.loads((folder / "surfaces.json").read_text())
    assert meta["payload"].pop("fill_mesh") == "surface_fill.ply"
    del meta["payload"]["fill_faces"], meta["config"]["fill_one_view"]
    (folder / "surfaces.json").write_text(json.dumps(meta))
    (folder / "surface_fill.ply").unlink()
    old = load_surfaces(folder)
    cam = PinholeCamera.look_down(height_m=1.0, size=(120, 90))
    assert len(old.fill_faces) == 0
    np.testing.assert_array_equal(old.render(cam)[0], fitted.render_supported(cam))


@pytest.fixture(scope="module")
def fitted_points(scene):
    mesh, cams, imgs, bbox = scene
    b = make_backend(SurfacesConfig(backend="points", n_depths=64, mvs_scale=0.5))
    b.fit(imgs, cams, bbox)
    return b


def test_points_render_new_downward_view_and_round_trip(scene, fitted_points, tmp_path):
    mesh, *_ = scene
    cam = PinholeCamera.look_down(height_m=1.2, size=(200, 150))
    depth, rgb = fitted_points.render(cam)
    d_true, _ = make_backend(SurfacesConfig(backend="truth"), mesh=mesh).render(cam)
    both = np.isfinite(depth) & np.isfinite(d_true)
    # measured: 85 % both hit, median error 23 mm (the tsdf fixture's fit: 73 %, 20 mm)
    assert both.mean() > 0.75, f"the splatted points cover only {both.mean():.0%} of the view"
    err = np.median(np.abs(depth[both] - d_true[both]))
    assert err < 0.03, f"median depth error {err:.3f} m"
    assert depth.dtype == np.float32 and rgb.dtype == np.uint8 and rgb.shape == (150, 200, 3)
    assert fitted_points.timings["visibility"] > 0 and len(fitted_points.depth_maps) == 14

    pts, cols = fitted_points.point_cloud(3000)
    assert len(pts) == 3000 and np.all((cols >= 0) & (cols <= 1))
    assert np.all((pts >= fitted_points.bbox[0]) & (pts <= fitted_points.bbox[1]))

    fitted_points.save(tmp_path / "p")
    again = load_surfaces(tmp_path / "p")
    d1, c1 = again.render(cam)
    np.testing.assert_array_equal(depth, d1)
    np.testing.assert_array_equal(rgb, c1)
    ply = tmp_path / "p" / "points.ply"
    ply.write_bytes(ply.read_bytes()[:-7])
    with pytest.raises(InputError, match="surface files are not the ones surfaces.json records"):
        load_surfaces(tmp_path / "p")
    meta = json.loads((tmp_path / "p" / "surfaces.json").read_text())
    del meta["files_sha256"]  # as saved before the record held them: the reader names it
    (tmp_path / "p" / "surfaces.json").write_text(json.dumps(meta))
    with pytest.raises(InputError, match="points.ply.*truncated"):
        load_surfaces(tmp_path / "p")


def test_points_render_with_the_density_cap_and_load_it_back(fitted_points, tmp_path):
    """``splat_density`` reaches the renderer and is saved with the surfaces: a small cap (a
    fifth of the coverage) leaves more of the view empty than none, and the loaded surfaces
    render the same."""
    import dataclasses

    cam = PinholeCamera.look_down(height_m=1.2, size=(200, 150))
    capped = copy.copy(fitted_points)
    capped.config = dataclasses.replace(fitted_points.config, splat_density=0.2)
    d_capped, _ = capped.render(cam)
    d_free, _ = fitted_points.render(cam)
    assert np.isfinite(d_capped).mean() < np.isfinite(d_free).mean() - 0.05
    capped.save(tmp_path / "c")
    np.testing.assert_array_equal(load_surfaces(tmp_path / "c").render(cam)[0], d_capped)


def _three_down(size=(40, 30)) -> list[PinholeCamera]:
    """Three cameras 1 m above the ground z = 0 looking straight down, 0.2 m apart in x."""
    return [PinholeCamera.look_down((x, 0.0), 1.0, size=size) for x in (0.0, 0.2, -0.2)]


def test_visibility_filter_drops_what_other_views_see_past_and_keeps_the_hidden():
    from cropcraft_core.surfaces.points import visibility_filter

    cams = _three_down()
    ground = [np.ones((30, 40), np.float32) for _ in cams]
    # view 0: a floating point 0.2 m above the ground that the two others see past, and
    # a ground point under a lid that the two others see (0.5 m up) and view 0 does not
    d0 = ground[0].copy()
    d0[15, 20] = 0.8
    lid = [np.full((30, 40), 0.5, np.float32) for _ in cams]
    out = visibility_filter([d0, *ground[1:]], cams, rel=0.01, ratio=0.25)
    assert np.isnan(out[0][15, 20])
    assert np.isfinite(out[0]).sum() == 30 * 40 - 1  # the ground the others agree with stays
    hidden = visibility_filter([ground[0], *lid[1:]], cams, rel=0.01, ratio=0.25)
    np.testing.assert_array_equal(hidden[0], ground[0])  # hidden from both: nothing says no
    # one view agreeing and one seeing past: dropped at a ratio below 1, kept at 1
    d2 = ground[2].copy()
    uv, _ = cams[2].project(cams[0].unproject(d0)[15:16, 20])
    d2[int(uv[0, 1]), int(uv[0, 0])] = 0.8
    for ratio, kept in ((0.25, False), (1.0, True)):
        out = visibility_filter([d0, ground[1], d2], cams, rel=0.01, ratio=ratio)
        assert np.isfinite(out[0][15, 20]) == kept


def test_consistency_with_colour_drops_a_leaf_pixel_that_matched_the_soil_beside_it():
    from cropcraft_core.surfaces.tsdf import consistency_count

    cams = _three_down()
    ground = [np.ones((30, 40), np.float32) for _ in cams]
    soil = [np.full((30, 40), 8.0, np.float32) for _ in cams]  # a* of brown soil
    # view 0 sees a thin leaf (green, a* -20) at a few pixels, but its stereo put the soil's
    # depth there (the window matched the soil beside the leaf); the others see that soil
    a0 = soil[0].copy()
    a0[14:16, 19:22] = -20.0
    a_star = [a0, soil[1], soil[2]]
    geometric = consistency_count(ground, cams, 0, [1, 2], 0.01)
    # geometry alone agrees with the leaf's pixels (the others see that soil too)
    assert (geometric[14:16, 19:22] == 2).all()
    coloured = consistency_count(ground, cams, 0, [1, 2], 0.01, a_star, 10.0)
    assert (coloured[14:16, 19:22] == 0).all()
    outside = np.ones((30, 40), bool)
    outside[14:16, 19:22] = False
    np.testing.assert_array_equal(coloured[outside], geometric[outside])
    # a leaf the others see in green where the depth puts it keeps its agreement; within the
    # tolerance counts, past it does not
    leaf_everywhere = [a0, np.full((30, 40), -20.0, np.float32), soil[2]]
    both = consistency_count(ground, cams, 0, [1, 2], 0.01, leaf_everywhere, 10.0)
    assert (both[14:16, 19:22] == 1).all()
    wide = consistency_count(ground, cams, 0, [1, 2], 0.01, a_star, 28.0)
    np.testing.assert_array_equal(wide, geometric)


def test_stereo_with_colour_consistency_keeps_fewer_leaf_pixels_on_the_soil(scene):
    """Through the stereo stage: with the colour check the filtered maps are a subset of the
    geometric ones, and the leaf-coloured pixels holding a depth on the soil (a window that
    matched the soil beside a leaf) lose more of their share than the rest."""
    from cropcraft_core.rowfit.lab import srgb_to_lab
    from cropcraft_core.surfaces.tsdf import stereo_depth_maps, to_colour

    _, cams, imgs, bbox = scene
    cams, imgs = cams[3:11], imgs[3:11]  # 8 of the 14: half the seconds
    cfg = SurfacesConfig(n_depths=32, mvs_scale=0.5)
    plain = stereo_depth_maps(imgs, cams, bbox, cfg, lambda *_: None)
    tol = replace(cfg, consistency_a_tol=10.0)
    coloured = stereo_depth_maps(imgs, cams, bbox, tol, lambda *_: None)
    on_soil = {"plain": 0, "coloured": 0}
    kept = {"plain": 0, "coloured": 0}
    for i, cam in enumerate(plain.cameras):
        p, c = plain.filtered[i], coloured.filtered[i]
        np.testing.assert_array_equal(np.isfinite(c), np.isfinite(c) & np.isfinite(p))
        np.testing.assert_array_equal(c[np.isfinite(c)], p[np.isfinite(c)])
        leaf = srgb_to_lab(to_colour(imgs[i], cams[i], 0.5), 1.0)[..., 1] < -10
        for name, d in (("plain", p), ("coloured", c)):
            z = cam.unproject(np.where(np.isfinite(d), d, 0.0))[..., 2]
            kept[name] += int(np.isfinite(d).sum())
            on_soil[name] += int((leaf & np.isfinite(d) & (z < 0.01)).sum())
    # measured: leaf pixels on the soil 346 -> 111, all kept depths 68,806 -> 55,606
    assert kept["coloured"] < kept["plain"]
    assert on_soil["plain"] > 0
    assert on_soil["coloured"] / on_soil["plain"] < 0.5 * kept["coloured"] / kept["plain"], (
        on_soil,
        kept,
    )


def test_colour_consistency_setting_is_checked():
    assert SurfacesConfig(consistency_a_tol=None).consistency_a_tol is None
    assert SurfacesConfig(consistency_a_tol=10).consistency_a_tol == 10
    for bad in (0, -3.0, float("nan"), float("inf"), "ten", True):
        with pytest.raises(ConfigError, match="consistency_a_tol must be a positive number"):
            SurfacesConfig(consistency_a_tol=bad)


def test_splat_renders_a_grid_of_points_as_a_closed_surface():
    from cropcraft_core.surfaces.points import splat

    s = 0.004
    g = np.arange(-0.3, 0.3, s)
    xy = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    pts = np.c_[xy, np.zeros(len(xy))]
    pts[xy[:, 0] > 0, 2] = 0.1  # a step: the half at x > 0 is 0.1 m higher
    cols = np.where(xy[:, :1] > 0, [[0, 200, 0]], [[150, 90, 60]]).astype(np.uint8)
    cam = PinholeCamera.look_down(height_m=1.0, size=(120, 90), vfov_deg=20.0)
    d, rgb = splat(pts, cols, np.full(len(pts), 0.71 * s), cam, blend=0.02, close=5)
    assert np.isfinite(d).all()  # the grid covers the view, the splats close it
    left, right = cam.unproject(d)[..., 0] < -0.01, cam.unproject(d)[..., 0] > 0.01
    np.testing.assert_allclose(d[left], 1.0, atol=1e-5)
    np.testing.assert_allclose(d[right], 0.9, atol=1e-5)
    assert (rgb[right] == [0, 200, 0]).all() and (rgb[left] == [150, 90, 60]).all()
    # far from the grid nothing is seen
    d_off, _ = splat(pts + [5.0, 0, 0], cols, np.full(len(pts), 0.71 * s), cam, 0.02, 5)
    assert np.isnan(d_off).all()


def test_density_radii_are_the_spacing_of_the_points_in_the_view():
    from cropcraft_core.surfaces.points import density_radii

    # one point per pixel centre of a 40 × 30 image, then each twice: ρ = 1 and 2 per pixel
    g = np.stack(np.meshgrid(np.arange(40) + 0.5, np.arange(30) + 0.5), -1).reshape(-1, 2)
    one = density_radii(g, (30, 40), coverage=1.0, window=5)
    np.testing.assert_allclose(one, 1 / np.sqrt(np.pi), rtol=1e-5)
    two = density_radii(np.r_[g, g], (30, 40), coverage=1.5, window=5)
    np.testing.assert_allclose(two, 1.5 / np.sqrt(2 * np.pi), rtol=1e-5)
    # a point left of the image takes its row's border pixel's density
    out = density_radii(np.r_[g, [[-3.0, 10.5]]], (30, 40), coverage=1.0, window=5)
    assert out[-1] == pytest.approx(1 / np.sqrt(np.pi), rel=1e-5)


def test_splat_density_keeps_a_patch_from_fattening_by_its_source_footprint():
    """A 20 cm patch of points 4 mm apart (about one a pixel at 1 m) whose source pixels were
    2 cm wide (a far camera): splatted at the footprint it spreads 2 cm past every edge; with
    discs capped at the points' spacing in the view it stays within two pixels of its edges,
    still closed inside. A lone point, far from the others, keeps its footprint."""
    from cropcraft_core.surfaces.points import splat

    s, half, foot = 0.004, 0.1, 0.02
    g = np.arange(-half, half + 1e-9, s)
    xy = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    pts = np.c_[xy, np.zeros(len(xy))]
    cols = np.full((len(pts), 3), 100, np.uint8)
    radii = np.full(len(pts), foot)
    cam = PinholeCamera.look_down(height_m=1.0, size=(120, 90), vfov_deg=20.0)
    pixel = 1.0 / cam.fx
    inner = (np.abs(cam.unproject(np.ones((90, 120)))[..., :2]) < half - pixel).all(-1)

    def extent(density):
        d, _ = splat(pts, cols, radii, cam, 0.02, 5, density=density, window=9)
        seen = np.isfinite(d)
        return np.abs(cam.unproject(d)[..., :2])[seen].max(), seen[inner].all()

    fat, fat_closed = extent(None)
    thin, thin_closed = extent(1.0)
    assert fat_closed and thin_closed
    assert fat > half + 0.75 * foot
    assert thin < half + 2.5 * pixel < half + 0.75 * foot
    # alone in its 9 × 9 pixels its cap is 9 / √π ≈ 5 pixels, more than its 2.5-pixel footprint
    r = np.array([foot / 2])
    lone, _ = splat(np.array([[0.15, 0.0, 0.0]]), cols[:1], r, cam, 0.02, 1, 1.0, 9)
    assert np.isfinite(lone).sum() == pytest.approx(np.pi * (r[0] * cam.fx) ** 2, rel=0.2)


def test_faces_shared_matches_faces_by_vertex_positions():
    from cropcraft_core.surfaces.tsdf import faces_shared

    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [2, 2, 2]], float)
    f = np.array([[0, 1, 2], [1, 3, 2], [2, 3, 4]])
    # the other mesh: the same first face in another vertex order and numbering, the second
    # face's vertices all present but in a different face, and the third face's vertex moved
    vo = np.array([[0, 1, 0], [0, 0, 0], [1, 0, 0], [1, 1, 0], [2, 2, 2.001]], float)
    fo = np.array([[2, 0, 1], [0, 1, 3], [0, 3, 4]])
    assert faces_shared(v, f, vo, fo).tolist() == [True, False, False]
    assert faces_shared(v, f, vo, fo[:0]).tolist() == [False, False, False]


def test_truth_backend_and_round_trip(scene, tmp_path):
    mesh, cams, imgs, bbox = scene
    b = make_backend(SurfacesConfig(backend="truth"), mesh=mesh)
    b.fit(imgs, cams, bbox)
    pts, cols = b.point_cloud(2000)
    assert len(pts) == 2000 and np.all(pts[:, 2] > -0.01)
    b.save(tmp_path / "t")
    cam = PinholeCamera.look_down(height_m=1.0, size=(80, 60))
    np.testing.assert_array_equal(b.render(cam)[0], load_surfaces(tmp_path / "t").render(cam)[0])


def test_unknown_backend_is_config_error():
    with pytest.raises(ConfigError, match="unknown surfaces backend"):
        make_backend(SurfacesConfig(backend="colmap-dense"))
    with pytest.raises(ConfigError):
        make_backend("nope")
    with pytest.raises(ConfigError):
        make_backend(SurfacesConfig(backend="truth"))  # no mesh


@pytest.mark.parametrize(
    "bad, match",
    [
        ({"splat_density": 0.0}, "splat_density must be a positive number or null"),
        ({"splat_density": float("nan")}, "splat_density must be a positive number or null"),
        ({"splat_density": True}, "splat_density must be a positive number or null"),
        ({"splat_density_window": 4}, "splat_density_window must be odd and ≥ 1"),
        ({"best_sources": -1}, "best_sources must be ≥ 0"),
        # each setting of its default's kind (the scene flow's --set passes text through)
        ({"neighbours": "abc"}, "neighbours must be a whole number, got 'abc'"),
        ({"weight_threshold": float("nan")}, "weight_threshold must be a finite number"),
        ({"soil_a_min": float("nan")}, "soil_a_min must be a finite number"),
        ({"colour": "no"}, "colour must be true or false"),
        ({"seed": -1}, "seed must be ≥ 0"),
        ({"depth_range": [1, 2, 3]}, "depth_range must be \\[near, far\\] in metres"),
        # nerfacto's, refused here and not in ns-train on the GPU worker (or as a bare error)
        ({"nerf_max_seconds": "ten"}, "nerf_max_seconds must be null or a number > 0"),
        ({"nerf_args": 5}, "nerf_args must be a list of options"),
        ({"orientation": "sideways"}, "orientation must be one of pca, up, vertical, none"),
        ({"hidden_dim": -64}, "hidden_dim must be null or a whole number > 0"),
        ({"near_plane": 2.0, "far_plane": 1.0}, "near_plane 2.0 must be below far_plane 1.0"),
        ({"near_plane": "near"}, "near_plane must be null or a number ≥ 0"),
    ],
)
def test_bad_stereo_settings_are_named_config_errors(bad, match):
    with pytest.raises(ConfigError, match=match):
        SurfacesConfig(backend="points", **bad)


def _cuda() -> bool:
    try:
        import torch

        return bool(torch.cuda.is_available())
    except ImportError:  # pragma: no cover
        return False


def _nerfstudio() -> bool:
    import importlib.util

    return importlib.util.find_spec("nerfstudio") is not None


@pytest.mark.skipif(_cuda() and _nerfstudio(), reason="nerfstudio and CUDA are present")
def test_nerfacto_without_cuda_names_cpu_backend():
    with pytest.raises(SurfacesError, match="--set surfaces.backend=tsdf"):
        make_backend(SurfacesConfig(backend="nerfacto"))


def test_paper_settings_per_crop():
    m = SurfacesConfig.for_crop("maize", backend="nerfacto")
    assert (m.near_plane, m.far_plane, m.hidden_dim, m.orientation) == (0.05, 6.0, 128, "vertical")
    assert SurfacesConfig.for_crop("soybean").nerf_iterations == 20000


def test_nerfacto_command_trains_every_photo_with_the_offline_method(tmp_path):
    """The ns-train command that ``NerfactoSurfaces.fit`` runs: this interpreter with ``-m``
    (nerfstudio installed with ``pip --target`` has no ``ns-train`` on the PATH), CropCraft's
    registered method (no LPIPS download at model build), every photo in training, nerfstudio's
    evaluation passes never due, checkpoints often enough for a deadline, the crop's settings."""
    import sys

    from cropcraft_core.surfaces.nerfacto import METHOD, METHOD_ENV, SAVE_EVERY, train_command

    cfg = SurfacesConfig.for_crop("maize", backend="nerfacto", nerf_iterations=300)
    cmd = train_command(cfg, tmp_path / "data", tmp_path / "out")
    assert cmd[:4] == [sys.executable, "-m", "nerfstudio.scripts.train", METHOD]

    def value(flag: str) -> str:
        return cmd[cmd.index(flag) + 1]

    assert value("--max-num-iterations") == "300"
    for flag in ("--steps-per-eval-batch", "--steps-per-eval-image", "--steps-per-eval-all-images"):
        assert int(value(flag)) > 300
    assert value("--steps-per-save") == str(SAVE_EVERY)
    assert (value("--pipeline.model.near-plane"), value("--pipeline.model.far-plane")) == (
        "0.05",
        "6.0",
    )
    assert value("--pipeline.model.hidden-dim") == "128"
    # the dataparser's own options come after its subcommand
    tail = cmd[cmd.index("nerfstudio-data") :]
    assert tail[tail.index("--orientation-method") + 1] == "vertical"
    assert tail[tail.index("--eval-mode") + 1] == "all"
    assert METHOD_ENV.startswith(f"{METHOD}=cropcraft_core.surfaces.nerfacto_method:")
    # a user's own options go before the dataparser's subcommand
    off = ("--pipeline.model.camera-optimizer.mode", "off")
    cmd = train_command(replace(cfg, nerf_args=off), tmp_path / "data", tmp_path / "out")
    i = cmd.index("nerfstudio-data")
    assert tuple(cmd[i - 2 : i]) == off


def test_nerfacto_far_plane_from_the_scene_box(tmp_path, monkeypatch):
    """``nerf_far_margin``: ``fit`` fixes nerfstudio's scale (the cameras' largest distance from
    their mean becomes 1) and puts the far plane at the margin times the farthest camera-to-box
    distance in that frame. By hand: cameras at x = ±2 (scale 1/2), box ±1 (farthest corner
    from either camera: √(3² + 1 + 1) = √11 m), the default margin 1.5 → far 1.5·√11/2 in
    nerfstudio's frame. Without a margin, or with a far plane given, nerfstudio keeps
    its own scale (and far plane); a margin without a box is an error that names the setting."""
    import cropcraft_core.surfaces.nerfacto as nf

    cams = []
    for x in (-2.0, 2.0):
        c = PinholeCamera.look_down((x, 0.0), 1.0, size=(32, 24))
        m = c.cam_to_world.copy()
        m[2, 3] = 0.0  # both centres at z = 0
        cams.append(replace(c, cam_to_world=m))
    assert nf.pose_scale(cams) == pytest.approx(0.5)
    box = np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    assert nf.scene_far(cams, box) == pytest.approx(math.sqrt(11))

    seen = []

    def no_training(cmd, log, deadline_s):  # records the command, fails as ns-train would
        seen.append(cmd)
        return 1, False

    monkeypatch.setattr(nf, "nerfacto_available", lambda: True)
    monkeypatch.setattr(nf, "run_training", no_training)
    images = [np.zeros((24, 32, 3), np.uint8)] * 2
    for kw in ({}, {"nerf_far_margin": None}, {"far_plane": 6.0}):
        cfg = SurfacesConfig(backend="nerfacto", workdir=str(tmp_path), **kw)
        with pytest.raises(SurfacesError, match="ns-train failed"):
            nf.NerfactoSurfaces(cfg).fit(images, cams, box)
    with_box, no_margin, given = seen
    tail = with_box[with_box.index("nerfstudio-data") :]
    assert tail[tail.index("--auto-scale-poses") + 1] == "False"
    assert float(tail[tail.index("--scale-factor") + 1]) == pytest.approx(0.5)
    far = float(with_box[with_box.index("--pipeline.model.far-plane") + 1])
    assert far == pytest.approx(1.5 * math.sqrt(11) * 0.5)
    assert "--scale-factor" not in no_margin and "--pipeline.model.far-plane" not in no_margin
    assert "--scale-factor" not in given
    assert given[given.index("--pipeline.model.far-plane") + 1] == "6.0"
    cfg = SurfacesConfig(backend="nerfacto", workdir=str(tmp_path))
    with pytest.raises(SurfacesError, match="nerf_far_margin needs a bounding box"):
        nf.NerfactoSurfaces(cfg).fit(images, cams, None)
    assert len(seen) == 3  # nothing was trained
    with pytest.raises(ConfigError, match="nerf_far_margin"):
        SurfacesConfig(backend="nerfacto", nerf_far_margin=0.5)


def _fake_ns_train(monkeypatch, made: list, fail: bool = False) -> None:
    """Makes nerfacto available and stands in for its ``run_training`` where nerfstudio is
    absent: writes what ``ns-train`` leaves in its output folder (config, dataparser transform,
    a checkpoint with the pipeline's and the optimisers' state) or, failing, a log line and
    exit 1. Each run's workdir is appended to ``made``."""
    import torch

    import cropcraft_core.surfaces.nerfacto as nf

    def train(cmd, log, deadline_s):
        out, data = Path(cmd[cmd.index("--output-dir") + 1]), Path(cmd[cmd.index("--data") + 1])
        made.append(data.parent)
        if fail:
            log.write("step 0\nRuntimeError: CUDA out of memory\n")
            return 1, False
        run = out / "cropcraft" / nf.METHOD / "run"
        (run / "nerfstudio_models").mkdir(parents=True)
        (run / "config.yml").write_text(f"method_name: {nf.METHOD}\n")
        meta = {"transform": np.eye(4)[:3].tolist(), "scale": 0.5}
        (run / "dataparser_transforms.json").write_text(json.dumps(meta))
        state = {
            "step": 499,
            "pipeline": {"_model.field.w": torch.arange(6.0)},
            "optimizers": {"fields": {"state": torch.zeros(1000)}},
            "scalers": {},
        }
        torch.save(state, run / "nerfstudio_models" / "step-000000499.ckpt")
        return 0, False

    monkeypatch.setattr(nf, "nerfacto_available", lambda: True)
    monkeypatch.setattr(nf, "run_training", train)


def test_saved_nerfacto_surfaces_load_without_their_training_folder(tmp_path, monkeypatch):
    """The flow saves the surfaces into the store and a later task (another worker, another
    night) loads them: ``save`` keeps the run with them (config, dataparser transform, the
    dataset's transforms.json, the last checkpoint's pipeline weights without the optimisers'
    state), ``fit``'s own temporary folder goes with the object, and the loaded surfaces point
    nerfstudio's ``eval_setup`` at the saved copy. ns-train itself needs CUDA; the GPU
    acceptance test renders through this path."""
    import gc
    import shutil
    from types import SimpleNamespace

    import torch

    import cropcraft_core.surfaces.nerfacto as nf
    from cropcraft_core.surfaces import load_surfaces

    made: list[Path] = []
    _fake_ns_train(monkeypatch, made)
    cams = [PinholeCamera.look_down((x, 0.0), 1.0, size=(32, 24)) for x in (-0.5, 0.5)]
    imgs = [np.zeros((24, 32, 3), np.uint8)] * 2
    box = np.array([[-1.0, -1.0, -0.1], [1.0, 1.0, 1.0]])
    b = nf.NerfactoSurfaces(SurfacesConfig(backend="nerfacto"))
    b.fit(imgs, cams, box)
    work = made[0]
    assert (work / "data" / "images" / "frame_00001.png").is_file()
    saved = b.save(tmp_path / "saved")
    del b
    gc.collect()
    assert not work.exists()  # photos and checkpoints of fit's own folder are gone
    run = saved / nf.RUN_FOLDER
    assert sorted(str(p.relative_to(run)) for p in run.rglob("*") if p.is_file()) == [
        "config.yml",
        "data/transforms.json",
        "dataparser_transforms.json",
        "nerfstudio_models/step-000000499.ckpt",
    ]
    state = torch.load(run / "nerfstudio_models" / "step-000000499.ckpt")
    assert set(state) == {"pipeline", "step"} and state["step"] == 499
    assert torch.equal(state["pipeline"]["_model.field.w"], torch.arange(6.0))

    moved = Path(shutil.move(saved, tmp_path / "elsewhere"))
    b2 = load_surfaces(moved)
    assert b2.run_dir == moved / nf.RUN_FOLDER and b2._scale == 0.5
    # what eval_setup reads once the callback ran: base_dir / relative_model_dir, the dataset
    old = work / "data"
    parser = SimpleNamespace(data=old, downscale_factor=None)
    config = SimpleNamespace(
        relative_model_dir=Path("nerfstudio_models"),
        pipeline=SimpleNamespace(datamanager=SimpleNamespace(data=old, dataparser=parser)),
    )
    b2._relocate(config)
    ckpt_dir = Path("/training/outputs/cropcraft/run") / config.relative_model_dir
    assert ckpt_dir == (moved / nf.RUN_FOLDER / "nerfstudio_models").resolve()
    assert (config.pipeline.datamanager.data / "transforms.json").is_file()
    assert parser.data == config.pipeline.datamanager.data and parser.downscale_factor == 1


def test_nerfacto_counts_only_surfaces_inside_the_box_as_supported(monkeypatch):
    """The observe stage's coverage figure: a depth that puts the surface outside the scene box
    (the backdrop at the far plane, seen past the soil) is not a reconstructed surface. The
    render is nerfstudio's (CUDA); here a known depth map stands in for it."""
    import cropcraft_core.surfaces.nerfacto as nf

    made: list[Path] = []
    _fake_ns_train(monkeypatch, made)
    cam = PinholeCamera.look_down((0.0, 0.0), 1.0, size=(4, 3))
    box = np.array([[-1.0, -1.0, -0.1], [1.0, 1.0, 1.0]])
    b = nf.NerfactoSurfaces(SurfacesConfig(backend="nerfacto"))
    other = PinholeCamera.look_down((0.3, 0.0), 1.0, size=(4, 3))
    b.fit([np.zeros((3, 4, 3), np.uint8)] * 2, [cam, other], box)
    depth = np.full((3, 4), 0.6, np.float32)  # 0.4 m up: inside
    depth[0, 0], depth[1, 2], depth[2, 3] = 4.5, np.nan, 1.05  # far shell, nothing, in the soil
    monkeypatch.setattr(b, "render", lambda camera: (depth, np.zeros((3, 4, 3), np.uint8)))
    got = b.render_supported(cam)
    want = depth.copy()
    want[0, 0] = np.nan
    np.testing.assert_array_equal(got, want)


def test_failed_nerfacto_training_keeps_its_folder_and_says_why(monkeypatch):
    """ns-train failing: the error carries the log's last lines (what a Prefect run shows) and
    names the log, and fit's temporary folder is kept for it."""
    import gc
    import shutil

    import cropcraft_core.surfaces.nerfacto as nf

    made: list[Path] = []
    _fake_ns_train(monkeypatch, made, fail=True)
    cams = [PinholeCamera.look_down((x, 0.0), 1.0, size=(32, 24)) for x in (-0.5, 0.5)]
    imgs = [np.zeros((24, 32, 3), np.uint8)] * 2
    b = nf.NerfactoSurfaces(SurfacesConfig(backend="nerfacto", nerf_far_margin=None))
    with pytest.raises(SurfacesError, match=r"(?s)ns-train failed \(exit 1\).*CUDA out of memory"):
        b.fit(imgs, cams)
    del b
    gc.collect()
    try:
        assert (made[0] / "ns-train.log").is_file()
    finally:
        shutil.rmtree(made[0], ignore_errors=True)


def test_nerf_training_deadline_stops_it_like_ctrl_c_and_reaps_its_workers(tmp_path):
    """``run_training`` past its deadline: SIGINT to the trainer's process group (the trainer
    saves nothing more and exits), then whatever it left behind (nerfstudio's data workers) is
    killed. Real processes: a 'trainer' that exits 0 on Ctrl-C and a 'worker' that would sleep
    on for a minute."""
    import os
    import sys
    import time

    from cropcraft_core.surfaces.nerfacto import run_training

    pidfile = tmp_path / "worker.pid"
    trainer = (
        "import signal, subprocess, sys, time\n"
        "w = subprocess.Popen([sys.executable, '-c', 'import time; time.sleep(60)'])\n"
        f"open({str(pidfile)!r}, 'w').write(str(w.pid))\n"
        "try:\n"
        "    time.sleep(60)\n"
        "except KeyboardInterrupt:\n"
        "    print('interrupted', flush=True)\n"
    )
    import signal

    t = time.perf_counter()
    # a host process that ignores Ctrl-C (as one did inside the test suite) must not pass that
    # on to the trainer, or the deadline's SIGINT goes unheard
    before = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        with open(tmp_path / "log", "w") as log:
            rc, stopped = run_training([sys.executable, "-c", trainer], log, deadline_s=3.0)
    finally:
        signal.signal(signal.SIGINT, before)
    assert stopped and rc == 0
    assert time.perf_counter() - t < 30
    assert "interrupted" in (tmp_path / "log").read_text()
    worker = int(pidfile.read_text())
    for _ in range(50):  # the worker was SIGKILLed; wait for its zombie to be reaped by init
        try:
            os.kill(worker, 0)
        except ProcessLookupError:
            break
        if open(f"/proc/{worker}/stat").read().split()[2] == "Z":
            break
        time.sleep(0.1)
    else:
        raise AssertionError("the trainer's worker outlived it")
    with open(tmp_path / "log2", "w") as log:  # no deadline: the exit code as it is
        assert run_training([sys.executable, "-c", "raise SystemExit(3)"], log, None) == (3, False)


def test_nerfacto_env_adds_the_method_to_a_users_own(monkeypatch):
    from cropcraft_core.surfaces.nerfacto import METHOD_ENV, train_env

    monkeypatch.delenv("NERFSTUDIO_METHOD_CONFIGS", raising=False)
    assert train_env()["NERFSTUDIO_METHOD_CONFIGS"] == METHOD_ENV
    monkeypatch.setenv("NERFSTUDIO_METHOD_CONFIGS", "mine=pkg.mod:spec")
    assert train_env()["NERFSTUDIO_METHOD_CONFIGS"] == f"mine=pkg.mod:spec,{METHOD_ENV}"


def test_nerf_deadline_must_be_positive():
    with pytest.raises(ConfigError, match="nerf_max_seconds"):
        SurfacesConfig(backend="nerfacto", nerf_max_seconds=0)
    with pytest.raises(ConfigError, match="nerf_args"):
        SurfacesConfig(backend="nerfacto", nerf_args="--pipeline.model.camera-optimizer.mode off")
    assert SurfacesConfig(nerf_max_seconds=60).nerf_max_seconds == 60


@pytest.mark.gpu
@pytest.mark.skipif(not (_cuda() and _nerfstudio()), reason="needs nerfstudio and CUDA")
def test_nerfacto_fits_on_gpu(scene, tmp_path):  # pragma: no cover - GPU hosts only
    """nerfacto (the default far plane at the scene box) fits a 14-view arc; the saved surfaces
    render the same after the training folder is gone."""
    import shutil

    from cropcraft_core.surfaces import load_surfaces

    mesh, cams, imgs, bbox = scene
    work = tmp_path / "train"
    cfg = SurfacesConfig(backend="nerfacto", nerf_iterations=2000, workdir=str(work))
    b = make_backend(cfg)
    b.fit(imgs, cams, bbox)
    cam = PinholeCamera.look_down(height_m=1.2, size=(200, 150))
    depth, rgb = b.render(cam)
    d_true = _view(mesh, cam)[1]  # the z-buffer, not Open3D: the GPU hosts lack it
    both = np.isfinite(depth) & np.isfinite(d_true)
    assert np.median(np.abs(depth[both] - d_true[both])) < 0.05
    assert len(b.point_cloud(1000)[0]) > 0
    b.save(tmp_path / "saved")
    shutil.rmtree(work)
    again, rgb_again = load_surfaces(tmp_path / "saved").render(cam)
    np.testing.assert_allclose(again, depth, rtol=1e-4, atol=1e-4)


def test_hole_breakdown_names_the_stage_that_lost_each_hole():
    """bench pipeline's diagnosis of the row camera's holes: four true points on the ground,
    each lost at a different stage, found through a shifted scene frame."""
    from benchmarks.bench_pipeline import hole_breakdown

    size = (64, 48)
    true_cams = [PinholeCamera.look_down((x, 0.0), 1.0, size=size) for x in (0.0, 0.1)]
    shift = np.eye(4)
    shift[:3, 3] = (0.5, -0.25, 2.0)  # scene frame = truth frame moved
    stereo_cams = []
    for c in true_cams:
        m = c.cam_to_world.copy()
        m[:3, 3] += shift[:3, 3]
        stereo_cams.append(PinholeCamera(c.width, c.height, c.fx, c.fy, c.cx, c.cy, m))
    true_depths = [np.ones(size[::-1]) for _ in true_cams]
    pts = np.array([[0.02, 0.01, 0.0], [0.05, -0.02, 0.0], [0.08, 0.03, 0.0], [9.0, 0.0, 0.0]])
    raw = [np.full(size[::-1], np.nan) for _ in true_cams]
    fused = [np.full(size[::-1], np.nan) for _ in true_cams]

    def put(maps, view, point):
        uv, z = stereo_cams[view].project((point + shift[:3, 3])[None])
        maps[view][int(uv[0, 1]), int(uv[0, 0])] = z[0]

    put(raw, 0, pts[1])  # stereo found it, the consistency filter dropped it
    put(raw, 1, pts[2])  # found and kept: fusion lost it
    put(fused, 1, pts[2])
    out = hole_breakdown(pts, true_cams, true_depths, stereo_cams, raw, fused, shift)
    assert out == {
        "holes": 4,
        "unseen": 0.25,
        "no_stereo": 0.25,
        "inconsistent": 0.25,
        "fusion": 0.25,
        "no_stereo_empty": 0.25,
        "no_stereo_front": 0.0,
        "no_stereo_behind": 0.0,
    }
    # a wrong depth is no find: 5 % too far in every map leaves the second point unmatched,
    # and the split says where the stereo put it
    raw[0] *= 1.05
    out = hole_breakdown(pts, true_cams, true_depths, stereo_cams, raw, fused, shift)
    assert out["no_stereo"] == pytest.approx(0.5)
    assert (out["no_stereo_empty"], out["no_stereo_behind"]) == pytest.approx((0.25, 0.25))
    raw[0] *= 0.9  # now 5.5 % too near
    out = hole_breakdown(pts, true_cams, true_depths, stereo_cams, raw, fused, shift)
    assert (out["no_stereo_front"], out["no_stereo_behind"]) == pytest.approx((0.25, 0.0))


@pytest.mark.parametrize("n_max", [50, 1000])
def test_point_cloud_subset_does_not_depend_on_the_vertex_order(n_max):
    """Open3D's TSDF returns the same vertices in a different order on each run: the subset the
    row fit gets (and its seeded RANSAC over it) must not change with that order."""
    from cropcraft_core.surfaces.base import subsample

    rng = np.random.default_rng(3)
    pts = rng.normal(size=(400, 3))
    pts[10] = pts[11]  # a repeated position with another colour
    cols = rng.uniform(size=(400, 3))
    perm = rng.permutation(400)
    a = subsample(pts, cols, n_max, seed=0)
    b = subsample(pts[perm], cols[perm], n_max, seed=0)
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])
    assert len(a[0]) == min(n_max, 400)
    rows = {tuple(r) for r in np.c_[pts, cols]}
    assert all(tuple(r) in rows for r in np.c_[a[0], a[1]])  # rows kept whole
    with pytest.raises(ConfigError, match="n_max"):
        subsample(pts, cols, -1, seed=0)


def test_the_gpu_acceptance_test_imports_without_open3d():
    """The lent GPU hosts have no Open3D (its wheel is too big to carry there): the z-buffer,
    the surfaces package and this test module import without it, and ray casting says what is
    missing only when asked for. A real interpreter with Open3D's import refused."""
    import subprocess
    import sys
    from pathlib import Path

    code = """
import importlib.abc, sys
class NoOpen3d(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path, target=None):
        if name.split(".")[0] == "open3d":
            raise ImportError("No module named 'open3d' (refused by the test)")
sys.meta_path.insert(0, NoOpen3d())
import tests.test_surfaces
import cropcraft_core.render as r
assert callable(r.render_depth) and "open3d" not in sys.modules
try:
    r.build_scene
except ImportError as exc:
    print("raycast:", exc)
"""
    root = Path(__file__).resolve().parents[1]
    out = subprocess.run(
        [sys.executable, "-c", code], cwd=root, capture_output=True, text=True, timeout=120
    )
    assert out.returncode == 0, out.stderr
    assert "raycast: No module named 'open3d'" in out.stdout


def test_prediction_blur_is_the_backends_own_softening_in_metres():
    """``auto``: tsdf's fused surfaces soften depth steps over 0.8 voxel (scene units, then
    metres by the row fit's scale); the other backends' softening is taken as none until
    measured; a number of metres is used as given, anything else is a named error."""
    from cropcraft_core.surfaces import prediction_blur_m
    from cropcraft_core.surfaces.tsdf import EDGE_BLUR_VOXELS

    tsdf = make_backend(SurfacesConfig(backend="tsdf", voxel_size=0.01))
    assert tsdf.edge_blur == pytest.approx(EDGE_BLUR_VOXELS * 0.01)
    assert prediction_blur_m(tsdf, 0.5) == pytest.approx(EDGE_BLUR_VOXELS * 0.005)
    assert prediction_blur_m(tsdf, 0.5, 0.002) == 0.002 and prediction_blur_m(tsdf, 2, 0) == 0
    assert prediction_blur_m(make_backend(SurfacesConfig(backend="points")), 1.0) == 0.0
    for bad in (-0.001, float("nan"), "voxel", True, None):
        with pytest.raises(ConfigError, match="prediction blur must be 'auto' or a number"):
            prediction_blur_m(tsdf, 1.0, bad)


# --------------------------------------------------------------------------- tsdf fusion


def _plane_depth(cam: PinholeCamera, slope: float, z0: float) -> np.ndarray:
    """z-depth of the plane z = slope * x + z0 seen by ``cam`` (NaN behind it)."""
    d = cam.ray_directions(normalized=False)
    c = cam.center
    t = (slope * c[0] + z0 - c[2]) / (d[..., 2] - slope * d[..., 0])
    return np.where(t > 0, t, np.nan).astype(np.float32)


@pytest.mark.parametrize("slope", [0.0, 0.3])
def test_fusion_puts_a_plane_where_its_depth_maps_say(slope):
    """Depth maps of an exact plane fuse onto that plane: Open3D reads pixel int(u), the
    camera's own convention, so K goes in unshifted (a half-pixel shift put it 1.1 mm low at
    this size, 4.8 mm at 160 x 120)."""
    from cropcraft_core.surfaces import tsdf

    cams = [PinholeCamera.look_down((x, y), 1.2, size=(480, 360)) for x, y in _OFFSETS]
    depths = [_plane_depth(c, slope, 0.1) for c in cams]
    b = tsdf.TsdfSurfaces(SurfacesConfig(fill_one_view=False))
    b.bbox = np.array([[-1.0, -1.0, -0.5], [1.0, 1.0, 1.0]])
    b._fuse([np.full((360, 480, 3), 128, np.uint8)] * 3, cams, depths, [(0.1, 6.0)] * 3)
    v = b.vertices
    off = (v[:, 2] - slope * v[:, 0] - 0.1) / math.sqrt(1 + slope**2)
    assert abs(float(np.median(off))) < 2e-4, np.median(off)


_OFFSETS = ((0.0, 0.0), (0.15, 0.05), (-0.1, 0.12))


def test_fusion_allocates_blocks_for_every_depth_not_every_fourth_pixel():
    """A view whose few depths all lie off Open3D's every-fourth-pixel grid is fused (it stopped
    the fusion with Open3D's "No block is touched"), and its surface is there."""
    from cropcraft_core.surfaces import tsdf

    cams = [PinholeCamera.look_down((0.0, 0.0), 1.0, size=(64, 48)) for _ in range(2)]
    d = np.full((48, 64), np.nan, np.float32)
    d[21:24, 33:36] = 0.9  # rows and columns 21-23, 33-35: one (not 4k) of each
    b = tsdf.TsdfSurfaces(SurfacesConfig(fill_one_view=True, weight_threshold=0.0))
    b.bbox = None
    b._fuse([np.zeros((48, 64, 3), np.uint8)] * 2, cams, [d, d.copy()], [(0.1, 6.0)] * 2)
    assert len(b.faces) and np.allclose(np.median(b.vertices[:, 2]), 0.1, atol=0.01)


def test_stereo_matches_large_photos_at_a_bounded_size():
    """mvs_scale of a 640 x 480 photo, but a phone's 4000 x 3000 is matched at 1024 x 768 (its
    cost volumes were ~10 GiB a view at 0.75); None lifts the limit."""
    from cropcraft_core.surfaces.tsdf import stereo_scale

    small = PinholeCamera.look_down((0.0, 0.0), 1.0, size=(640, 480))
    phone = PinholeCamera.look_down((0.0, 0.0), 1.0, size=(4000, 3000))
    cfg = SurfacesConfig()
    assert stereo_scale(small, cfg) == 0.75
    assert phone.scaled(stereo_scale(phone, cfg)).width == 1024
    assert stereo_scale(phone, SurfacesConfig(mvs_max_side=None)) == 0.75
    with pytest.raises(ConfigError, match="mvs_max_side must be at least 32"):
        SurfacesConfig(mvs_max_side=16)


def test_photos_that_do_not_see_the_scene_box_are_named_and_left_to_the_caller():
    """One more drone photo 40 m along the field stopped the whole stage ("the camera at
    [36.4, 3.7, 13.1] does not see the bounding box"): ``views_in_box`` keeps the others and
    names the photos only where fewer than two see the box."""
    from cropcraft_core.surfaces import views_in_box

    box = np.array([[-3.0, -3.0, -0.5], [3.0, 3.0, 2.5]])
    over = [PinholeCamera.look_down((x, 0.0), 13.0, size=(64, 48)) for x in (-1.0, 1.0)]
    along = PinholeCamera.look_down((40.0, 0.0), 13.0, size=(64, 48))
    names = ["a.png", "b.png", "far.png"]
    assert views_in_box(names, [*over, along], box) == [0, 1]
    assert views_in_box(names, [*over, along], None) == [0, 1, 2]
    few = r"only 1 of 3 photos see the scene box.*b\.png, far\.png\); 3 photos are too few"
    with pytest.raises(InputError, match=few):
        views_in_box(names, [over[0], along, along], box)
    many = [f"p{i}.png" for i in range(12)]
    with pytest.raises(InputError, match=r"p8\.png, \.\.\.\)$"):  # enough photos: no hint
        views_in_box(many, [over[0], *[along] * 11], box)


def test_a_depth_range_bounds_the_horizontal_sweeps_depths(scene):
    """The default sweep's planes span the box's heights, not ``depth_range``: set to (2.5, 8) m
    on a walk whose surfaces lie 0.9-4.8 m away, 83 % of the stereo's depths lay nearer (a
    user's feet or a near row, set apart by the range, reconstructed anyway). Now none does."""
    mesh, cams, imgs, bbox = scene
    cfg = SurfacesConfig(n_depths=32, mvs_scale=0.5, voxel_size=0.01, depth_range=(1.6, 8.0))
    b = make_backend(cfg)
    b.fit(imgs, cams, bbox)
    depths = np.concatenate([d[np.isfinite(d)] for d in b.raw_depth_maps])
    assert len(depths) and depths.min() >= 1.6
