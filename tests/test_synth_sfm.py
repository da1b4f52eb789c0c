"""Synthetic scenes, image ingest, pose formats and real pycolmap SfM on a rendered scene."""

import dataclasses
import io
import json
import math
import shutil

import numpy as np
import pytest
from PIL import Image

from cropcraft_core.errors import CropCraftError, InputError
from cropcraft_core.geometry import PinholeCamera
from cropcraft_core.sfm import (
    Poses,
    SfmError,
    export_colmap_text,
    export_transforms_json,
    import_colmap,
    import_transforms_json,
    ingest_images,
    level_poses,
    run_sfm,
    umeyama,
)
from cropcraft_core.sfm import poses as sfm_poses
from cropcraft_core.sfm.ingest import IngestedImage, IngestManifest
from cropcraft_core.sfm.poses import loop_pairs, quaternion_to_rotation, rotation_to_quaternion
from cropcraft_core.synth import make_scene
from cropcraft_core.synth.scene import camera_from_angles


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """12 views at 320 × 240 over a 40° arc of the walk (dense enough for SfM with few views)."""
    out = tmp_path_factory.mktemp("synth") / "soy"
    summary = make_scene("soybean", out, seed=3, views=12, resolution=(320, 240), walk_arc_deg=40.0)
    return out, summary


def _same_camera(a: PinholeCamera, b: PinholeCamera, atol=1e-12):
    assert (a.width, a.height) == (b.width, b.height)
    np.testing.assert_allclose([a.fx, a.fy, a.cx, a.cy], [b.fx, b.fy, b.cx, b.cy], atol=atol)
    np.testing.assert_allclose(a.cam_to_world, b.cam_to_world, atol=atol)


# --------------------------------------------------------------------------- synthetic scene


def test_scene_files(scene):
    out, s = scene
    names = [f"view_{i:03d}" for i in range(12)]
    for n in names:
        assert (out / "images" / f"{n}.jpg").is_file()
        d = np.load(out / "depth" / f"{n}.npy")
        assert d.shape == (240, 320) and d.dtype == np.float32
    for f in ("cameras.txt", "images.txt", "points3D.txt"):
        assert (out / "colmap" / "sparse" / "0" / f).is_file()
    for f in ("transforms.json", "scene.json", "truth/params.json", "truth/metrics.json"):
        json.loads((out / f).read_text())
    assert (out / "truth" / "canopy.ply").stat().st_size > 1000
    meta = json.loads((out / "scene.json").read_text())
    assert meta["crop"] == "soybean" and meta["resolution"] == [320, 240]
    assert meta["world_frame"].startswith("z up")
    lo, hi = meta["camera_height_range_m"]
    assert 1.0 <= lo <= hi <= 1.8
    metrics = json.loads((out / "truth" / "metrics.json").read_text())
    assert metrics["lai"] > 0
    img = np.asarray(Image.open(out / "images" / "view_000.jpg"))
    assert img.shape == (240, 320, 3) and img.std() > 10  # textured, not flat


def test_scene_colours(scene):
    """Soil pixels are brown (a* > 0), canopy pixels green (a* < 0)."""
    import cv2

    out, _ = scene
    img = np.asarray(Image.open(out / "images" / "view_004.jpg"))
    lab = cv2.cvtColor(img, cv2.COLOR_RGB2LAB).astype(float)
    a = lab[..., 1] - 128
    cam = import_colmap(out / "colmap" / "sparse" / "0").camera("view_004.jpg")
    pts = cam.unproject(np.load(out / "depth" / "view_004.npy").astype(np.float64))
    ground = pts[..., 2] < 1e-6
    plant = pts[..., 2] > 0.05
    assert ground.mean() > 0.02 and plant.mean() > 0.2
    assert np.median(a[ground]) > 0 > np.median(a[plant])


def test_depth_consistent_with_camera_and_canopy(scene):
    """Unprojected truth depth lands on the ground plane or on (near) a canopy triangle."""
    out, _ = scene
    from cropcraft_core.export import read_ply

    poses = import_transforms_json(out / "transforms.json")
    cam = poses.camera("view_006.jpg")
    depth = np.load(out / "depth" / "view_006.npy").astype(np.float64)
    assert np.isfinite(depth).all()  # looking down: no sky
    pts = cam.unproject(depth)
    # projecting the points back gives the pixel centres and the depth
    rng = np.random.default_rng(0)
    ij = rng.integers(0, [240, 320], size=(200, 2))
    p = pts[ij[:, 0], ij[:, 1]]
    uv, z = cam.project(p)
    np.testing.assert_allclose(uv, ij[:, ::-1] + 0.5, atol=1e-6)
    np.testing.assert_allclose(z, depth[ij[:, 0], ij[:, 1]], rtol=1e-6)
    # every point is on the ground or on the surface of the canopy
    assert p[:, 2].min() > -1e-4
    above = p[p[:, 2] > 1e-4]
    assert len(above) > 50
    mesh = read_ply(out / "truth" / "canopy.ply")  # plot plants only; test those within it
    import open3d as o3d

    scene_o3d = o3d.t.geometry.RaycastingScene()
    scene_o3d.add_triangles(
        o3d.core.Tensor(mesh.vertices.astype(np.float32)),
        o3d.core.Tensor(mesh.faces.astype(np.uint32)),
    )
    d = scene_o3d.compute_distance(o3d.core.Tensor(above.astype(np.float32))).numpy()
    lo, hi = mesh.vertices[:, :2].min(0) + 0.3, mesh.vertices[:, :2].max(0) - 0.3
    inside = np.all((above[:, :2] > lo) & (above[:, :2] < hi), axis=1)
    assert inside.sum() >= 10
    assert np.median(d[inside]) < 1e-3


def test_trajectories_look_down_and_inward():
    from cropcraft_core.config import default_layout
    from cropcraft_core.synth import drone_trajectory, walk_trajectory

    rng = np.random.default_rng(0)
    lay = default_layout("soybean")
    cams = walk_trajectory(lay, 30, rng, canopy_top=0.6)
    for c in cams:
        fwd = c.cam_to_world[:3, 2]
        assert 1.0 <= c.center[2] <= 1.8
        assert fwd[2] < -math.sin(math.radians(44))
        # the optical axis meets the ground near the plot
        hit = c.center - fwd * c.center[2] / fwd[2]
        assert np.abs(hit[:2]).max() < 2.0
    drone = drone_trajectory(default_layout("maize"), 20, rng, canopy_top=2.0)
    assert all(12.5 < c.center[2] < 13.5 and c.cam_to_world[2, 2] < -0.95 for c in drone)
    # right-handed, orthonormal rotations
    c = camera_from_angles(np.zeros(3), 0.3, 0.9, 0.1, (64, 48), 50)
    r = c.cam_to_world[:3, :3]
    np.testing.assert_allclose(r.T @ r, np.eye(3), atol=1e-12)
    assert np.linalg.det(r) > 0


# --------------------------------------------------------------------------- pose formats


def _random_poses(n=6, seed=0):
    rng = np.random.default_rng(seed)
    views = []
    for i in range(n):
        c = camera_from_angles(
            rng.normal(0, 2, 3), rng.uniform(-3, 3), rng.uniform(-1.5, 1.5),
            rng.uniform(-3, 3), (640, 480), 50,
        )  # fmt: skip
        if i % 2:  # a second set of intrinsics
            c = PinholeCamera(320, 240, 250.5, 251.0, 161.2, 119.7, c.cam_to_world)
        views.append((f"img_{i}.png", c))
    return Poses(tuple(views))


def test_quaternion_round_trip():
    rng = np.random.default_rng(1)
    for _ in range(200):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        q = q if q[0] >= 0 else -q
        r = quaternion_to_rotation(q)
        np.testing.assert_allclose(rotation_to_quaternion(r), q, atol=1e-12)
    # COLMAP's own conversion agrees (pycolmap quat is x, y, z, w)
    import pycolmap

    r = quaternion_to_rotation(q)
    xyzw = pycolmap.Rotation3d(r).quat
    w = np.array([xyzw[3], *xyzw[:3]])
    np.testing.assert_allclose(w * np.sign(w[0]), q, atol=1e-12)


