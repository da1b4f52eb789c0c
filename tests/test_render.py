"""Depth rendering: numba rasterizer against geometry and against Open3D ray casting; previews."""

from __future__ import annotations

import os

import numpy as np
import pytest
from PIL import Image

from cropcraft_core.errors import ConfigError, GeometryError, InputError, OutputError
from cropcraft_core.geometry.camera import PinholeCamera
from cropcraft_core.geometry.mesh import CanopyMesh, Organ
from cropcraft_core.render import (
    RenderResult,
    build_scene,
    cast_rays,
    depth_map,
    depth_to_rgb,
    oblique_camera,
    raycast_depth,
    render_depth,
    save_png,
    shade_rgb,
)

ROW_CAM = PinholeCamera.look_down(height_m=1.0)


def _square(half: float, z: float, center=(0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    cx, cy = center
    v = np.array(
        [
            [cx - half, cy - half, z],
            [cx + half, cy - half, z],
            [cx + half, cy + half, z],
            [cx - half, cy + half, z],
        ]
    )
    return v, np.array([[0, 1, 2], [0, 2, 3]], np.int32)


def _random_soup(n: int, seed: int, size: float = 0.03) -> tuple[np.ndarray, np.ndarray]:
    """n independent small triangles (edges ~size) over 1.2 m × 1 m, heights 0–0.7 m."""
    rng = np.random.default_rng(seed)
    centre = np.column_stack(
        [rng.uniform(-0.6, 0.6, n), rng.uniform(-0.5, 0.5, n), rng.uniform(0.0, 0.7, n)]
    )
    corners = centre[:, None, :] + rng.normal(0, size / 2, (n, 3, 3))
    return corners.reshape(-1, 3), np.arange(3 * n, dtype=np.int32).reshape(n, 3)


def _rigid(seed: int) -> np.ndarray:
    """A random rotation (3, 3)."""
    q, r = np.linalg.qr(np.random.default_rng(seed).normal(size=(3, 3)))
    q *= np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


# ------------------------------------------------------------------------------------ geometry
@pytest.mark.parametrize("h", [0.0, 0.3, 0.75])
def test_horizontal_square_depth_and_coverage(h):
    cam = ROW_CAM
    half = 0.2 * (1.0 - h)  # ~316 px wide at any height
    v, f = _square(half, h, center=(0.0123, -0.0371))
    res = render_depth(v, f, cam)
    assert isinstance(res, RenderResult)
    assert res.depth.shape == (cam.height, cam.width) and res.depth.dtype == np.float32
    assert res.face_id.dtype == np.int32
    cover = res.mask
    # depth is exactly the camera height above the square wherever it is seen, NaN elsewhere
    np.testing.assert_allclose(res.depth[cover], 1.0 - h, rtol=1e-6)
    assert np.all(np.isnan(res.depth[~cover]))
    assert np.all(res.face_id[~cover] == -1) and set(np.unique(res.face_id[cover])) == {0, 1}
    # pixel coverage = projected area (a square of side f * 2 half / depth pixels)
    side_px = cam.fx * 2 * half / (1.0 - h)
    assert abs(cover.sum() - side_px**2) / side_px**2 < 0.01
    # and exactly the pixels whose centre projects inside the square (away from its border)
    uv, _ = cam.project(v)
    u = np.arange(cam.width) + 0.5
    w = np.arange(cam.height) + 0.5
    inside_u = (u > uv[:, 0].min()) & (u < uv[:, 0].max())
    inside_v = (w > uv[:, 1].min()) & (w < uv[:, 1].max())
    expected = inside_v[:, None] & inside_u[None, :]
    near_border_u = np.min(np.abs(u[None, :] - uv[:2, 0, None]), axis=0) < 1e-6
    near_border_v = np.min(np.abs(w[None, :] - uv[1:3, 1, None]), axis=0) < 1e-6
    sure = ~(near_border_v[:, None] | near_border_u[None, :])
    assert np.array_equal(cover[sure], expected[sure])


def test_perspective_correct_depth_on_tilted_plane():
    """On a strongly tilted triangle the z-depth at every pixel equals the ray/plane hit."""
    cam = ROW_CAM.scaled(0.5)
    v = np.array([[-0.3, -0.2, 0.1], [0.3, -0.2, 0.1], [0.0, 0.25, 0.8]])
    f = np.array([[0, 1, 2]], np.int32)
    res = render_depth(v, f, cam)
    n = np.cross(v[1] - v[0], v[2] - v[0])
    d = cam.ray_directions(normalized=False)
    t = (n @ (v[0] - cam.center)) / (d @ n)  # ray/plane: z-depth since d has unit camera z
    m = res.mask
    assert m.sum() > 1000
    np.testing.assert_allclose(res.depth[m], t[m], rtol=1e-6)


def test_agrees_with_open3d_raycast_on_random_soup():
    v, f = _random_soup(2000, seed=3)
    cam = ROW_CAM
    ras = render_depth(v, f, cam)
    ref = raycast_depth((v, f), cam)
    same = ras.mask == ref.mask
    assert same.mean() >= 0.99
    both = ras.mask & ref.mask
    rel = np.abs(ras.depth[both] - ref.depth[both]) / ref.depth[both]
    # agreement per pixel: same status and (miss, or depth within 1e-4)
    agree = same.copy()
    agree[both] = rel <= 1e-4
    assert agree.mean() >= 0.99
    # in practice the renderers differ only at a few pixel centres grazing triangle edges
    assert same.mean() > 0.9995 and np.mean(rel <= 1e-4) > 0.9995
    assert np.mean(ras.face_id[both] == ref.face_id[both]) > 0.999
    assert 0.2 < ras.coverage < 0.95  # a meaningful scene: neither empty nor full


def test_raycast_near_option_matches_raster_culling():
    """``near`` drops the faces nearer than it from both renderers alike: of a small square at
    0.5 m over a larger one at 1.0 m, near = 0.6 leaves the far square whole, with its own face
    ids; a near that is not a positive finite distance is refused by both (NaN or inf dropped
    every face from the reference: an empty view, no error)."""
    cam = ROW_CAM.scaled(0.25)
    v0, f0 = _square(0.1, 0.5)  # the camera looks down from 1 m: 0.5 m away
    v1, f1 = _square(0.3, 0.0)  # 1.0 m away
    v, f = np.vstack([v0, v1]), np.vstack([f0, f1 + 4])
    everything = render_depth(v, f, cam, near=0.01)
    assert set(np.unique(everything.face_id)) == {-1, 0, 1, 2, 3}
    for res in (raycast_depth((v, f), cam, near=0.6), render_depth(v, f, cam, near=0.6)):
        assert set(np.unique(res.face_id)) == {-1, 2, 3}
        assert np.array_equal(res.mask, render_depth(v1, f1, cam).mask)
        assert np.allclose(res.depth[res.mask], 1.0, atol=1e-6)
    for bad in (float("nan"), float("inf"), 0.0, -1.0, "0.5", True):
        with pytest.raises(GeometryError, match="near must be a positive finite distance"):
            raycast_depth((v, f), cam, near=bad)
        with pytest.raises(GeometryError, match="near must be a positive finite distance"):
            render_depth(v, f, cam, near=bad)


def test_face_ids_point_at_the_face_containing_the_point():
    v, f = _random_soup(400, seed=5, size=0.06)
    cam = ROW_CAM.scaled(0.5)
    res = render_depth(v, f, cam)
    pts = res.points()
    hit = res.mask
    fid = res.face_id[hit]
    p = pts[hit]
    tri = v[f[fid]]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    dist = np.abs(np.sum((p - tri[:, 0]) * n, axis=1))
    assert np.max(dist) < 1e-5  # metres; depth is stored as float32
    # and the point lies inside that face (barycentric coordinates ≥ 0 up to rounding)
    e1, e2, r = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0], p - tri[:, 0]
    d11, d12, d22 = (e1 * e1).sum(1), (e1 * e2).sum(1), (e2 * e2).sum(1)
    r1, r2 = (r * e1).sum(1), (r * e2).sum(1)
    den = d11 * d22 - d12**2
    b1 = (d22 * r1 - d12 * r2) / den
    b2 = (d11 * r2 - d12 * r1) / den
    assert min(b1.min(), b2.min(), (1 - b1 - b2).min()) > -1e-3


def test_normals():
    cam = ROW_CAM.scaled(0.5)
    rot = np.array([[1.0, 0, 0], [0, np.cos(0.5), -np.sin(0.5)], [0, np.sin(0.5), np.cos(0.5)]])
    v, f = _square(0.2, 0.0)
    v = v @ rot.T + [0, 0, 0.4]
    res = render_depth(v, f, cam)
    nrm = res.normals((v, f))
    assert nrm.shape == (cam.height, cam.width, 3)
    expected = rot @ [0.0, 0.0, 1.0]
    np.testing.assert_allclose(nrm[res.mask], np.broadcast_to(expected, nrm[res.mask].shape))
    assert np.all(np.isnan(nrm[~res.mask]))
    # flipped faces: normals flip, unless asked to face the camera
    f_flip = f[:, ::-1].copy()
    res_f = render_depth(v, f_flip, cam)
    np.testing.assert_allclose(res_f.normals((v, f_flip))[res_f.mask][0], -expected)
    np.testing.assert_allclose(
        res_f.normals((v, f_flip), toward_camera=True)[res_f.mask][0], expected
    )
    mesh = CanopyMesh(v, f, np.zeros(2, np.uint8), np.zeros(2, np.int32), np.zeros(2, np.int32))
    np.testing.assert_allclose(res.normals(mesh), nrm)


def test_no_cracks_on_shared_edges_and_vertices():
    cam = ROW_CAM.scaled(0.5)
    # (a) a quad split along a diagonal that runs exactly through pixel centres
    a = np.array([100.5, 80.5])
    corners_px = np.array([a, a + [200, 0], a + [200, 200], a + [0, 200]])
    z = 0.6
    corners_cam = np.column_stack(
        [(corners_px[:, 0] - cam.cx) / cam.fx * z, (corners_px[:, 1] - cam.cy) / cam.fy * z]
    )
    v = np.column_stack([corners_cam, np.full(4, z)]) @ cam.cam_to_world[:3, :3].T + cam.center
    f = np.array([[0, 1, 2], [0, 2, 3]], np.int32)
    both = render_depth(v, f, cam).mask
    m0 = render_depth(v, f[:1], cam).mask
    m1 = render_depth(v, f[1:], cam).mask
    assert not np.any(m0 & m1), "pixels on the shared edge drawn twice"
    assert np.array_equal(both, m0 | m1)
    inner = np.zeros_like(both)
    inner[81:280, 101:300] = True  # pixel centres strictly inside the quad
    assert both[inner].all(), "crack along the shared diagonal"
    # (b) a fan of 12 triangles around a vertex sitting exactly on a pixel centre, tilted plane
    k = 12
    ang = np.linspace(0, 2 * np.pi, k, endpoint=False) + 0.1
    ring_px = np.column_stack([180.5 + 60 * np.cos(ang), 140.5 + 60 * np.sin(ang)])
    pix = np.vstack([[180.5, 140.5], ring_px])
    depth = 0.5 + 0.002 * (pix[:, 0] - 180.5)  # tilted
    pc = np.column_stack(
        [(pix[:, 0] - cam.cx) / cam.fx * depth, (pix[:, 1] - cam.cy) / cam.fy * depth, depth]
    )
    v = pc @ cam.cam_to_world[:3, :3].T + cam.center
    f = np.array([[0, 1 + i, 1 + (i + 1) % k] for i in range(k)], np.int32)
    count = sum(render_depth(v, f[i : i + 1], cam).mask.astype(int) for i in range(k))
    assert count.max() == 1, "pixel centre covered by two fan triangles"
    assert count[140, 180] == 1, "the shared vertex's pixel is lost"
    yy, xx = np.mgrid[0 : cam.height, 0 : cam.width] + 0.5
    inside = np.hypot(xx - 180.5, yy - 140.5) < 60 * np.cos(np.pi / k) - 1e-3
    assert count[inside].min() == 1, "crack inside the fan"
    assert np.array_equal(render_depth(v, f, cam).mask, count > 0)


def test_random_pose_quad_grid_is_watertight():
    """A 10 × 10 grid of quads (200 triangles) in a random pose covers its interior once."""
    cam = ROW_CAM.scaled(0.5)
    g = np.linspace(-0.2, 0.2, 11)
    gx, gy = np.meshgrid(g, g)
    v = np.column_stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)]) @ _rigid(7).T
    v = v * [1, 1, 0.3] + [0.01, -0.02, 0.45]
    idx = np.arange(121).reshape(11, 11)
    a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, 1:], idx[1:, :-1]
    f = np.concatenate(
        [np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)]
    ).astype(np.int32)
    count = sum(render_depth(v, f[i : i + 1], cam).mask.astype(int) for i in range(len(f)))
    assert count.max() == 1
    full = render_depth(v, f, cam).mask
    assert np.array_equal(full, count > 0)
    # no holes: every background pixel inside the grid's outline is connected to the outside
    from scipy import ndimage

    filled = ndimage.binary_fill_holes(full)
    assert np.array_equal(filled, full)


