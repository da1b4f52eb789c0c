"""The surfaces against the photos at the photos' own cameras
(:mod:`cropcraft_core.surfaces.consistency`), on exact renders of known geometry: a square leaf
over brown soil, photographed by the truth backend, against reconstructions that lose or add
leaf. The expected shares are counted from the renders' face ids, not from colours."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("open3d")

from cropcraft_core.errors import InputError  # noqa: E402
from cropcraft_core.geometry.camera import PinholeCamera  # noqa: E402
from cropcraft_core.geometry.mesh import CanopyMesh  # noqa: E402
from cropcraft_core.surfaces.base import SurfacesError  # noqa: E402
from cropcraft_core.surfaces.consistency import (  # noqa: E402
    NET_WARN,
    consistency_warning,
    describe,
    photo_consistency,
    pick_views,
)
from cropcraft_core.surfaces.mesh_truth import TruthSurfaces  # noqa: E402

UP, GROUND = (0.0, 0.0, 1.0), 0.0
BOX = np.array([[-1.0, -1.0, -0.1], [1.0, 1.0, 1.0]])


def leaf(half: float, z: float = 0.3) -> CanopyMesh:
    """One horizontal square leaf of half-size ``half`` (m) centred over the origin."""
    v = np.array([[-half, -half, z], [half, -half, z], [half, half, z], [-half, half, z]])
    f = np.array([[0, 1, 2], [0, 2, 3]], np.int32)
    zeros = np.zeros(2, np.int32)
    return CanopyMesh(v, f, np.zeros(2, np.uint8), zeros, zeros)  # organ 0: leaf


def cameras() -> list[PinholeCamera]:
    """One camera straight down and two oblique ones looking at the plot's centre."""
    cams = [PinholeCamera.look_down((0.0, 0.0), 1.5, size=(160, 120), vfov_deg=60.0)]
    for eye in ((1.2, 0.3, 1.4), (-0.8, -1.1, 1.5)):
        eye = np.asarray(eye)
        fwd = -eye / np.linalg.norm(eye)
        right = np.cross(fwd, [0.0, 0.0, 1.0])
        right /= np.linalg.norm(right)
        m = np.eye(4)
        m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = right, np.cross(fwd, right), fwd, eye
        cams.append(PinholeCamera.from_vfov(160, 120, 60.0, m))
    return cams


def photos(truth: TruthSurfaces, cams: list[PinholeCamera]) -> list[np.ndarray]:
    return [truth.render(c)[1] for c in cams]


def leaf_pixels(backend: TruthSurfaces, cams: list[PinholeCamera]) -> np.ndarray:
    """(views, H, W) bool: where each camera sees the canopy (face id ≥ 0)."""
    return np.stack([backend.render_faces(c)[1] >= 0 for c in cams])


def check(render, imgs, cams, **kw):
    return photo_consistency(render, imgs, cams, UP, GROUND, bbox=BOX, **kw)


def test_the_true_surfaces_agree_with_their_own_photos():
    truth, cams = TruthSurfaces(leaf(0.2)), cameras()
    out = check(truth.render, photos(truth, cams), cams)
    seen = leaf_pixels(truth, cams)
    assert out.views == (0, 1, 2) and out.unreconstructed == 0 and out.extra == 0
    assert out.net == 0 and out.holes == 0 and out.warning() is None
    assert out.photo_plant == pytest.approx(seen.sum() / out.plot_pixels)
    assert out.surface_raised == pytest.approx(out.photo_plant)
    assert [v["index"] for v in out.per_view] == [0, 1, 2]


def test_lost_leaf_counts_as_unreconstructed_and_warns_low():
    """The reconstruction keeps only the middle of the leaf and no soil: the rest of the leaf
    the photos show has no surface."""
    truth, cams = TruthSurfaces(leaf(0.3)), cameras()
    recon = TruthSurfaces(leaf(0.15), ground=False)
    out = check(recon.render, photos(truth, cams), cams)
    big, small = leaf_pixels(truth, cams), leaf_pixels(recon, cams)
    assert out.unreconstructed == pytest.approx((big & ~small).sum() / big.sum())
    assert out.extra == 0 and out.unreconstructed > 0.5
    assert out.net == pytest.approx(-out.unreconstructed)
    assert out.holes > out.photo_plant  # the soil is a hole too, but not plant in the photos
    assert "no surface under" in out.warning() and "low" in out.warning()


