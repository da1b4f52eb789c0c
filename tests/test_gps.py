"""The photos' GPS positions: read at ingest, and the metric scale of SfM poses from them."""

import json
import math

import numpy as np
import pytest
from PIL import Image

from cropcraft_core.errors import InputError
from cropcraft_core.sfm import ingest_images
from cropcraft_core.sfm.gps import gps_scale, to_enu
from cropcraft_core.synth import make_scene
from cropcraft_core.synth.scene import GPS_ORIGIN, _gps_exif


def _lla(enu: np.ndarray) -> np.ndarray:
    import pycolmap

    t = pycolmap.GPSTransform(pycolmap.GPSTransformEllipsoid.WGS84)
    return np.asarray(t.enu_to_ellipsoid(np.asarray(enu, float), *GPS_ORIGIN))


def _flight(n=60, side=8.0, height=25.0):
    """A lawnmower flight's camera centres (m), in capture order."""
    lines, out = 6, []
    for k in range(lines):
        xs = np.linspace(-side / 2, side / 2, n // lines)[:: 1 if k % 2 == 0 else -1]
        out += [[x, -side / 2 + side * k / (lines - 1), height] for x in xs]
    return np.array(out)


def _sfm_frame(true: np.ndarray, scale: float = 0.137) -> np.ndarray:
    """The same centres as SfM returns them: turned, moved and ``scale`` of a metre a unit."""
    a = 0.7
    r = np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1.0]])
    r = r @ np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])
    return scale * true @ r.T + [4.0, -2.0, 7.0]


def test_enu_of_a_thousandth_of_a_degree_north_and_east():
    """At 40.0646 deg N on WGS84 (by hand: the meridian's radius of curvature 6,361,879 m, the
    prime vertical's 6,387,002 m times cos 40.0646 = 4,888,093 m), 0.001 deg of latitude is
    111.03 m north and of longitude 85.31 m east; an altitude 10 m higher is 10 m up. Bad
    positions are named."""
    lat, lon, alt = GPS_ORIGIN
    enu = to_enu([[lat, lon, alt], [lat + 0.001, lon, alt], [lat, lon + 0.001, alt + 10]])
    d = enu - enu[0]
    assert d[1] == pytest.approx([0, 111.03, 0], abs=0.01)
    assert d[2] == pytest.approx([85.315, 0, 10], abs=0.01)
    with pytest.raises(InputError, match="latitude"):
        to_enu([[91.0, 0.0, 0.0]])
    with pytest.raises(InputError, match="finite"):
        to_enu([[float("nan"), 0.0, 0.0]])


def test_a_flight_with_rtk_positions_sets_the_scale():
    """Fixes 2 cm off (an RTK drone's) on an 8 m flight: the scale to 0.5 %, with its error."""
    true = _flight()
    rng = np.random.default_rng(0)
    g = gps_scale(_sfm_frame(true), _lla(true + rng.normal(0, 0.02, true.shape) + [3, 1, -2]))
    assert g.used and g.scale == pytest.approx(1 / 0.137, rel=0.005)
    assert g.n_photos == g.n_inliers == 60 and g.relative_se < 0.01
    assert g.residual_m < 0.05 and g.spread_m == pytest.approx(4.0, rel=0.2)
    assert json.loads(json.dumps(g.summary()))["used"] is True


def test_fixes_that_jumped_are_left_out():
    """Two fixes 30 m off (a lost lock) among 60: the other 58 set the scale."""
    true = _flight()
    noisy = true + np.random.default_rng(1).normal(0, 0.02, true.shape)
    noisy[[10, 40]] += [30.0, -20.0, 5.0]
    g = gps_scale(_sfm_frame(true), _lla(noisy))
    assert g.used and g.n_inliers == 58 and g.scale == pytest.approx(1 / 0.137, rel=0.005)