def test_colmap_and_transforms_round_trips(tmp_path):
    poses = _random_poses()
    export_colmap_text(poses, tmp_path / "model")
    back = import_colmap(tmp_path / "model")
    assert back.names == sorted(poses.names)
    for n, c in poses:
        _same_camera(back.camera(n), c, atol=1e-12)
    export_transforms_json(poses, tmp_path / "transforms.json")
    ns = import_transforms_json(tmp_path / "transforms.json")
    for n, c in poses:
        _same_camera(ns.camera(n), c, atol=1e-12)
    # nerfstudio camera axes are OpenGL: the camera looks down its -z axis
    doc = json.loads((tmp_path / "transforms.json").read_text())
    m = np.array(doc["frames"][0]["transform_matrix"])
    np.testing.assert_allclose(-m[:3, 2], poses.cameras[0].cam_to_world[:3, 2], atol=1e-12)
    np.testing.assert_allclose(m[:3, 1], -poses.cameras[0].cam_to_world[:3, 1], atol=1e-12)
    # a transforms.json written on Windows: "images\\view.png" names view.png
    for f in doc["frames"]:
        f["file_path"] = f["file_path"].replace("/", "\\")
    (tmp_path / "windows.json").write_text(json.dumps(doc))
    assert import_transforms_json(tmp_path / "windows.json").names == sorted(poses.names)


def test_scene_formats_agree(scene):
    out, _ = scene
    a = import_colmap(out / "colmap" / "sparse" / "0")
    b = import_transforms_json(out / "transforms.json")
    doc = json.loads((out / "transforms.json").read_text())
    assert {"fl_x", "fl_y", "cx", "cy", "w", "h"} <= set(doc)
    assert a.names == b.names and len(a) == 12
    for n, c in a:
        _same_camera(b.camera(n), c, atol=1e-12)
        # projection of the plot centre agrees between the formats
        uv_a, _ = c.project(np.zeros((1, 3)))
        uv_b, _ = b.camera(n).project(np.zeros((1, 3)))
        np.testing.assert_allclose(uv_a, uv_b, atol=1e-9)


def test_umeyama_recovers_similarity():
    rng = np.random.default_rng(2)
    src = rng.normal(size=(20, 3))
    r = quaternion_to_rotation(rng.normal(size=4))
    dst = 2.5 * src @ r.T + [1.0, -2.0, 0.5]
    s, r2, t = umeyama(src, dst)
    assert s == pytest.approx(2.5)
    np.testing.assert_allclose(r2, r, atol=1e-10)
    np.testing.assert_allclose(t, [1.0, -2.0, 0.5], atol=1e-10)


def test_import_errors(tmp_path):
    with pytest.raises(InputError, match="no COLMAP model"):
        import_colmap(tmp_path)
    (tmp_path / "t.json").write_text('{"frames": [{"file_path": "a.png"}]}')
    with pytest.raises(InputError, match="frame 0"):
        import_transforms_json(tmp_path / "t.json")
    good = {"file_path": "a.png", "transform_matrix": np.eye(4).tolist()}
    head = {"w": 64, "h": 48, "fl_x": 50.0}
    for frame, match in (
        ("a.png", "frame 1 is not a mapping"),
        (None, "frame 1 is not a mapping"),
        ({**good, "k1": "abc"}, "frame 1: distortion k1 must be a number"),
        ({**good, "fl_x": "nan"}, "frame 1: intrinsics must be finite"),
        ({**good, "w": 0}, "frame 1: camera size must be positive"),
        ({**good, "transform_matrix": np.full((4, 4), np.nan).tolist()}, "frame 1: "),
    ):
        doc = {**head, "frames": [good, frame]}
        (tmp_path / "t.json").write_text(json.dumps(doc))
        with pytest.raises(InputError, match=f"t.json {match}"):
            import_transforms_json(tmp_path / "t.json")


def test_imported_poses_follow_the_photos_as_ingested():
    """Poses name the source photos at their own size: renamed to the ingested images, their
    intrinsics scaled where ingest downscaled (``ingest.max_size``); a camera of another size
    than the upright photo (a rotated or cropped one) is named."""
    from tasks.poses import _rename_to_ingested

    cam = PinholeCamera(320, 240, 260.0, 250.0, 160.5, 119.5, np.eye(4))
    poses = Poses(tuple((f"IMG_{i}.JPG", cam) for i in range(3)))
    images = [
        {"name": f"IMG_{i}.png", "source": f"IMG_{i}.JPG", "width": 160, "height": 120,
         "source_width": 320, "source_height": 240}
        for i in range(3)
    ]  # fmt: skip
    out, photoless = _rename_to_ingested(poses, {"images": images}, "poses.json")
    c = out.camera("IMG_1.png")
    assert (c.width, c.height, c.fx, c.fy, c.cx, c.cy) == (160, 120, 130.0, 125.0, 80.25, 59.75)
    assert photoless == []
    # posed at a quarter of the photos' size (nerfstudio's images_4): scaled as ingested
    quarter = PinholeCamera(80, 60, 65.0, 62.5, 40.125, 29.875, np.eye(4))
    small = Poses(tuple((f"IMG_{i}.JPG", quarter) for i in range(3)))
    c = _rename_to_ingested(small, {"images": images}, "poses.json")[0].camera("IMG_1.png")
    assert (c.width, c.height, c.fx, c.fy, c.cx, c.cy) == (160, 120, 130.0, 125.0, 80.25, 59.75)
    cropped = Poses(
        tuple((f"IMG_{i}.JPG", dataclasses.replace(quarter, height=70)) for i in range(3))
    )
    with pytest.raises(InputError, match=r"as 80x70 pixels, but the photo IMG_0.JPG is 320x240"):
        _rename_to_ingested(cropped, {"images": images}, "poses.json")
    # every such photo named at once, not one a rerun (session 92's photos audit)
    with pytest.raises(InputError, match=r"IMG_0.JPG is 320x240 upright \(and 2 more: IMG_1"):
        _rename_to_ingested(cropped, {"images": images}, "poses.json")
    # ... a whole folder of them is named by its first eight, as ingest names bad photos
    many = [{**images[0], "name": f"M{i}.png", "source": f"M{i}.JPG"} for i in range(20)]
    posed = Poses(tuple((f"M{i}.JPG", dataclasses.replace(quarter, height=70)) for i in range(20)))
    with pytest.raises(InputError, match=r"\(and 19 more: M1.JPG .*M7.JPG [^;]*, \.\.\.\)") as e:
        _rename_to_ingested(posed, {"images": many}, "poses.json")
    assert "M8.JPG" not in str(e.value)
    # a Finder copy ("IMG_1 copy.JPG") sorted first and was kept, the posed original dropped
    # as its duplicate: the original's pose is the copy's (session 91's ingest audit)
    copied = [*images[:1], {**images[1], "name": "IMG_1 copy.png", "source": "IMG_1 copy.JPG"}]
    copied += images[2:]
    dup = {"source": "IMG_1.JPG", "duplicate_of": "IMG_1 copy.JPG"}
    ghost = Poses((*poses.views, ("IMG_9.JPG", cam)))  # a frame whose photo is not here
    out, photoless = _rename_to_ingested(ghost, {"images": copied, "duplicates": [dup]}, "t")
    assert out.names == ["IMG_0.png", "IMG_1 copy.png", "IMG_2.png"] and photoless == ["IMG_9.JPG"]
    # accented names as macOS writes them (decomposed) against poses that name them as typed
    # (composed): "0 of them were ingested" for photos plainly there (session 94's folders audit)
    import unicodedata

    nfd = [
        {**im, "source": unicodedata.normalize("NFD", f"été_{i}.JPG")}
        for i, im in enumerate(images)
    ]
    accented = Poses(tuple((unicodedata.normalize("NFC", f"été_{i}.JPG"), cam) for i in range(3)))
    out, photoless = _rename_to_ingested(accented, {"images": nfd}, "t")
    assert out.names == ["IMG_0.png", "IMG_1.png", "IMG_2.png"] and photoless == []
    images[2].update(width=120, height=160, source_width=240, source_height=320)
    with pytest.raises(InputError, match=r"poses.json gives IMG_2.JPG as 320x240 pixels, but"):
        _rename_to_ingested(poses, {"images": images}, "poses.json")
    # ... unless the photo is stored sideways with its EXIF tag saying so (a phone held
    # upright): COLMAP posed the stored pixels, so the camera turns as ingest turned them
    images[2]["exif_orientation"] = 6
    c = _rename_to_ingested(poses, {"images": images}, "poses.json")[0].camera("IMG_2.png")
    assert (c.width, c.height, c.fx, c.fy, c.cx, c.cy) == (120, 160, 125.0, 130.0, 60.25, 80.25)
    np.testing.assert_allclose(c.cam_to_world[:3, 0], [0, -1, 0], atol=1e-12)  # x' = -y
    images[2]["exif_orientation"] = 2  # a mirror image: no camera sees that
    with pytest.raises(InputError, match=r"IMG_2.JPG carries EXIF orientation 2, a mirror"):
        _rename_to_ingested(poses, {"images": images}, "poses.json")


