"""Lens distortion of photos, and the pinhole photos every later stage reads.

SfM and imported poses keep a photo's distortion beside its :class:`PinholeCamera` (the pinhole
part): ``{"model": "radial_tangential" | "fisheye", "k1": ..., ...}`` (:func:`lens`). The
visible-surfaces backends, their photo-consistency check and nerfacto all treat photos as
pinhole ones, so :func:`undistort_image` resamples a photo into the pinhole camera of the same
intrinsics first: for every pixel centre of that camera the ray's point on the distorted photo
is computed by the lens's forward model and sampled bilinearly (pixels whose ray leaves the
photo are black).

Models, in normalised camera coordinates (x, y) = (X/Z, Y/Z), r² = x² + y²:

* ``radial_tangential`` (COLMAP SIMPLE_RADIAL, RADIAL, OPENCV, FULL_OPENCV; nerfstudio OPENCV;
  OpenCV's rational model): x' = x·R + 2p₁xy + p₂(r² + 2x²), y' = y·R + p₁(r² + 2y²) + 2p₂xy,
  R = (1 + k₁r² + k₂r⁴ + k₃r⁶) / (1 + k₄r² + k₅r⁴ + k₆r⁶);
* ``fisheye`` (COLMAP SIMPLE_RADIAL_FISHEYE, RADIAL_FISHEYE, OPENCV_FISHEYE; nerfstudio
  OPENCV_FISHEYE; OpenCV's fisheye): θ = atan r, θ_d = θ(1 + k₁θ² + k₂θ⁴ + k₃θ⁶ + k₄θ⁸),
  (x', y') = (θ_d / r)(x, y).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from cropcraft_core.errors import InputError
from cropcraft_core.geometry.camera import PinholeCamera

#: A lens that moves no pixel of the photo by this much (pixels) is left alone: resampling
#: would blur the photo more than it corrects (SfM's SIMPLE_RADIAL on the synthetic pinhole
#: photos: k = 6e-5, 0.02 px at the corners).
NEGLIGIBLE_PX = 0.05

RADIAL_TANGENTIAL = "radial_tangential"
FISHEYE = "fisheye"

#: Coefficients of each model (COLMAP's SIMPLE_RADIAL / SIMPLE_RADIAL_FISHEYE ``k`` is k1).
MODEL_COEFFICIENTS = {
    RADIAL_TANGENTIAL: ("k1", "k2", "k3", "k4", "k5", "k6", "p1", "p2"),
    FISHEYE: ("k1", "k2", "k3", "k4"),
}

#: COLMAP camera models by the lens model their extra parameters belong to (None: pinhole).
COLMAP_MODELS = {
    "SIMPLE_PINHOLE": None,
    "PINHOLE": None,
    "SIMPLE_RADIAL": RADIAL_TANGENTIAL,
    "RADIAL": RADIAL_TANGENTIAL,
    "OPENCV": RADIAL_TANGENTIAL,
    "FULL_OPENCV": RADIAL_TANGENTIAL,
    "SIMPLE_RADIAL_FISHEYE": FISHEYE,
    "RADIAL_FISHEYE": FISHEYE,
    "OPENCV_FISHEYE": FISHEYE,
}

#: nerfstudio's ``camera_model`` values (``transforms.json``) by lens model. Its OPENCV lists
#: k1-k4 but ns-process-data writes k3 and k4 as 0 and nerfstudio's own undistortion reads k4
#: as OpenCV's (rational); a non-zero k4 there is refused as ambiguous.
#: nerfstudio's ``camera_model`` values and the lens each is read as: its perspective models
#: share OpenCV's radial-tangential coefficients (k1, k2, p1, p2; absent ones are zero, so a
#: PINHOLE frame is a pinhole camera), as nerfstudio's dataparser reads them.
NERFSTUDIO_MODELS = {
    "OPENCV": RADIAL_TANGENTIAL,
    "OPENCV_FISHEYE": FISHEYE,
    "PINHOLE": RADIAL_TANGENTIAL,
    "SIMPLE_PINHOLE": RADIAL_TANGENTIAL,
    "SIMPLE_RADIAL": RADIAL_TANGENTIAL,
    "RADIAL": RADIAL_TANGENTIAL,
}


def lens(model: str | None, coefficients: Mapping[str, float], where: str) -> dict[str, Any]:
    """A photo's distortion as stored beside its camera: ``{"model": ..., name: value}`` with
    the non-zero coefficients only, or ``{}`` for none. ``model``: ``radial_tangential``,
    ``fisheye`` or None (pinhole: every coefficient must be zero). ``where`` names the photo
    or file in errors (an unknown coefficient, a value that is not a finite number)."""
    out: dict[str, Any] = {}
    for name, value in coefficients.items():
        key = "k1" if name == "k" else name
        try:
            v = float(value)
        except (TypeError, ValueError):
            raise InputError(
                f"{where}: distortion {name} must be a number, got {value!r}"
            ) from None
        if not math.isfinite(v):
            raise InputError(f"{where}: distortion {name} must be finite, got {value!r}")
        if v == 0.0:
            continue
        if model is None or key not in MODEL_COEFFICIENTS[model]:
            kind = "a pinhole camera" if model is None else f"the {model} lens model"
            raise InputError(f"{where}: distortion {name}={v:g} does not belong to {kind}")
        out[key] = v
    return {"model": model, **out} if out else {}


def stored_lens(d: Mapping[str, Any] | None, where: str) -> dict[str, Any]:
    """A stored distortion record as :func:`lens` makes it. Poses written before the model was
    recorded hold SfM's SIMPLE_RADIAL ``k`` or radial-tangential names: read as such."""
    if not d:
        return {}
    d = dict(d)
    model = d.pop("model", None)
    if model is None:
        if "k4" in d:
            raise InputError(
                f"{where}: distortion k4 without its lens model (poses written by an older "
                "version): recompute the poses (cropcraft run --force)"
            )
        model = RADIAL_TANGENTIAL
    if model not in MODEL_COEFFICIENTS:
        raise InputError(f"{where}: unknown lens model {model!r}")
    return lens(model, d, where)


