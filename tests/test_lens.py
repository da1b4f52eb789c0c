"""Lens distortion (``cropcraft_core.geometry.lens``): the forward models against OpenCV's own,
photos undistorted into their pinhole cameras, and what the importers record or refuse."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from PIL import Image

from cropcraft_core.errors import InputError
from cropcraft_core.geometry.camera import PinholeCamera
from cropcraft_core.geometry.lens import (
    FISHEYE,
    RADIAL_TANGENTIAL,
    distort,
    lens,
    stored_lens,
    undistort_image,
)
from cropcraft_core.sfm import Poses, import_poses, pinhole_photos

CAM = PinholeCamera(320, 240, 260.0, 255.0, 161.3, 118.2, np.eye(4))
RADTAN = lens(
    RADIAL_TANGENTIAL,
    {"k1": -0.12, "k2": 0.03, "p1": 0.002, "p2": -0.001, "k3": 0.01, "k4": 0.02},
    "test",
)
FISH = lens(FISHEYE, {"k1": 0.05, "k2": -0.01, "k3": 0.002, "k4": -0.0005}, "test")


def _grid():
    x, y = np.meshgrid(np.linspace(-0.6, 0.6, 13), np.linspace(-0.45, 0.45, 9))
    return x.ravel(), y.ravel()


def test_forward_models_are_opencvs():
    x, y = _grid()
    pts = np.stack([x, y, np.ones_like(x)], axis=1)[:, None, :]
    k = np.eye(3)
    xd, yd = distort(x, y, RADTAN)
    c = RADTAN
    coeffs = np.array([c["k1"], c["k2"], c["p1"], c["p2"], c["k3"], c["k4"], 0, 0])
    ref, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), k, coeffs)
    np.testing.assert_allclose(np.stack([xd, yd], 1), ref[:, 0], atol=1e-9)
    xd, yd = distort(x, y, FISH)
    fc = np.array([FISH[n] for n in ("k1", "k2", "k3", "k4")])
    ref = cv2.fisheye.distortPoints(np.stack([x, y], 1)[:, None, :], k, fc)
    np.testing.assert_allclose(np.stack([xd, yd], 1), ref[:, 0], atol=1e-9)


@pytest.mark.parametrize("d", [RADTAN, FISH], ids=["radial_tangential", "fisheye"])
def test_a_photo_is_undistorted_into_its_pinhole_camera(d):
    """A dot the pinhole camera would see at (u, v) lies where the lens puts that ray on the
    photo; undistorted, it is back at (u, v)."""
    h, w = CAM.height, CAM.width
    vv, uu = np.mgrid[0:h, 0:w] + 0.5
    for u, v in ((40.0, 30.0), (160.0, 120.0), (290.0, 215.0)):
        x, y = (u - CAM.cx) / CAM.fx, (v - CAM.cy) / CAM.fy
        xd, yd = distort(np.array([x]), np.array([y]), d)
        ud, vd = CAM.fx * xd[0] + CAM.cx, CAM.fy * yd[0] + CAM.cy
        photo = 255 * np.exp(-((uu - ud) ** 2 + (vv - vd) ** 2) / (2 * 1.5**2))
        out = undistort_image(photo.astype(np.float32), CAM, d)
        wsum = out.sum()
        assert (out * uu).sum() / wsum == pytest.approx(u, abs=0.1)
        assert (out * vv).sum() / wsum == pytest.approx(v, abs=0.1)
    assert undistort_image(photo, CAM, {}) is photo
    # a lens that moves no pixel by a twentieth is left alone (SfM's k on pinhole photos)
    tiny = lens(RADIAL_TANGENTIAL, {"k": 6e-5}, "sfm")
    assert undistort_image(photo, CAM, tiny) is photo


def test_lens_records_are_checked_and_legacy_ones_read():
    assert lens(RADIAL_TANGENTIAL, {"k": 0.1, "p1": 0.0}, "x") == {
        "model": RADIAL_TANGENTIAL,
        "k1": 0.1,
    }
    assert lens(None, {"k1": 0.0}, "x") == {}
    with pytest.raises(InputError, match="x: distortion p1=0.1 does not belong to the fisheye"):
        lens(FISHEYE, {"p1": 0.1}, "x")
    with pytest.raises(InputError, match="x: distortion k1 must be finite"):
        lens(RADIAL_TANGENTIAL, {"k1": float("nan")}, "x")
    # poses written before the model was recorded: SfM's SIMPLE_RADIAL k
    assert stored_lens({"k": 0.02}, "a.jpg") == {"model": RADIAL_TANGENTIAL, "k1": 0.02}
    with pytest.raises(InputError, match="a.jpg: distortion k4 without its lens model"):
        stored_lens({"k1": 0.1, "k4": 0.01}, "a.jpg")


def _colmap_model(folder, model: str, params: str):
    """A COLMAP text model of three views whose one camera is ``model`` with ``params``."""
    from cropcraft_core.sfm import export_colmap_text

    views = []
    for i in range(3):
        m = np.eye(4)
        m[0, 3] = 0.1 * i
        views.append((f"v{i}.png", PinholeCamera(320, 240, 260.0, 255.0, 161.0, 118.0, m)))
    export_colmap_text(Poses(tuple(views)), folder)
    (folder / "cameras.txt").write_text(f"1 {model} 320 240 {params}\n")


def test_importers_record_the_lens_model_or_refuse_it(tmp_path):
    _colmap_model(tmp_path / "opencv", "OPENCV", "260 255 161 118 -0.1 0.02 0.001 0")
    d = import_poses(tmp_path / "opencv").poses.distortion["v0.png"]
    assert d == {"model": RADIAL_TANGENTIAL, "k1": -0.1, "k2": 0.02, "p1": 0.001}
    _colmap_model(tmp_path / "fish", "OPENCV_FISHEYE", "260 255 161 118 0.05 -0.01 0 0.001")
    d = import_poses(tmp_path / "fish").poses.distortion["v1.png"]
    assert d == {"model": FISHEYE, "k1": 0.05, "k2": -0.01, "k4": 0.001}
    _colmap_model(tmp_path / "fov", "FOV", "260 255 161 118 0.9")
    with pytest.raises(InputError, match="COLMAP camera model FOV is not supported"):
        import_poses(tmp_path / "fov")

    frame = {"file_path": "images/a.png", "transform_matrix": np.eye(4).tolist()}
    base = {"w": 320, "h": 240, "fl_x": 260.0, "frames": [frame]}
    for extra, expect in (
        ({"camera_model": "OPENCV_FISHEYE", "k1": 0.05, "k4": 0.001}, FISHEYE),
        ({"camera_model": "OPENCV", "k1": -0.1, "p2": 0.001}, RADIAL_TANGENTIAL),
        ({"k1": -0.1}, RADIAL_TANGENTIAL),  # nerfstudio's default model
        ({"camera_model": "SIMPLE_RADIAL", "k1": -0.1}, RADIAL_TANGENTIAL),
        ({"camera_model": "RADIAL", "k1": -0.1, "k2": 0.01}, RADIAL_TANGENTIAL),
    ):
        (tmp_path / "t.json").write_text(json.dumps({**base, **extra}))
        assert import_poses(tmp_path / "t.json").poses.distortion["a.png"]["model"] == expect
    for model in ("PINHOLE", "SIMPLE_PINHOLE"):  # nerfstudio reads them as perspective too
        (tmp_path / "t.json").write_text(json.dumps({**base, "camera_model": model}))
        assert import_poses(tmp_path / "t.json").poses.distortion == {}
    for extra, match in (
        ({"camera_model": "EQUIRECTANGULAR"}, "camera_model 'EQUIRECTANGULAR' is not supported"),
        ({"camera_model": "OPENCV", "k4": 0.01}, "OPENCV distortion k4=0.01 is read as"),
        ({"camera_model": "OPENCV_FISHEYE", "p1": 0.01}, "p1=0.01 does not belong to the fish"),
    ):
        (tmp_path / "t.json").write_text(json.dumps({**base, **extra}))
        with pytest.raises(InputError, match=match):
            import_poses(tmp_path / "t.json")


def test_the_stages_read_posed_photos_undistorted(tmp_path):
    rng = np.random.default_rng(0)
    photo = rng.integers(0, 255, (CAM.height, CAM.width, 3), dtype=np.uint8)
    Image.fromarray(photo).save(tmp_path / "a.png")
    Image.fromarray(photo).save(tmp_path / "b.png")
    poses = Poses((("a.png", CAM), ("b.png", CAM)), {"b.png": RADTAN})
    a, b = pinhole_photos(tmp_path, poses)
    np.testing.assert_array_equal(a, photo)
    np.testing.assert_array_equal(b, undistort_image(photo, CAM, RADTAN))
    assert not np.array_equal(a, b)
    (only,) = pinhole_photos(tmp_path, Poses.from_dict(poses.to_dict()), [1])
    np.testing.assert_array_equal(only, b)


@pytest.mark.parametrize("orientation", [3, 6, 8])
def test_a_camera_turned_upright_sees_each_point_where_ingest_turned_its_pixel(orientation):
    """COLMAP poses a photo's pixels as stored; ingest turns them upright by the EXIF tag
    (``Image.transpose``). The turned camera must project every point onto the pixel that
    ingest moved the point's stored pixel to, and its lens must distort as the stored one."""
    from cropcraft_core.geometry.lens import distort, turn_upright
    from cropcraft_core.sfm.ingest import _UPRIGHT

    w, h = 64, 48
    rng = np.random.default_rng(orientation)
    pose = np.eye(4)
    pose[:3, :3] = cv2.Rodrigues(np.array([0.3, -0.2, 0.7]))[0]
    pose[:3, 3] = [0.5, -1.0, 2.0]
    cam = PinholeCamera(w, h, 50.0, 53.0, 30.3, 25.1, pose)
    index = np.arange(w * h, dtype=np.int32).reshape(h, w)
    moved = np.asarray(Image.fromarray(index).transpose(_UPRIGHT[orientation]))
    turned, _ = turn_upright(cam, None, orientation)
    assert (turned.width, turned.height) == (moved.shape[1], moved.shape[0])
    # points on the rays through stored pixel centres, at random depths
    i, j = rng.integers(0, w, 20), rng.integers(0, h, 20)
    x, y = (i + 0.5 - cam.cx) / cam.fx, (j + 0.5 - cam.cy) / cam.fy
    z = rng.uniform(1.0, 5.0, 20)
    pc = np.stack([x * z, y * z, z, np.ones(20)], axis=1)
    world = (pc @ cam.cam_to_world.T)[:, :3]
    uv, _ = turned.project(world)
    col, row = np.floor(uv).astype(int).T
    np.testing.assert_allclose(uv - np.floor(uv), 0.5, atol=1e-9)  # pixel centres again
    np.testing.assert_array_equal(moved[row, col], index[j, i])
    # the lens: distorting in the stored frame then turning = turning then distorting
    d = {"model": RADIAL_TANGENTIAL, "k1": -0.1, "k2": 0.02, "p1": 0.003, "p2": -0.002}
    _, dt = turn_upright(cam, d, orientation)
    assert dt["k1"] == d["k1"] and dt["k2"] == d["k2"]
    m = turned.cam_to_world[:3, :3].T @ cam.cam_to_world[:3, :3]  # stored → upright axes
    xs, ys = rng.uniform(-0.6, 0.6, (2, 50))
    xd, yd = distort(xs, ys, d)
    pts = np.stack([xs, ys, np.ones(50)])
    up = m @ pts
    upd = m @ np.stack([xd, yd, np.ones(50)])
    got = distort(up[0] / up[2], up[1] / up[2], dt)
    np.testing.assert_allclose(got, (upd[0] / upd[2], upd[1] / upd[2]), atol=1e-12)