@pytest.mark.parametrize(
    "centres, noise, says",
    [
        # a phone's GPS (3 m) round a 1.5 m walk: most fixes fit no similarity
        ("walk", 3.0, r"only \d+ of 50 photos' GPS positions agree"),
        # consumer GPS (0.5 m) over the same walk: a scale, but uncertain by far more than 3 %
        ("walk", 0.5, r"spread .* uncertain by [\d.]+ % \(at most 3 % is used\)"),
        # consumer GPS (1 m) over a small plot's 8 m flight
        ("flight", 1.0, r"uncertain by [\d.]+ %"),
    ],
)
def test_positions_that_spread_too_little_against_their_error_are_not_used(centres, noise, says):
    if centres == "walk":
        a = np.linspace(0, 2 * math.pi, 50, endpoint=False)
        true = np.c_[1.5 * np.cos(a), 1.5 * np.sin(a), np.full(50, 1.5)]
    else:
        true = _flight()
    rng = np.random.default_rng(2)
    g = gps_scale(_sfm_frame(true), _lla(true + rng.normal(0, noise, true.shape)))
    assert not g.used and g.scale is None
    assert g.reason and __import__("re").search(says, g.reason), g.reason


@pytest.mark.parametrize("case", ["drift", "two flights"])
def test_fixes_stretched_against_their_cameras_are_not_used(case):
    """A bias every photo shares escapes the jackknife (a helper's audit: 8-15 % scale errors
    accepted at a reported 2-3 %): consumer GPS drifting 1.5 m through an 8 m lawnmower flight
    (time runs across its lines, so the flight is stretched across them), and two flights at
    12 and 25 m merged, the second's altitudes 2 m off the first's. Refused as stretched."""
    true = _flight()
    rng = np.random.default_rng(4)
    fixes = true + rng.normal(0, 0.02, true.shape)
    if case == "drift":
        fixes[:, 1] += np.linspace(0.0, 1.5, len(true))
    else:
        low = _flight(height=12.0)
        true = np.vstack([true, low])
        fixes = np.vstack([fixes, low + rng.normal(0, 0.02, low.shape) + [0.0, 0.0, 2.0]])
    g = gps_scale(_sfm_frame(true), _lla(fixes))
    assert not g.used and g.anisotropy > 0.03, g
    assert "stretched" in g.reason and "drifting through the flight" in g.reason


def test_one_stale_fix_or_one_line_of_cameras_is_named():
    true = _flight()
    g = gps_scale(_sfm_frame(true), _lla(np.zeros_like(true) + [1.0, 2.0, 3.0]))
    assert not g.used and "all 60 photos carry the same GPS position" in g.reason
    line = np.c_[np.linspace(-5, 5, 30), np.zeros(30), np.full(30, 25.0)]
    g = gps_scale(_sfm_frame(line), _lla(line))
    assert not g.used and "the cameras lie on one line" in g.reason


def test_too_few_positions_and_mismatched_counts():
    true = _flight()[:5]
    g = gps_scale(_sfm_frame(true), _lla(true))
    assert not g.used and "5 posed photos carry a GPS position; at least 8" in g.reason
    with pytest.raises(InputError, match="5 camera centres for 4 GPS positions"):
        gps_scale(_sfm_frame(true), _lla(true)[:4])


def test_ingest_reads_the_gps_position_from_exif(tmp_path):
    """``gps`` [lat, lon, alt] as the camera wrote it (degrees, minutes, seconds; south and west
    negative; below sea level negative), in the manifest and its identity; none where a tag
    is missing or the position is the (0, 0) placeholder, and those photos' manifest entries
    and identity are as before GPS was read."""
    src = tmp_path / "src"
    src.mkdir()
    img = Image.fromarray(np.full((30, 40, 3), 120, np.uint8))
    places = {
        "a.jpg": [40.0646, -88.1963, 250.5],
        "b.png": [-33.9249, 18.4241, -3.25],
        "c.jpg": [0.0, 0.0, 10.0],
    }
    for i, (name, lla) in enumerate(places.items()):
        px = np.asarray(img).copy()
        px[0, 0] = i  # distinct pixels: not duplicates
        Image.fromarray(px).save(src / name, exif=_gps_exif(np.array(lla)))
    Image.fromarray(np.full((30, 40, 3), 9, np.uint8)).save(src / "d.png")
    # tags as some cameras write them: the altitude's ref a number (0: above sea level)
    exif = Image.Exif()
    g = exif.get_ifd(0x8825)
    g.update({1: "S", 2: (33.0, 55.0, 29.64), 3: "E", 4: (18.0, 25.0, 26.676), 5: 0, 6: 12.5})
    Image.fromarray(np.full((30, 40, 3), 200, np.uint8)).save(src / "e.png", exif=exif.tobytes())
    places["e.png"] = [-33.9249, 18.424077, 12.5]
    man = ingest_images(str(src), tmp_path / "out")
    gps = {im.source: im.gps for im in man.images}
    assert gps["a.jpg"] == pytest.approx(places["a.jpg"], abs=1e-9)
    assert gps["b.png"] == pytest.approx(places["b.png"], abs=1e-9)
    assert gps["e.png"] == pytest.approx(places["e.png"], abs=1e-6)
    assert gps["c.jpg"] is gps["d.png"] is None
    doc = json.loads((tmp_path / "out" / "manifest.json").read_text())
    assert [("gps" in im) for im in doc["images"]] == [True, True, False, False, True]
    without = [im for im in man.images if im.gps is None]
    import dataclasses

    plain = dataclasses.replace(man, images=without)
    assert all("gps" not in im for im in plain.to_dict()["images"])
    assert (
        man.identity()
        != dataclasses.replace(
            man, images=[dataclasses.replace(im, gps=None) for im in man.images]
        ).identity()
    )