def distort(x: np.ndarray, y: np.ndarray, d: Mapping[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """Normalised pinhole coordinates → where the lens ``d`` (:func:`lens`) puts them."""
    k = {n: float(d.get(n, 0.0)) for n in ("k1", "k2", "k3", "k4", "k5", "k6", "p1", "p2")}
    r2 = x * x + y * y
    if d.get("model") == FISHEYE:
        r = np.sqrt(r2)
        th = np.arctan(r)
        t2 = th * th
        th_d = th * (1 + t2 * (k["k1"] + t2 * (k["k2"] + t2 * (k["k3"] + t2 * k["k4"]))))
        f = np.divide(th_d, r, out=np.ones_like(r), where=r > 1e-12)
        return x * f, y * f
    num = 1 + r2 * (k["k1"] + r2 * (k["k2"] + r2 * k["k3"]))
    den = 1 + r2 * (k["k4"] + r2 * (k["k5"] + r2 * k["k6"]))
    radial = num / den
    xy = x * y
    xd = x * radial + 2 * k["p1"] * xy + k["p2"] * (r2 + 2 * x * x)
    yd = y * radial + k["p1"] * (r2 + 2 * y * y) + 2 * k["p2"] * xy
    return xd, yd


def undistort_image(image: np.ndarray, camera: PinholeCamera, d: Mapping[str, Any]) -> np.ndarray:
    """``image`` (taken through the lens ``d`` with ``camera``'s intrinsics) as the pinhole
    ``camera`` sees it; ``image`` itself where ``d`` is empty or moves no pixel by
    :data:`NEGLIGIBLE_PX`."""
    if not d:
        return image
    import cv2

    h, w = image.shape[:2]
    if (w, h) != (camera.width, camera.height):
        raise InputError(f"photo of {w}x{h} pixels for a camera of {camera.width}x{camera.height}")
    x = (np.arange(w, dtype=np.float64) + 0.5 - camera.cx) / camera.fx
    y = (np.arange(h, dtype=np.float64) + 0.5 - camera.cy) / camera.fy
    xx, yy = np.meshgrid(x, y)
    xd, yd = distort(xx, yy, d)
    shift = np.hypot(camera.fx * (xd - xx), camera.fy * (yd - yy))
    if float(shift.max()) < NEGLIGIBLE_PX:
        return image
    map_x = (camera.fx * xd + camera.cx - 0.5).astype(np.float32)
    map_y = (camera.fy * yd + camera.cy - 0.5).astype(np.float32)
    return cv2.remap(
        np.ascontiguousarray(image),
        map_x,
        map_y,
        interpolation=cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=0,
    )


__all__ = [
    "COLMAP_MODELS",
    "FISHEYE",
    "MODEL_COEFFICIENTS",
    "NEGLIGIBLE_PX",
    "NERFSTUDIO_MODELS",
    "RADIAL_TANGENTIAL",
    "distort",
    "lens",
    "stored_lens",
    "undistort_image",
]


#: EXIF orientations that turn a photo (without mirroring it) → (M, how p1, p2 follow): M
#: gives the stored camera's axes from the upright one's, (x, y, z)_stored = M (x, y, z)_upright,
#: for ingest's turn (``Image.transpose``: 3 half a turn, 6 a quarter clockwise, 8 a quarter
#: counter-clockwise).
_TURNS = {
    3: (np.diag([-1.0, -1.0, 1.0]), lambda p1, p2: (-p1, -p2)),
    6: (np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]), lambda p1, p2: (p2, -p1)),
    8: (np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]), lambda p1, p2: (-p2, p1)),
}
#: EXIF orientations that mirror the photo: no camera sees its scene mirrored.
MIRRORING_ORIENTATIONS = (2, 4, 5, 7)