def test_triangles_behind_camera_or_crossing_near_plane_are_not_drawn():
    cam = ROW_CAM.scaled(0.5)  # at z = 1 looking down
    behind = np.array([[-0.2, -0.2, 1.5], [0.2, -0.2, 1.5], [0.0, 0.2, 1.5]])
    crossing = np.array([[-0.2, -0.2, 0.5], [0.2, -0.2, 0.5], [0.0, 0.2, 1.2]])
    shallow = np.array([[-0.2, -0.2, 0.995], [0.2, -0.2, 0.995], [0.0, 0.2, 0.995]])
    f = np.array([[0, 1, 2]], np.int32)
    assert not render_depth(behind, f, cam).mask.any()
    assert not render_depth(crossing, f, cam).mask.any()
    assert not render_depth(shallow, f, cam, near=0.01).mask.any()
    assert render_depth(shallow, f, cam, near=0.001).mask.any()
    # with the triangle in front added, only it shows
    v = np.vstack([behind, behind * [1, 1, 0] + [0, 0, 0.5]])
    res = render_depth(v, np.array([[0, 1, 2], [3, 4, 5]], np.int32), cam)
    assert set(np.unique(res.face_id)) == {-1, 1}


def test_nearest_face_wins_and_render_is_deterministic():
    cam = ROW_CAM.scaled(0.5)
    v1, f1 = _square(0.2, 0.2)
    v2, f2 = _square(0.1, 0.4)
    v = np.vstack([v1, v2])
    f = np.vstack([f1, f2 + 4]).astype(np.int32)
    res = render_depth(v, f, cam)
    assert np.isclose(np.nanmin(res.depth), 0.6) and np.isclose(np.nanmax(res.depth), 0.8)
    assert np.all(res.face_id[res.depth < 0.7] >= 2)
    again = render_depth(v, f, cam)
    assert np.array_equal(res.face_id, again.face_id)
    assert np.array_equal(res.depth, again.depth, equal_nan=True)