def test_imported_poses_say_whether_sfm_made_them(tmp_path):
    """A COLMAP model (with its points) and a transforms.json that ns-process-data made from
    an SfM project (``applied_transform``) are of arbitrary scale and up; one without it (a
    phone's AR capture, cropcraft synth's) is metric and gravity-aligned."""
    from cropcraft_core.sfm import import_poses

    poses = _random_poses()
    pts = np.random.default_rng(0).normal(size=(25, 3))
    export_colmap_text(poses, tmp_path / "project" / "sparse" / "0", points=pts)
    colmap = import_poses(tmp_path / "project")
    assert colmap.from_sfm and colmap.poses.names == sorted(poses.names)
    np.testing.assert_allclose(np.sort(colmap.points, axis=0), np.sort(pts, axis=0), atol=1e-6)
    export_transforms_json(poses, tmp_path / "ar.json")
    ar = import_poses(tmp_path / "ar.json")
    assert not ar.from_sfm and ar.points is None
    applied = {"applied_transform": np.eye(4)[:3].tolist()}
    export_transforms_json(poses, tmp_path / "sfm.json", extra=applied)
    assert import_poses(tmp_path / "sfm.json").from_sfm
    # ns-process-data releases before applied_transform: COLMAP's image ids on the frames
    doc = json.loads((tmp_path / "ar.json").read_text())
    for i, f in enumerate(doc["frames"]):
        f["colmap_im_id"] = i + 1
    (tmp_path / "old_sfm.json").write_text(json.dumps(doc))
    assert import_poses(tmp_path / "old_sfm.json").from_sfm
    # instant-ngp's colmap2nerf.py: "NeRF sized" poses, a sharpness on every frame (read as
    # metres, a walk's cameras stood 2x too high: session 91's ingest audit)
    doc = json.loads((tmp_path / "ar.json").read_text())
    doc["aabb_scale"] = 32
    for f in doc["frames"]:
        f["sharpness"] = 812.5
    (tmp_path / "ngp.json").write_text(json.dumps(doc))
    assert import_poses(tmp_path / "ngp.json").from_sfm
    # ns-process-data's sparse points beside it, in the poses' frame
    lines = [f"{x:.6f} {y:.6f} {z:.6f}" for x, y, z in pts]
    head = ["ply", "format ascii 1.0", f"element vertex {len(pts)}"]
    head += [f"property float {a}" for a in "xyz"] + ["end_header"]
    (tmp_path / "sparse_pc.ply").write_text("\n".join(head + lines) + "\n")
    export_transforms_json(
        poses, tmp_path / "sfm.json", extra={**applied, "ply_file_path": "sparse_pc.ply"}
    )
    np.testing.assert_allclose(import_poses(tmp_path / "sfm.json").points, pts, atol=1e-5)
    absolute = {**applied, "ply_file_path": str(tmp_path / "sparse_pc.ply")}  # as nerfstudio
    export_transforms_json(poses, tmp_path / "elsewhere" / "abs.json", extra=absolute)
    far = import_poses(tmp_path / "elsewhere" / "abs.json")
    np.testing.assert_allclose(far.points, pts, atol=1e-5)
    # ns-process-data's output folder given as it is: its transforms.json is read
    out = tmp_path / "processed"
    out.mkdir()
    shutil.copy(tmp_path / "sfm.json", out / "transforms.json")
    shutil.copy(tmp_path / "sparse_pc.ply", out / "sparse_pc.ply")
    folder = import_poses(out)
    assert folder.from_sfm and folder.poses.names == sorted(poses.names)
    np.testing.assert_allclose(folder.points, pts, atol=1e-5)
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="no COLMAP model .* and no transforms.json"):
        import_poses(tmp_path / "empty")


# --------------------------------------------------------------------------- ingest


def _png(color, size=(40, 30)):
    rng = np.random.default_rng(sum(color))
    a = np.clip(rng.normal(color, 20, (size[1], size[0], 3)), 0, 255).astype(np.uint8)
    return Image.fromarray(a)


def test_ingest_dedup_manifest_and_exif(tmp_path):
    src = tmp_path / "src"
    src.mkdir()
    for i, col in enumerate([(200, 30, 30), (30, 200, 30), (30, 30, 200)]):
        _png(col).save(src / f"p{i}.png")
    (src / "p0_copy.png").write_bytes((src / "p0.png").read_bytes())
    _png((200, 30, 30)).save(src / "p0_resaved.jpg", quality=100)  # not pixel-identical
    (src / "notes.txt").write_text("field notes")
    # an EXIF-rotated JPEG: stored 40 × 30, orientation 6 (rotate 90° clockwise to view)
    img = _png((120, 120, 20))
    exif = Image.Exif()
    exif[0x0112] = 6
    img.save(src / "rot.jpg", exif=exif.tobytes(), quality=95)
    exif[0x0112] = 9  # outside EXIF's 1-8 (some software writes it): read as stored
    _png((60, 120, 200)).save(src / "nine.jpg", exif=exif.tobytes(), quality=95)
    man = ingest_images(str(src), tmp_path / "out", max_size=32)
    nine = next(im for im in man.images if im.source == "nine.jpg")
    assert nine.exif_orientation == 1 and (nine.source_width, nine.source_height) == (40, 30)
    (src / "nine.jpg").unlink()
    man = ingest_images(str(src), tmp_path / "out", max_size=32)
    assert "in_subfolders" not in man.to_dict()  # a flat folder's manifest: bytes as before
    (src / "more" / "deeper").mkdir(parents=True)  # a second card folder: not read, named
    (src / ".thumbs").mkdir()
    _png((10, 200, 30)).save(src / "more" / "m1.jpg")
    _png((10, 200, 90)).save(src / "more" / "deeper" / "m2.png")
    _png((10, 200, 90)).save(src / ".thumbs" / "t.png")
    man = ingest_images(str(src), tmp_path / "out", max_size=32)
    assert man.in_subfolders == ["more/deeper/m2.png", "more/m1.jpg"]
    assert IngestManifest.read(tmp_path / "out").in_subfolders == man.in_subfolders
    names = man.names
    assert "p0_copy.png" not in names and names.count("p0.png") == 1
    assert man.duplicates == [{"source": "p0_copy.png", "duplicate_of": "p0.png"}]
    assert "notes.txt" in man.ignored
    rot = next(im for im in man.images if im.source == "rot.jpg")
    assert (rot.source_width, rot.source_height) == (30, 40)  # transposed
    assert rot.exif_orientation == 6 and max(rot.width, rot.height) == 32
    with Image.open(tmp_path / "out" / rot.name) as im:
        assert im.size == (24, 32)
    doc = json.loads((tmp_path / "out" / "manifest.json").read_text())
    assert doc["n_images"] == len(names) == 5
    import hashlib

    e = doc["images"][0]
    assert e["sha256_file"] == hashlib.sha256((src / e["source"]).read_bytes()).hexdigest()
    assert len(e["sha256_pixels"]) == 64