def turn_upright(
    camera: PinholeCamera, distortion: Mapping[str, Any] | None, orientation: int
) -> tuple[PinholeCamera, dict[str, Any]]:
    """The camera (and lens) of a photo's stored pixels → those of the photo turned upright
    by its EXIF ``orientation`` (1, 3, 6 or 8), as ingest turns it: COLMAP, and the tools that
    run it, ignore the tag and pose the pixels as stored. The intrinsics swap and move with
    the pixel grid, the pose turns about the optical axis, and the tangential coefficients
    turn with it (radial ones are symmetric)."""
    d = dict(distortion or {})
    if orientation == 1:
        return camera, d
    if orientation not in _TURNS:
        raise ValueError(f"EXIF orientation {orientation} is not a turn of the photo")
    m, tangential = _TURNS[orientation]
    w, h, c = camera.width, camera.height, camera
    pose = camera.cam_to_world.copy()
    pose[:3, :3] = camera.cam_to_world[:3, :3] @ m
    if orientation == 3:
        turned = PinholeCamera(w, h, c.fx, c.fy, w - c.cx, h - c.cy, pose)
    elif orientation == 6:  # stored (u, v) → upright (h - v, u)
        turned = PinholeCamera(h, w, c.fy, c.fx, h - c.cy, c.cx, pose)
    else:  # 8: stored (u, v) → upright (v, w - u)
        turned = PinholeCamera(h, w, c.fy, c.fx, c.cy, w - c.cx, pose)
    if d.get("model") == RADIAL_TANGENTIAL and ("p1" in d or "p2" in d):
        p1, p2 = tangential(float(d.get("p1", 0.0)), float(d.get("p2", 0.0)))
        d = {k: v for k, v in d.items() if k not in ("p1", "p2")}
        d.update({k: v for k, v in (("p1", p1), ("p2", p2)) if v != 0.0})
    return turned, d