@pytest.mark.parametrize("width", [1, 7, 9, 994])
def test_spans_ending_at_the_image_edge_cover_exactly_their_pixels(width):
    """The rasteriser finishes each span in whole groups of pixels, past its end into a padded
    row, and keeps only what lies inside: a square reaching past both side edges (and a
    second, nearer one ending inside the image) covers exactly the pixels whose centres it
    holds, at any width. The padding (where a group past the last column is stored back
    unchanged) is a whole number of groups wide."""
    from cropcraft_core.render.raster import LANES, padded_width

    stride = padded_width(width)
    assert stride % LANES == 0 and stride >= width + LANES - 1
    cam = PinholeCamera(
        width, 12, 40.0, 40.0, width / 2, 6.0, PinholeCamera.look_down(height_m=1.0).cam_to_world
    )
    half_w = 0.6 * width / 40.0 + 0.013  # past both side edges
    wide = np.array(
        [
            [-half_w, -0.0737, 0.0],
            [half_w, -0.0737, 0.0],
            [half_w, 0.0811, 0.0],
            [-half_w, 0.0811, 0.0],
        ]
    )
    near = wide * [0.21, 0.5, 1.0] + [0.0, 0.0, 0.5]
    v = np.vstack([wide, near])
    f = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]], np.int32)
    res = render_depth(v, f, cam)
    assert res.face_id.flags.c_contiguous and res.face_id.shape == (12, width)
    u = np.arange(width) + 0.5
    w = np.arange(12) + 0.5
    for quad, depth, ids in ((wide, 1.0, {0, 1}), (near, 0.5, {2, 3})):
        uv, _ = cam.project(quad)
        inside = ((w > uv[:, 1].min()) & (w < uv[:, 1].max()))[:, None] & (
            (u > uv[:, 0].min()) & (u < uv[:, 0].max())
        )[None, :]
        if depth == 1.0:
            inside &= ~np.isin(res.face_id, [2, 3])
        got = np.isin(res.face_id, list(ids))
        assert np.array_equal(got, inside)
        np.testing.assert_allclose(res.depth[got], depth, rtol=1e-6)
    assert np.all(np.isnan(res.depth[res.face_id < 0]))