def _exif(orientation=None, **sub):
    """EXIF bytes: ``orientation`` in IFD0, ``sub`` ({tag: value}) in the Exif sub-IFD."""
    exif = Image.Exif()
    if orientation:
        exif[0x0112] = orientation
    ifd = exif.get_ifd(0x8769)
    for tag, value in sub.items():
        ifd[int(tag, 16)] = value
    return exif.tobytes()


def test_ingest_reads_the_focal_length_from_exif(tmp_path):
    """``focal_px`` at the written size: a phone's 35 mm equivalent (26 mm on a 40 x 30 photo
    stored sideways, 50 px of diagonal: 26 * 50 / 43.27 = 30.04 px, whatever the orientation;
    downscaled to 32 px it is 24.03); a camera's focal length over its sensor's pixel pitch
    (4 mm at 10 px/mm = 40 px) only where its pixel dimensions are the photo's; none where
    EXIF has none, or an implausible one (500 mm equivalent: 14 x the photo's width)."""
    from tasks.poses import focal_priors

    src = tmp_path / "src"
    src.mkdir()
    plane = {"920A": 4.0, "A20E": 10.0, "A210": 4}
    _png((200, 30, 30)).save(src / "a.jpg", exif=_exif(6, A405=26), quality=95)
    _png((30, 200, 30)).save(src / "b.png", exif=_exif(**plane, A002=40, A003=30))
    _png((30, 30, 200)).save(src / "c.png", exif=_exif(**plane, A002=4000, A003=3000))
    _png((90, 90, 90)).save(src / "d.png")
    _png((10, 90, 190)).save(src / "e.jpg", exif=_exif(A405=500), quality=95)
    man = ingest_images(str(src), tmp_path / "out")
    focal = {im.source: im.focal_px for im in man.images}
    assert focal["a.jpg"] == pytest.approx(26 * 50 / math.hypot(36, 24))
    assert focal["b.png"] == pytest.approx(40.0)
    assert focal["c.png"] is focal["d.png"] is focal["e.jpg"] is None
    small = ingest_images(str(src), tmp_path / "small", max_size=32)
    assert small.images[0].focal_px == pytest.approx(0.8 * focal["a.jpg"])
    doc = json.loads((tmp_path / "small" / "manifest.json").read_text())
    assert focal_priors(doc) == pytest.approx({"a.png": 0.8 * focal["a.jpg"], "b.png": 32.0})
    assert IngestManifest.read(tmp_path / "small") == small


#: ``IngestManifest.identity()`` of the test's three photos, by the code before ``focal_px``.
IDENTITY_BEFORE_FOCAL = "688d2e43e21db1e0a8875002c5e88be885fc2daa2459ca40886996769f85c8e7"


def test_ingest_identity_of_photos_without_exif_focal_is_as_before_it_was_read():
    """Photos whose EXIF gives no focal length key as they did before ingest read focal lengths
    (this hash was computed by the code before that change): stored scenes are not recomputed."""
    images = [
        IngestedImage(
            name=f"p{i}.png",
            source=f"p{i}.jpg",
            sha256_file="f" * 64,
            sha256_pixels=str(i) * 64,
            width=640,
            height=480,
            source_width=1280,
            source_height=960,
            exif_orientation=1,
            scale=0.5,
            format="JPEG",
        )  # fmt: skip
        for i in range(3)
    ]
    man = IngestManifest(source="s", dest_dir="d", max_size=640, images=images)
    assert man.identity() == IDENTITY_BEFORE_FOCAL
    with_focal = dataclasses.replace(images[0], focal_px=500.0)
    assert dataclasses.replace(man, images=[with_focal, *images[1:]]).identity() != man.identity()


def test_ingest_identity_is_what_the_images_are_not_where_they_were_read(tmp_path):
    """The same photos read from another folder, one of them re-saved with new metadata (same
    pixels), give the same identity; a changed photo, a new one or another downscale do not."""
    src, copy = tmp_path / "src", tmp_path / "copy"
    src.mkdir()
    for i, col in enumerate([(200, 30, 30), (30, 200, 30), (30, 30, 200)]):
        _png(col).save(src / f"p{i}.png")
    shutil.copytree(src, copy)
    with Image.open(src / "p1.png") as im:
        im.save(copy / "p1.png", pnginfo=_png_text("Software", "a photo manager"))
    assert (copy / "p1.png").read_bytes() != (src / "p1.png").read_bytes()
    a = ingest_images(str(src), tmp_path / "a")
    b = ingest_images(str(copy), tmp_path / "b")
    assert a.to_dict() != b.to_dict() and a.identity() == b.identity()
    assert ingest_images(str(src), tmp_path / "c", max_size=32).identity() != a.identity()
    _png((31, 200, 30)).save(copy / "p1.png")
    assert ingest_images(str(copy), tmp_path / "d").identity() != a.identity()
    _png((90, 90, 90)).save(src / "p3.png")
    assert ingest_images(str(src), tmp_path / "e").identity() != a.identity()


def _png_text(key, value):
    from PIL import PngImagePlugin

    info = PngImagePlugin.PngInfo()
    info.add_text(key, value)
    return info


def test_ingest_malformed_exif(tmp_path):
    """A photo whose EXIF has one mis-typed tag (the pixels are fine) ingests, turned upright by
    its orientation tag; one whose orientation tag cannot be parsed is an error naming it."""
    src = tmp_path / "src"
    src.mkdir()
    for i in range(2):
        _png((60 * i, 100, 100)).save(src / f"ok{i}.jpg", quality=90)
    exif = Image.Exif()
    exif[0x0112] = 6
    exif[0x010F] = "Canon"
    buf = io.BytesIO()
    _png((120, 120, 20)).save(buf, format="JPEG", exif=exif, quality=95)
    raw = buf.getvalue()
    make = raw.find(b"\x01\x0f\x00\x02")  # big-endian IFD entry: Make (0x010F), ASCII
    orient = raw.find(b"\x01\x12\x00\x03")  # Orientation (0x0112), SHORT
    assert make > 0 and orient > 0
    mistyped = bytearray(raw)
    mistyped[make + 1] = 0x00  # re-tagged as ImageWidth (0x0100) with an ASCII value
    (src / "IMG_1.JPG").write_bytes(bytes(mistyped))
    man = ingest_images(str(src), tmp_path / "o1")
    rot = next(im for im in man.images if im.source == "IMG_1.JPG")
    assert rot.exif_orientation == 6 and (rot.width, rot.height) == (30, 40)
    unparseable = bytearray(raw)
    unparseable[orient + 3] = 0x07  # the orientation's type: SHORT -> UNDEFINED
    (src / "IMG_1.JPG").write_bytes(bytes(unparseable))
    with pytest.raises(InputError, match=r"IMG_1\.JPG.*EXIF"):
        ingest_images(str(src), tmp_path / "o2")


