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
NERFSTUDIO_MODELS = {"OPENCV": RADIAL_TANGENTIAL, "OPENCV_FISHEYE": FISHEYE}


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