def test_depth_map_is_render_depths_depth_to_the_bit():
    """The fit's renderer, which skips the face ids, gives the depths ``render_depth`` gives, on
    a random soup at two sizes and near planes and on the fit's own canopies of both crops."""
    from cropcraft_core.config import default_layout
    from cropcraft_core.fit import observe_canopy
    from cropcraft_core.fit.forward import ForwardModel
    from cropcraft_core.observe import preset
    from cropcraft_core.procedural import generate_canopy

    v, f = _random_soup(3000, 5, size=0.05)
    for cam, near in ((ROW_CAM, 0.01), (ROW_CAM.scaled(0.37), 0.5)):
        a = render_depth(v, f, cam, near=near).depth
        b = depth_map(v, f, cam, near=near)
        assert b.dtype == np.float32 and b.shape == a.shape
        assert np.array_equal(a.view(np.uint32), b.view(np.uint32))
    for crop, params in (("soybean", {}), ("maize", {"leaf_length": 1.2, "num_nodes": 14.0})):
        truth = generate_canopy(crop, params, default_layout(crop), seed=2)
        fm = ForwardModel(observe_canopy(truth, preset(crop)))
        mesh, cam = fm.canopy(params, seed=3, culled=True).mesh, fm.camera
        a = render_depth(mesh.vertices, mesh.faces, cam).depth
        b = depth_map(mesh.vertices, mesh.faces, cam)
        assert np.isfinite(b).mean() > 0.05
        assert np.array_equal(a.view(np.uint32), b.view(np.uint32))
    with pytest.raises(GeometryError, match="near"):
        depth_map(v, f, ROW_CAM, near=-1.0)
    with pytest.raises(GeometryError, match="PinholeCamera"):
        depth_map(v, f, "camera")