def test_ingest_names_corrupt_and_truncated(tmp_path):
    src = tmp_path / "src"
    src.mkdir()
    for i in range(3):
        _png((50 * i, 100, 100), size=(64, 64)).save(src / f"ok{i}.jpg", quality=90)
    data = (src / "ok0.jpg").read_bytes()
    (src / "trunc.jpg").write_bytes(data[: len(data) // 2])
    with pytest.raises(InputError, match=r"trunc\.jpg"):
        ingest_images(str(src), tmp_path / "o1")
    (src / "trunc.jpg").unlink()
    buf = io.BytesIO()
    _png((10, 10, 10)).save(buf, format="PNG")
    (src / "garbage.png").write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(200))
    with pytest.raises(InputError, match=r"garbage\.png"):
        ingest_images(str(src), tmp_path / "o2")
    (src / "garbage.png").write_bytes(buf.getvalue()[:-30])  # truncated PNG
    with pytest.raises(InputError, match=r"garbage\.png"):
        ingest_images(str(src), tmp_path / "o3")
    (src / "garbage.png").unlink()
    (src / "x.heic").write_bytes(b"ftypheic")
    with pytest.raises(InputError, match=r"x\.heic"):
        ingest_images(str(src), tmp_path / "o4")
    (src / "x.heic").unlink()
    (src / "x.jpg").write_bytes(b"\x00\x00\x00\x18ftypheic\x00\x00\x00\x00mif1heic" + bytes(64))
    with pytest.raises(InputError, match=r"x\.jpg is HEIC whatever its name says"):
        ingest_images(str(src), tmp_path / "o4b")
    (src / "x.jpg").unlink()
    # three bad photos named in one message, not one a night (session 91's season audit)
    (src / "a_empty.jpg").write_bytes(b"")
    (src / "b_cut.png").write_bytes(buf.getvalue()[:-30])
    (src / "c_noise.jpg").write_bytes(bytes(range(256)))
    with pytest.raises(
        InputError,
        match=r"3 of the 6 photos in .* cannot be read: image "
        r"a_empty\.jpg is empty .*; image b_cut\.png .*; image c_noise\.jpg",
    ):
        ingest_images(str(src), tmp_path / "o4c")
    for name in ("a_empty.jpg", "b_cut.png", "c_noise.jpg"):
        (src / name).unlink()
    assert len(ingest_images(f"file://{src}", tmp_path / "o5")) == 3
    with pytest.raises(InputError, match="at least 4"):
        ingest_images(str(src), tmp_path / "o6", min_images=4)
    with pytest.raises(InputError, match="does not exist"):
        ingest_images(str(tmp_path / "nope"), tmp_path / "o7")


def test_ingest_stage_drops_photos_removed_since(tmp_path):
    """SfM and the surfaces read every file in the store's images folder: a photo removed from
    the source between two runs must go from there too, not ride along into the model."""
    from cropcraft_core.store import SceneStore
    from tasks.ingest import ingest

    src = tmp_path / "src"
    src.mkdir()
    for i in range(4):
        _png((60 * i, 100, 100)).save(src / f"p{i}.png")
    scene, store_root = "plotA/soybean/2024-07-01", str(tmp_path / "store")
    first = ingest.fn(store_root, scene, {"min_images": 3}, {}, str(src))
    (src / "p3.png").unlink()
    second = ingest.fn(store_root, scene, {"min_images": 3}, {}, str(src))
    assert (first["summary"]["n_images"], second["summary"]["n_images"]) == (4, 3)
    folder = second["artefacts"]["images"]
    images = [k for k in SceneStore(store_root).list(folder) if k.endswith(".png")]
    assert sorted(k.rsplit("/", 1)[-1] for k in images) == ["p0.png", "p1.png", "p2.png"]


def test_ingest_reads_16_bit_grey_pngs_as_grey_not_white(tmp_path):
    """A NIR or scientific camera's 16-bit greyscale PNG: Pillow's RGB conversion clipped
    every value over 255 to white, so distinct photos all read as one white image (and then
    as duplicates of each other)."""
    src = tmp_path / "src"
    src.mkdir()
    rng = np.random.default_rng(5)
    for i in range(3):
        a = rng.integers(0, 65536, (30, 40)).astype(np.uint16)
        Image.fromarray(a).save(src / f"nir{i}.png")
    man = ingest_images(str(src), tmp_path / "out")
    assert man.names == ["nir0.png", "nir1.png", "nir2.png"] and man.duplicates == []
    with Image.open(src / "nir0.png") as im16, Image.open(tmp_path / "out" / "nir0.png") as im:
        want = np.asarray(im16).astype(np.uint32) >> 8
        got = np.asarray(im.convert("RGB"))
    assert got.shape == (30, 40, 3) and np.array_equal(got[..., 0], want.astype(np.uint8))


def test_ingest_follows_linked_photos_and_sees_them_change(tmp_path):
    """Photos linked into a folder (links into a camera dump, a DVC checkout) are photos:
    both ingest and the input fingerprint read them, the fingerprint by the linked file."""
    from tasks.common import fingerprint

    dump, links = tmp_path / "dump", tmp_path / "links"
    dump.mkdir()
    links.mkdir()
    for i in range(3):
        _png((70 * i, 90, 60)).save(dump / f"p{i}.png")
        (links / f"p{i}.png").symlink_to(dump / f"p{i}.png")
    assert ingest_images(str(links), tmp_path / "out").names == ["p0.png", "p1.png", "p2.png"]
    before = fingerprint(str(links))
    assert sorted(before) == ["p0.png", "p1.png", "p2.png"]
    _png((1, 2, 3), size=(41, 30)).save(dump / "p1.png")  # the linked photo replaced
    assert fingerprint(str(links))["p1.png"] != before["p1.png"]
    # links into a git-annex checkout whose content was never fetched: named, before any
    # work and by ingest; they were dropped without a word (fewer photos, or "no images found"
    # for a folder of them only: session 94's folders audit)
    for i in (7, 8):
        (links / f"p{i}.png").symlink_to(tmp_path / "annex" / f"p{i}.png")
    for read in (fingerprint, lambda src: ingest_images(src, tmp_path / "out2")):
        with pytest.raises(
            InputError, match=r"2 photo\(s\) in .* links whose target is not there: p7"
        ):
            read(str(links))
    # a link to a folder of photos is a folder: its photos named as a subfolder's
    (tmp_path / "card").mkdir()
    (tmp_path / "card" / "photos").symlink_to(dump, target_is_directory=True)
    with pytest.raises(InputError, match="the photos are in 'photos' below it"):
        fingerprint(str(tmp_path / "card"))


def test_photos_named_with_backslashes_are_written_under_names_the_store_keys(tmp_path):
    """A Windows-made zip unpacked here names its photos ``DCIM\\100MEDIA\\DJI_0001.JPG``: the
    run failed on an internal store-key error after decoding every photo (session 94's
    folders audit). The written name is keyable; the source name is kept for the poses."""
    from cropcraft_core.store import _check_key

    src = tmp_path / "src"
    src.mkdir()
    for i in range(3):
        _png((60 * i, 90, 60)).save(src / f"DCIM\\100MEDIA\\DJI_000{i}.png")
    man = ingest_images(str(src), tmp_path / "out")
    assert man.names == [f"DCIM_100MEDIA_DJI_000{i}.png" for i in range(3)]
    assert [im.source for im in man.images] == [f"DCIM\\100MEDIA\\DJI_000{i}.png" for i in range(3)]
    for name in man.names:
        _check_key(f"plotA/soybean/2024-07-01/ingest/images/{name}")
    # ... and a name longer than a file system holds once the store's temporary sibling
    # adds its prefix (249 bytes: legal where it came from) is written shortened, still apart
    long = tmp_path / "long"
    long.mkdir()
    for i in range(3):
        _png((60 * i, 90, 60)).save(long / f"{'写' * 80}_{i}.png")
    man = ingest_images(str(long), tmp_path / "out-long")
    assert len(set(man.names)) == 3
    assert all(len(n.encode()) <= 200 and n.startswith("写") for n in man.names)


def test_ingest_leaves_a_cameras_raw_and_band_files_beside_its_jpegs(tmp_path):
    """A drone's RAW+JPEG mode or a multispectral drone's band TIFFs sit beside the JPEGs:
    ignored and listed, not an error; without any JPEG/PNG they are named, and a phone's
    HEIC (its photos themselves) is named even beside JPEGs. A HEIC added after a run
    changes the input fingerprint, so the rerun reads the folder and names it."""
    from tasks.common import fingerprint

    src = tmp_path / "src"
    src.mkdir()
    for i in range(3):
        _png((60 * i, 120, 80)).save(src / f"DJI_000{i}.JPG", quality=90)
        (src / f"DJI_000{i}.DNG").write_bytes(b"II*\x00raw")
    (src / "DJI_0009.TIF").write_bytes(b"II*\x00band")
    man = ingest_images(str(src), tmp_path / "out")
    assert len(man.names) == 3
    assert {"DJI_0000.DNG", "DJI_0009.TIF"} <= set(man.ignored)
    before = fingerprint(str(src))
    (src / "IMG_1.HEIC").write_bytes(b"ftypheic")
    assert fingerprint(str(src)) != before
    with pytest.raises(InputError, match=r"IMG_1\.HEIC.*convert it"):
        ingest_images(str(src), tmp_path / "out2")
    raw = tmp_path / "raw"
    raw.mkdir()
    (raw / "DJI_0000.DNG").write_bytes(b"II*\x00raw")
    with pytest.raises(InputError, match=r"DJI_0000\.DNG"):
        ingest_images(str(raw), tmp_path / "out3")


def test_ingest_memory_filesystem(tmp_path):
    import fsspec

    fs = fsspec.filesystem("memory")
    for i in range(3):
        buf = io.BytesIO()
        _png((60 * i, 80, 90)).save(buf, format="PNG")
        fs.pipe(f"/plot7/im{i}.png", buf.getvalue())
    man = ingest_images("memory://plot7", tmp_path / "out")
    assert man.names == ["im0.png", "im1.png", "im2.png"]


# --------------------------------------------------------------------------- SfM


def _check_sfm(result, truth: Poses, n_views: int):
    assert result.registered_fraction >= 0.95
    assert result.n_registered >= math.ceil(0.95 * n_views)
    assert result.mean_reprojection_error_px < 1.0
    assert len(result.points) > 100 and result.colors.shape == result.points.shape
    names = result.poses.names
    src = np.array([result.poses.camera(n).center for n in names])
    dst = np.array([truth.camera(n).center for n in names])
    s, r, t = umeyama(src, dst)
    resid = np.linalg.norm(s * src @ r.T + t - dst, axis=1)
    spread = np.linalg.norm(dst - dst.mean(0), axis=1).max()
    assert resid.max() < 0.02 * max(spread, 0.5)  # < 1 cm on a ~0.5-1 m baseline
    # orientations agree after the alignment
    for n in names:
        ra = r @ result.poses.camera(n).cam_to_world[:3, :3]
        rb = truth.camera(n).cam_to_world[:3, :3]
        ang = math.degrees(math.acos(np.clip((np.trace(ra.T @ rb) - 1) / 2, -1, 1)))
        assert ang < 0.5
    return resid


def _sfm_scene(tmp_path, views, arc, seed):
    out = tmp_path / f"soy{views}"
    make_scene(
        "soybean", out, seed=seed, views=views, resolution=(640, 480), walk_arc_deg=arc,
        metrics=False,
    )  # fmt: skip
    return out, import_colmap(out / "colmap" / "sparse" / "0")


def test_sfm_of_two_captures_that_share_nothing_names_their_separate_models(tmp_path):
    """Two short walks over different plots (a drone's flight lines without side overlap are
    the real case): SfM registers every photo, in separate models; the error said the photos
    outside the largest were "not registered", which sent users looking for bad photos."""
    a, _ = _sfm_scene(tmp_path / "a", 8, 20.0, seed=5)
    b, _ = _sfm_scene(tmp_path / "b", 8, 20.0, seed=9)
    both = tmp_path / "both"
    both.mkdir()
    for tag, out in (("a", a), ("b", b)):
        for p in sorted((out / "images").iterdir()):
            shutil.copy(p, both / f"{tag}_{p.name}")
    noise = np.random.default_rng(1).integers(0, 255, (120, 160, 3), dtype=np.uint8)
    Image.fromarray(noise).resize((640, 480), Image.NEAREST).save(both / "z_noise.png")
    with pytest.raises(SfmError, match=r"built 2 separate models \(8, 8 images\) that share") as e:
        run_sfm(both, tmp_path / "work", num_threads=2)
    # a photo in neither model is named as such (session 92's photos audit: 19 of 24 in none
    # read as two parts that do not overlap)
    assert "and 1 are in none (z_noise.png): the photos of one part do not" in str(e.value)


def test_sfm_small_scene(tmp_path):
    """Real pycolmap SfM, kept as fast as it can be: 8 views at 640 × 480 along 20° of the walk
    (at 320 × 240 the canopy's SIFT features are too few to register such a short capture)."""
    out, truth = _sfm_scene(tmp_path, 8, 20.0, seed=5)
    # a focal-length prior 3 % off (as from EXIF); bundle adjustment refines it
    f0 = 1.03 * truth.cameras[0].fx
    res = run_sfm(out / "images", tmp_path / "work", num_threads=2, focal_length_px=f0)
    assert res.matcher == "exhaustive"
    _check_sfm(res, truth, 8)
    assert res.camera_params[0] == pytest.approx(truth.cameras[0].fx, rel=0.05)
    assert (tmp_path / "work" / "model" / "images.txt").is_file()
    # levelled by the real sparse points (a 20° arc: the cameras alone would tilt it): z up,
    # metres from the camera-height hint
    true_h = float(np.median([c.center[2] for c in truth.cameras]))
    levelled, _, frame = level_poses(res.poses, res.points, camera_height_m=true_h)
    assert frame.up_source == "sparse_points"
    names = levelled.names
    s, r, _ = umeyama(levelled.centers(), np.array([truth.camera(n).center for n in names]))
    assert math.degrees(math.acos(min(1.0, r[2, 2]))) < 3.0
    assert s == pytest.approx(1.0, abs=0.1)
    # the same photos among more unrelated ones: fewer than half registered is a named failure
    mixed = tmp_path / "mixed"
    shutil.copytree(out / "images", mixed)
    rng = np.random.default_rng(1)
    for i in range(9):
        noise = rng.integers(0, 255, (120, 160, 3), dtype=np.uint8)
        Image.fromarray(noise).resize((640, 480), Image.NEAREST).save(mixed / f"z_noise{i}.png")
    with pytest.raises(SfmError, match=r"registered only 8 of 17 images \(47 %, need 50 %\)"):
        run_sfm(mixed, tmp_path / "work-mixed", num_threads=2, focal_length_px=f0)
    # every other shot held upright (ingest turns it so: 480 x 640): COLMAP's one camera
    # skipped every photo of the second size; one camera per size registers them all
    upright = tmp_path / "upright"
    upright.mkdir()
    for i, p in enumerate(sorted((out / "images").iterdir())):
        with Image.open(p) as im:
            im = im.transpose(Image.Transpose.ROTATE_90) if i % 2 else im.copy()
        im.save(upright / f"{p.stem}.png")
    # ... each camera from its photos' EXIF focal lengths (one photo without: it shares them)
    names = sorted(p.name for p in upright.iterdir())
    exif = {n: f0 * (1 + 0.01 * (i % 3)) for i, n in enumerate(names) if i != 2}
    res = run_sfm(upright, tmp_path / "work-upright", num_threads=2, focal_priors=exif)
    assert res.n_registered == 8
    assert res.focal_priors == pytest.approx(
        {n: f0 * (1.01 if i % 2 else 1.0) for i, n in enumerate(names)}
    )  # medians: landscape 0, 4, 6 (1.0, 1.01, 1.0), upright 1, 3, 5, 7 (1.01, 1.0, 1.02, 1.01)
    sizes = {(c.width, c.height) for c in res.poses.cameras}
    assert sizes == {(640, 480), (480, 640)}
    for c in res.poses.cameras:  # each size's camera refined from the prior, centred on it
        assert c.fx == pytest.approx(truth.cameras[0].fx, rel=0.05)
        assert (c.cx, c.cy) == pytest.approx((c.width / 2, c.height / 2), abs=0.05 * c.width)


def test_sfm_stage_starts_each_camera_from_the_photos_exif_focal_length(tmp_path):
    """Through the ingest and poses stages: the phone's 35 mm equivalent (a whole number of
    mm, so 0.6 % off here) read at ingest is the camera's prior, which bundle adjustment
    refines to the truth; the summary says so. A photo without EXIF shares its camera's."""
    from tasks.ingest import ingest
    from tasks.poses import poses

    out, truth = _sfm_scene(tmp_path, 8, 20.0, seed=5)
    src = tmp_path / "phone"
    src.mkdir()
    diag = math.hypot(640, 480)
    f35 = round(truth.cameras[0].fx * math.hypot(36, 24) / diag)
    for i, p in enumerate(sorted((out / "images").iterdir())):
        with Image.open(p) as im:
            im.save(src / p.name, quality=95, exif=_exif(A405=f35) if i else b"")
    scene, root = "plotA/soybean/2024-07-01", str(tmp_path / "store")
    ing = ingest.fn(root, scene, {"min_images": 3}, {}, str(src))
    assert ing["summary"]["n_focal_exif"] == 7
    rec = poses.fn(root, scene, {"num_threads": 2}, {"ingest": ing})
    prior = f35 * diag / math.hypot(36, 24)
    assert rec["summary"]["n_focal_prior"] == 8 == rec["summary"]["n_registered"]
    assert rec["summary"]["focal_prior_px"] == [pytest.approx(prior, abs=0.01)]
    assert rec["summary"]["camera_params"][0] == pytest.approx(truth.cameras[0].fx, rel=0.01)


def test_sfm_closes_the_loop_before_matching_the_unplaced_images(tmp_path, monkeypatch):
    """``auto`` matching's three passes through real pycolmap: the neighbours in name order,
    then the pairs round the end of the order (the list pycolmap imports), then each image
    outside the largest model with every other, mapping again only after a pass that verified a
    pair reaching such an image. Here 8 views and one frame of noise (a drone's take-off shot),
    the auto threshold lowered to them: the noise frame is matched with the 8 others, not every
    pair of all 9 (a 500-photo flight's 25 such frames cost ~3 h of every-pair matching and a
    mapping per pass: session 94's drone audit), and no pass maps again for it."""
    import pycolmap

    out, truth = _sfm_scene(tmp_path, 8, 20.0, seed=5)
    noise = np.random.default_rng(1).integers(0, 255, (120, 160, 3), dtype=np.uint8)
    Image.fromarray(noise).resize((640, 480), Image.NEAREST).save(out / "images" / "z_noise.png")
    monkeypatch.setattr(sfm_poses, "EXHAUSTIVE_MAX_IMAGES", 4)
    mappings = []
    real = pycolmap.incremental_mapping

    def counted(*args, **kwargs):
        mappings.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(pycolmap, "incremental_mapping", counted)
    said = []
    res = run_sfm(
        out / "images", tmp_path / "work", num_threads=2, sequential_overlap=3,
        focal_length_px=1.03 * truth.cameras[0].fx, progress=lambda *a: said.append(a),
    )  # fmt: skip
    assert res.matcher == "sequential+loop+unplaced" and len(mappings) == 1
    # each step said as it starts and ends, the mapping by the images it registers (at 500
    # photos SfM ran ~36 min without a line: session 94's drone audit)
    steps = [s for s, f in said if f == 0.0]
    assert steps == [
        "features", "matching (sequential)", "mapping", "matching (loop)", "matching (unplaced)"
    ]  # fmt: skip
    mapped = [f for s, f in said if s == "mapping"]
    assert mapped == sorted(mapped) and mapped[-1] == 1.0 and 0.5 < mapped[-2] < 1.0
    assert {"matching_sequential", "matching_loop", "matching_unplaced"} <= set(res.seconds)
    names = sorted(p.name for p in (out / "images").iterdir())
    listed = (tmp_path / "work" / "loop_pairs.txt").read_text().split("\n")
    assert listed[:-1] == [f"{names[a]} {names[b]}" for a, b in loop_pairs(9, 3)]
    listed = (tmp_path / "work" / "unplaced_pairs.txt").read_text().split("\n")[:-1]
    assert sorted(listed) == sorted(f"{n} z_noise.png" for n in names[:-1])
    assert sorted(res.poses.names) == names[:-1]  # the 8 views, as well as before
    _check_sfm(dataclasses.replace(res, registered_fraction=8 / 8), truth, 8)  # noise aside


def test_completion_pairs_match_the_unplaced_with_every_other_image():
    """By hand: 10 images, 8 and 9 unplaced: each with the 9 others, the pair (8, 9) once (17
    of 45 pairs); where those would be most of all pairs (7, 8, 9: 24 of 45), None (every
    pair)."""
    pairs = sfm_poses.completion_pairs(10, [8, 9])
    assert pairs == sorted({(a, 8) for a in range(8)} | {(a, 9) for a in range(9)})
    assert len(pairs) == 17
    assert sfm_poses.completion_pairs(10, [7, 8, 9]) is None
    assert sfm_poses.completion_pairs(500, list(range(25)))[-1] == (24, 499)
    assert len(sfm_poses.completion_pairs(500, list(range(25)))) == 12_175


def test_loop_pairs_take_sequential_matching_round_the_end():
    """By hand, 6 images and 2 neighbours (steps 1, 2; the quadratic steps 1, 2 are the same):
    4 -> 0, 5 -> 0, 5 -> 1 wrap round the end; 10 images and 3 neighbours add step 4 (the
    quadratic 2**2): 6..9 -> 0..3 by 4, 7..9 -> 0..2 by 3, 8, 9 -> 0, 1 by 2, 9 -> 0 by 1. Too few
    images for a loop beyond the sequential pairs: none."""
    assert loop_pairs(6, 2) == [(0, 4), (0, 5), (1, 5)]
    assert loop_pairs(10, 3) == [
        (0, 6), (0, 7), (0, 8), (0, 9), (1, 7), (1, 8), (1, 9), (2, 8), (2, 9), (3, 9),
    ]  # fmt: skip
    assert loop_pairs(5, 2) == [] and loop_pairs(21, 10) == []


@pytest.mark.slow
def test_sfm_longer_walk_both_matchers(tmp_path):
    """16 views along 60° of the walk; exhaustive and sequential matching, no focal prior."""
    out, truth = _sfm_scene(tmp_path, 16, 60.0, seed=7)
    res = run_sfm(out / "images", tmp_path / "w1", num_threads=2)
    _check_sfm(res, truth, 16)
    res = run_sfm(out / "images", tmp_path / "w2", matcher="sequential", num_threads=2)
    assert res.matcher == "sequential"
    _check_sfm(res, truth, 16)


def test_sfm_errors(tmp_path):
    d = tmp_path / "imgs"
    d.mkdir()
    _png((10, 20, 30)).save(d / "a.png")
    with pytest.raises(InputError, match="at least 3"):
        run_sfm(d, tmp_path / "w")
    rng = np.random.default_rng(0)
    for i in range(4):  # unrelated noise images: nothing to reconstruct
        Image.fromarray(rng.integers(0, 255, (120, 160, 3), dtype=np.uint8)).save(d / f"n{i}.png")
    with pytest.raises(SfmError) as e:
        run_sfm(d, tmp_path / "w")
    assert isinstance(e.value, CropCraftError)
    with pytest.raises(InputError, match="unknown matcher"):
        run_sfm(d, tmp_path / "w", matcher="vocab")
    kept = tmp_path / "kept"
    kept.mkdir()
    (kept / "database.db").write_bytes(b"an earlier run's")
    for bad in (0.0, -0.01, float("nan")):
        with pytest.raises(InputError, match="sift_peak_threshold must be positive"):
            run_sfm(d, kept, sift_peak_threshold=bad)
    assert (kept / "database.db").read_bytes() == b"an earlier run's"  # checked before any work


def test_a_scene_made_again_in_its_folder_replaces_the_earlier_one(tmp_path):
    """Three views after five in the same folder: the folder holds the second scene alone
    (the first one's view_003/004 stayed beside it, and without metrics its truth)."""
    kw = dict(resolution=(64, 48), shadows=False, walk_arc_deg=40, supersample=1)
    make_scene("soybean", tmp_path, seed=1, views=5, metrics=True, **kw)
    (tmp_path / "notes.txt").write_text("mine")
    make_scene("soybean", tmp_path, seed=2, views=3, metrics=False, **kw)
    assert sorted(p.name for p in (tmp_path / "images").iterdir()) == [
        f"view_{i:03d}.jpg" for i in range(3)
    ]
    assert len(list((tmp_path / "depth").iterdir())) == 3
    assert not (tmp_path / "truth" / "metrics.json").exists()  # seed 1's truth is gone
    assert json.loads((tmp_path / "truth" / "params.json").read_text())["seed"] == 2
    assert (tmp_path / "notes.txt").read_text() == "mine"  # not a scene's file: left alone


@pytest.mark.parametrize(
    "bad, match",
    [
        ({"supersample": 1.5}, "supersample must be a whole number"),
        ({"resolution": (float("nan"), 48)}, "resolution must be two whole numbers"),
        ({"views": 2.7}, "whole number of views"),
        ({"vfov_deg": 120.0}, "vfov_deg 120.0 at 64x48 sees above the horizon"),
        ({"drone_height_m": 300.0, "trajectory": "drone"}, "drone height must be 1-120 m"),
        ({"gps_noise_m": -1.0}, "GPS noise must be 0-50 m"),
        ({"drone_height_m": 20.0}, "a drone height is for the drone trajectory, not the walk"),
    ],
)
def test_make_scene_names_a_bad_setting(tmp_path, bad, match):
    kw = dict(resolution=(64, 48), shadows=False, walk_arc_deg=40, supersample=1, views=2)
    with pytest.raises(CropCraftError, match=match):
        make_scene("soybean", tmp_path, metrics=False, **{**kw, **bad})


def test_make_scene_refuses_bad_arguments_before_it_replaces_a_scene(tmp_path):
    """A scene already in the folder stays whole when the new one is refused: a bad seed or
    walk arc (checked after the old files were removed: all 15 lost), and a plot too large
    for a walk, whose views looking down 45-70 degrees from its edge miss its centre (a
    6 m plot: none of 50 saw it; more than 3 m a side is refused)."""
    import dataclasses

    from cropcraft_core.config import default_layout
    from cropcraft_core.errors import ConfigError

    out = tmp_path / "scene"
    make_scene("soybean", out, views=2, resolution=(32, 24), metrics=False, supersample=1)
    before = {p: p.read_bytes() for p in out.rglob("*") if p.is_file()}
    big = dataclasses.replace(default_layout("soybean"), plot_width=6.0, plot_length=6.0)
    for kw, match in (
        ({"seed": -1}, "seed must be a whole number"),
        ({"walk_arc_deg": 0.0}, "walk arc must be in"),
        ({"layout": big, "views": 20}, r"6 x 6 m plot is too large for the walk trajectory"),
    ):
        args = {"views": 2, "resolution": (32, 24), "metrics": False, **kw}
        with pytest.raises(ConfigError, match=match):
            make_scene("soybean", out, **args)
        assert {p: p.read_bytes() for p in out.rglob("*") if p.is_file()} == before


def test_photos_without_an_imported_pose_are_named_and_too_few_poses_refused(
    tmp_path, caplog, capsys
):
    """A photo added after the capture was posed was dropped without a word (the report's
    "registered 12 of 13" the only trace), and poses covering 3 of 50 photos reconstructed
    from 3: the poses stage now names the photos it leaves out, and refuses poses of fewer
    than half of them, as SfM registering fewer is refused."""
    import logging

    from flows.service_cli import _print_left_out
    from tasks.ingest import ingest
    from tasks.poses import poses

    out = tmp_path / "scene"
    make_scene("soybean", out, views=4, resolution=(64, 48), metrics=False, supersample=1)
    photos = tmp_path / "photos"
    shutil.copytree(out / "images", photos)
    _png((200, 30, 30), size=(64, 48)).save(photos / "late.png")
    scene, root = "plotA/soybean/2024-07-01", str(tmp_path / "store")
    ing = ingest.fn(root, scene, {"min_images": 3}, {}, str(photos))
    log = logging.getLogger("cropcraft")  # the stage's logger outside a Prefect run
    log.addHandler(caplog.handler)
    try:
        rec = poses.fn(root, scene, {}, {"ingest": ing}, str(out / "transforms.json"))
    finally:
        log.removeHandler(caplog.handler)
    assert rec["summary"]["unposed"] == ["late.png"] and rec["summary"]["n_registered"] == 4
    assert "1 of 5 photos have no pose" in caplog.text and "late.png" in caplog.text
    assert "photoless_poses" not in rec["summary"]
    # the other way round: a pose whose photo is not here (a folder of the capture's best)
    culled = tmp_path / "culled"
    shutil.copytree(out / "images", culled)
    next(iter(sorted(culled.iterdir()))).unlink()
    ing = ingest.fn(root, scene, {"min_images": 3}, {}, str(culled))
    log.addHandler(caplog.handler)
    try:
        rec = poses.fn(root, scene, {}, {"ingest": ing}, str(out / "transforms.json"))
    finally:
        log.removeHandler(caplog.handler)
    assert rec["summary"]["photoless_poses"] == 1 and rec["summary"]["n_registered"] == 3
    assert "1 of the 4 poses in" in caplog.text
    assert "have no photo among the 3 ingested: view_000" in caplog.text
    ing = ingest.fn(root, scene, {"min_images": 3}, {}, str(photos))
    for i in range(4):
        _png((10 * i, 90, 30), size=(64, 48)).save(photos / f"later{i}.png")
    ing = ingest.fn(root, scene, {"min_images": 3}, {}, str(photos))
    with pytest.raises(InputError, match=r"cover 4 of the 9 photos \(e\.g\. without a pose"):
        poses.fn(root, scene, {}, {"ingest": ing}, str(out / "transforms.json"))
    _print_left_out({"photos_left_out": {"unposed": ["late.png"], "outside_box": []}})
    said = capsys.readouterr().out
    assert said == "WARNING  1 photo(s) have no pose in the imported poses, left out: late.png\n"


def test_a_drone_capture_filed_under_the_wrong_crop_is_told_where_its_ground_went(tmp_path):
    """Maize drone photos with metric poses (no points) run as soybean: the ground was placed
    soybean's 1.4 m below the 13 m cameras, the scene box missed the plot, and the run failed
    on "no view has a usable depth map" with no word of the ground, the crop or the setting
    that places it (session 90's maize audit). Filed as maize, the poses keep their ground."""
    from tasks.ingest import ingest
    from tasks.poses import poses
    from tasks.surfaces import surfaces

    out = tmp_path / "scene"
    make_scene(
        "maize", out, views=6, resolution=(64, 48), trajectory="drone", metrics=False,
        supersample=1,
    )  # fmt: skip
    root, photos, posed = str(tmp_path / "store"), str(out / "images"), str(out / "transforms.json")
    recs = {}
    for crop in ("maize", "soybean"):
        scene = f"plotM/{crop}/2024-07-01"
        ing = ingest.fn(root, scene, {"min_images": 3}, {}, photos)
        recs[crop] = {"ingest": ing, "poses": poses.fn(root, scene, {}, {"ingest": ing}, posed)}
    assert recs["maize"]["poses"]["summary"]["frame"]["ground_source"] == "input_frame"
    assert recs["soybean"]["poses"]["summary"]["frame"]["ground_source"] == "prior"
    hint = (
        r"placed 1\.4 m below the cameras \(poses\.prior_camera_height, soybean's usual "
        r"capture height\).*check the crop \(maize's ~13 m\)"
    )
    with pytest.raises(CropCraftError, match=hint):
        surfaces.fn(root, "plotM/soybean/2024-07-01", {"bbox": "auto"}, recs["soybean"])


def test_photos_of_one_size_through_two_lenses_get_a_camera_each():
    """Two phones of the same resolution (or a phone's main and telephoto cameras) shared one
    SfM camera started at the median of both focal lengths, 25 % off each (session 92's photos
    audit): split by lens where their EXIF focal lengths part by over LENS_RATIO; one lens's
    jitter stays one camera, and photos without EXIF join the one lens there is."""
    from cropcraft_core.sfm.poses import _by_lens

    names = [f"v{i}.jpg" for i in range(6)]
    two = {n: (258.9 if i % 2 == 0 else 388.3) for i, n in enumerate(names)}
    assert _by_lens(names, two) == [names[0::2], names[1::2]]
    jitter = {n: 300.0 * (1 + 0.01 * i) for i, n in enumerate(names[:5])}
    assert _by_lens(names, jitter) == [names]  # v5 has none: it joins
    del two["v5.jpg"]
    assert _by_lens(names, two) == [names[0::2], ["v1.jpg", "v3.jpg"], ["v5.jpg"]]
    assert _by_lens(names, None) == [names] == _by_lens(names, {})