def test_signed_degrees_take_their_sign_from_the_ref_or_themselves():
    """A camera writing degrees as signed rationals (-33 deg 55' with ref S) is 33.92 deg S,
    not 32.08; without a ref its own sign stands."""
    from cropcraft_core.sfm.ingest import _gps_degrees

    assert _gps_degrees((-33, 55, 29.64), "S", "S") == pytest.approx(-33.9249)
    assert _gps_degrees((-33, 55, 29.64), "", "S") == pytest.approx(-33.9249)
    assert _gps_degrees((33, 55, 29.64), b"S\x00", "S") == pytest.approx(-33.9249)
    assert _gps_degrees((33, 55, 29.64), "N", "S") == pytest.approx(33.9249)


def _colmap_scene(tmp_path, noise, scale=0.137):
    """A synthetic maize flight (tiny photos) with GPS tags, and its poses as a COLMAP model
    ``scale`` of a metre a unit (as SfM would give them)."""
    from cropcraft_core.sfm import export_colmap_text, import_colmap

    out = tmp_path / f"scene{noise}"
    make_scene(
        "maize", out, views=24, resolution=(64, 48), trajectory="drone", metrics=False,
        supersample=1, drone_height_m=25.0, gps_noise_m=noise, image_format="png",
    )  # fmt: skip
    poses = import_colmap(out / "colmap" / "sparse" / "0")
    model = tmp_path / f"model{noise}"
    export_colmap_text(poses.transformed(scale, np.eye(3), np.zeros(3)), model)
    return out, model


@pytest.mark.parametrize("noise", [0.02, 3.0])
def test_the_poses_stage_scales_sfm_poses_by_their_photos_gps(tmp_path, noise):
    """Poses of unknown scale (a COLMAP model) of a 25 m maize flight, whose photos carry
    their positions: RTK-grade ones (2 cm) set the scale (the cameras 25 m up, the summary
    says from what), a phone's (3 m) do not and the crop's 13 m prior stands, said with its
    reason. A camera distance given goes over the GPS, and ``gps`` false turns it off."""
    from tasks.ingest import ingest
    from tasks.poses import poses

    out, model = _colmap_scene(tmp_path, noise)
    root, scene = str(tmp_path / "store"), "plotG/maize/2024-07-01"
    ing = ingest.fn(root, scene, {"min_images": 3}, {}, str(out / "images"))
    rec = poses.fn(root, scene, {"imported_metric": False}, {"ingest": ing}, str(model))
    s = rec["summary"]
    assert s["gps"]["n_photos"] == 24
    if noise < 1:
        assert s["gps"]["used"] and s["frame"]["scale_source"] == "gps" and s["metric"]
        assert s["frame"]["scale"] == pytest.approx(1 / 0.137, rel=0.01)
    else:
        assert not s["gps"]["used"] and "GPS positions agree" in s["gps"]["reason"]
        assert s["frame"]["scale_source"] == "camera_height_prior" and not s["metric"]
    given = {"imported_metric": False, "camera_distance": ["view_000", "view_001", 1.0]}
    hinted = poses.fn(root, scene, given, {"ingest": ing}, str(model))
    assert hinted["summary"]["frame"]["scale_source"] == "camera_distance"
    assert "gps" not in hinted["summary"]
    off = {"imported_metric": False, "gps": False}
    off = poses.fn(root, scene, off, {"ingest": ing}, str(model))
    assert off["summary"]["frame"]["scale_source"] == "camera_height_prior"