def test_empty_mesh_and_bad_input():
    cam = ROW_CAM.scaled(0.25)
    res = render_depth(np.zeros((0, 3)), np.zeros((0, 3), np.int32), cam)
    assert not res.mask.any() and np.all(res.face_id == -1)
    assert not raycast_depth((np.zeros((0, 3)), np.zeros((0, 3), int)), cam).mask.any()
    v, f = _square(0.1, 0.2)
    with pytest.raises(GeometryError, match="vertices"):
        render_depth(v[:, :2], f, cam)
    with pytest.raises(GeometryError, match="faces"):
        render_depth(v, f + 10, cam)
    with pytest.raises(GeometryError, match="non-finite"):
        render_depth(np.where(v == v[0, 0], np.nan, v), f, cam)
    with pytest.raises(GeometryError, match="near"):
        render_depth(v, f, cam, near=0.0)


def test_cast_rays_miss_and_hit():
    v, f = _square(0.5, 0.2)
    scene = build_scene(v, f)
    t, fid = cast_rays(scene, [[0.0, 0.0, 1.0], [5.0, 5.0, 1.0]], [[0.0, 0.0, -2.0]] * 2)
    assert t.dtype == np.float64 and fid.dtype == np.int64
    assert np.isclose(t[0], 0.4, rtol=1e-6) and fid[0] in (0, 1)
    assert t[1] == np.inf and fid[1] == -1