def test_fattened_leaf_counts_as_extra_and_warns_high():
    truth, cams = TruthSurfaces(leaf(0.2)), cameras()
    recon = TruthSurfaces(leaf(0.3))
    out = check(recon.render, photos(truth, cams), cams)
    small, big = leaf_pixels(truth, cams), leaf_pixels(recon, cams)
    assert out.extra == pytest.approx((big & ~small).sum() / small.sum())
    assert out.unreconstructed == 0 and out.extra > 1 and out.net == pytest.approx(out.extra)
    assert "raises surface over soil" in out.warning() and "high" in out.warning()


def test_a_surface_below_the_raised_height_is_not_extra():
    """A reconstruction whose leaf lies flat on the soil (1 cm up) over soil-coloured photo
    pixels adds no raised surface; a lower ``min_height_m`` counts it."""
    truth, cams = TruthSurfaces(leaf(0.1)), cameras()
    recon = TruthSurfaces(leaf(0.3, z=0.01))
    imgs = photos(truth, cams)
    assert check(recon.render, imgs, cams).extra == 0
    assert check(recon.render, imgs, cams, min_height_m=0.005).extra > 0
    # the same in a frame of half-metre units: the height is converted by the scale
    assert check(recon.render, imgs, cams, scale=0.5).extra == 0


def test_only_the_plot_is_compared_and_no_plant_gives_no_shares():
    truth, cams = TruthSurfaces(leaf(0.2)), cameras()
    imgs = photos(truth, cams)
    corner = np.array([[0.5, 0.5, -0.1], [1.0, 1.0, 1.0]])  # soil only, beside the leaf
    out = photo_consistency(truth.render, imgs, cams, UP, GROUND, bbox=corner)
    whole = check(truth.render, imgs, cams)
    assert 0 < out.plot_pixels < whole.plot_pixels and out.photo_plant == 0
    assert out.unreconstructed is None and out.extra is None and out.net is None
    assert out.warning() is None


def test_bad_input_is_named():
    truth, cams = TruthSurfaces(leaf(0.2)), cameras()
    imgs = photos(truth, cams)
    with pytest.raises(InputError, match="3 photos but 2 cameras"):
        check(truth.render, imgs, cams[:2])
    with pytest.raises(InputError, match="ground_normal"):
        photo_consistency(truth.render, imgs, cams, (0, 0, 0), 0.0)
    with pytest.raises(InputError, match="photo 1 is"):
        check(truth.render, [imgs[0], imgs[1][:50], imgs[2]], cams)
    for views in ([-1], [3], [0, 0]):  # -1 compared photo 2, [0, 0] counted photo 0 twice
        with pytest.raises(InputError, match="views must be distinct photo indices in 0..2"):
            photo_consistency(truth.render, imgs, cams, UP, GROUND, views=views)
    far = np.array([[50.0, 50.0, -0.1], [51.0, 51.0, 1.0]])
    with pytest.raises(SurfacesError, match="none of the 3 photos"):
        photo_consistency(truth.render, imgs, cams, UP, GROUND, bbox=far)


def test_the_shares_in_words():
    text = describe(0.074, 0.083)
    assert (
        "no surface under 7.4 %" in text and "soil 8.3 %" in text and "(net cover +0.9 %)" in text
    )


def test_views_are_spread_over_the_photos():
    assert pick_views(50) == tuple(int(round(x)) for x in np.linspace(0, 49, 12))
    assert pick_views(5) == (0, 1, 2, 3, 4) and pick_views(1) == (0,)
    with pytest.raises(InputError):
        pick_views(0)


def test_warning_threshold_is_on_the_net_cover_and_per_crop():
    soy = NET_WARN["soybean"]
    assert consistency_warning(0.20, 0.06, soy) is None  # net −0.14
    assert "low" in consistency_warning(0.25, 0.05, soy)  # net −0.20
    assert "high" in consistency_warning(0.0, soy, soy)
    assert consistency_warning(None, 0.3, soy) is None
    assert consistency_warning(0.3, 0.0, limit=0.5) is None
    # maize reports its shares but does not warn: there the sign did not follow the LAI
    assert NET_WARN["maize"] is None and consistency_warning(0.0, 0.5, NET_WARN["maize"]) is None