# ------------------------------------------------------------------------------------ previews
def _demo_mesh() -> CanopyMesh:
    v, f = _random_soup(1500, seed=11, size=0.04)
    m = len(f)
    rng = np.random.default_rng(2)
    organ = rng.choice([Organ.LEAF, Organ.PETIOLE, Organ.STEM], m, p=[0.8, 0.1, 0.1])
    plant = (v[f[:, 0], 0] > 0).astype(np.int32)
    return CanopyMesh(v, f, organ.astype(np.uint8), plant, np.zeros(m, np.int32))


def test_shade_rgb_shows_a_face_without_an_organ_label_in_magenta():
    """A face whose organ label is none of the three was drawn as a stem, hiding a damaged
    mesh in the one image a person looks at."""
    import dataclasses

    mesh = _demo_mesh()
    cam = ROW_CAM.scaled(0.5)
    res = render_depth(mesh.vertices, mesh.faces, cam)
    shown = shade_rgb(mesh, cam, shadows=False)[res.mask].astype(int)
    assert not ((shown[:, 0] > shown[:, 1] + 40) & (shown[:, 2] > shown[:, 1] + 40)).any()
    bad = dataclasses.replace(mesh, organ=np.full_like(mesh.organ, 7))
    shown = shade_rgb(bad, cam, shadows=False)[res.mask].astype(int)
    assert ((shown[:, 0] > shown[:, 1] + 40) & (shown[:, 2] > shown[:, 1] + 40)).mean() > 0.95


def test_shade_rgb_top_and_oblique(tmp_path):
    mesh = _demo_mesh()
    cam = ROW_CAM.scaled(0.5)
    img = shade_rgb(mesh, cam)
    assert img.shape == (cam.height, cam.width, 3) and img.dtype == np.uint8
    assert img.std() > 5
    res = render_depth(mesh.vertices, mesh.faces, cam)
    canopy, soil = img[res.mask].astype(float), img[~res.mask].astype(float)
    assert canopy[:, 1].mean() > canopy[:, 2].mean()  # greenish
    assert soil[:, 0].mean() > soil[:, 2].mean()  # brownish
    obl = oblique_camera((-0.6, 0.6, -0.5, 0.5), 0.7, size=(320, 240))
    img2 = shade_rgb(mesh, obl, shadows=False)
    assert img2.shape == (240, 320, 3) and img2.std() > 5
    p = save_png(tmp_path / "view.png", img2)
    assert np.array_equal(np.asarray(Image.open(p)), img2)
    assert [q.name for q in tmp_path.iterdir()] == ["view.png"]  # no temp file left behind
    umask = os.umask(0)
    os.umask(umask)
    assert p.stat().st_mode & 0o777 == 0o666 & ~umask  # readable by the team, not mkstemp's 0600


def test_oblique_camera_frames_the_plot():
    cam = oblique_camera((0.0, 2.0, 1.0, 3.0), 0.8, elevation_deg=40)
    uv, z = cam.project(np.array([[1.0, 2.0, 0.4]]))
    np.testing.assert_allclose(uv[0], [cam.cx, cam.cy], atol=1e-6)
    corners = np.array([[x, y, h] for x in (0, 2) for y in (1, 3) for h in (0, 0.8)], float)
    uvc, zc = cam.project(corners)
    assert np.all(zc > 0)
    assert np.all((uvc >= 0) & (uvc <= [cam.width, cam.height]))
    assert cam.center[2] > 0.8  # above the canopy
    # image "up" is world up: the box top projects above its bottom
    top, bottom = cam.project(np.array([[1.0, 2.0, 0.8], [1.0, 2.0, 0.0]]))[0]
    assert top[1] < bottom[1]


def test_depth_to_rgb_and_save_png_errors(tmp_path):
    d = np.full((20, 30), np.nan, np.float32)
    d[5:15, 5:25] = np.linspace(0.2, 0.9, 20)[None, :]
    rgb = depth_to_rgb(d)
    assert rgb.shape == (20, 30, 3) and rgb.dtype == np.uint8
    assert np.all(rgb[0, 0] == 128)
    assert len({tuple(c) for c in rgb[10, 5:25]}) > 10
    assert np.array_equal(depth_to_rgb(d, 0.0, 2.0, cmap="viridis")[0, 0], [128, 128, 128])
    for lo, hi, message in (
        (2.0, 0.0, "vmin 2.0 is above vmax 0.0"),
        (np.nan, 2.0, "vmin must be"),
    ):
        with pytest.raises(ConfigError, match=message):  # crossed: flat; NaN: every pixel black
            depth_to_rgb(d, lo, hi)
    flat = depth_to_rgb(np.full((2, 2), 1.5))  # a flat map's own bounds are equal: one colour
    assert (flat == flat[0, 0]).all() and not np.array_equal(flat[0, 0], [128, 128, 128])
    with pytest.raises(InputError):
        save_png(tmp_path / "x.png", rgb.astype(np.float32))
    with pytest.raises(OutputError):
        save_png(tmp_path / "missing" / "x.png", rgb)


def test_a_camera_pose_must_be_rigid_and_above_the_ground_it_frames():
    """A transforms.json whose rotation was scaled by 2 put a point 4 m away at 16 m; a mirror
    or a bad last row passed too. A camera under the ground read a mirrored footprint, and a
    record of 640.7 pixels was cut to 640."""
    from cropcraft_core.errors import ConfigError

    cam = PinholeCamera.look_down(height_m=1.0, size=(64, 48))
    for bad in (2.0 * np.eye(4), np.diag([1.0, 1.0, -1.0, 1.0])):
        m = cam.cam_to_world.copy()
        m[:3, :3] = m[:3, :3] @ bad[:3, :3]
        with pytest.raises(ConfigError, match="must be a rigid transform"):
            PinholeCamera(64, 48, 50.0, 50.0, 32.0, 24.0, m)
    m = cam.cam_to_world.copy()
    m[3, 0] = 0.1
    with pytest.raises(ConfigError, match="must be a rigid transform"):
        PinholeCamera(64, 48, 50.0, 50.0, 32.0, 24.0, m)
    with pytest.raises(ConfigError, match="is not above the ground"):
        cam.ground_footprint(ground_z=2.0)
    with pytest.raises(ConfigError, match="whole number of pixels, got 640.7"):
        PinholeCamera.from_dict({**cam.to_dict(), "width": 640.7})
    with pytest.raises(ConfigError, match="camera record is malformed"):
        PinholeCamera.from_dict({**cam.to_dict(), "fx": "wide"})
