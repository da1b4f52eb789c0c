"""sRGB → CIELAB (D65) in true units, vectorised.

L* is in [0, 100]; a* and b* are signed (green a* < 0, red a* > 0; blue b* < 0, yellow b* > 0).
This is *not* OpenCV's 8-bit encoding (``cv2.cvtColor`` on uint8 images returns L*·255/100,
a* + 128, b* + 128); it agrees with ``cv2.cvtColor`` on float32 images in [0, 1] to within a few
tenths (OpenCV interpolates a table).
"""

from __future__ import annotations

import numpy as np

from cropcraft_core.errors import InputError

#: Linear sRGB → CIE XYZ (D65), IEC 61966-2-1.
SRGB_TO_XYZ = np.array(
    [
        [0.4124564, 0.3575761, 0.1804375],
        [0.2126729, 0.7151522, 0.0721750],
        [0.0193339, 0.1191920, 0.9503041],
    ]
)
#: D65 reference white (Y = 1), the XYZ of sRGB (1, 1, 1).
D65_WHITE = SRGB_TO_XYZ.sum(axis=1)

_EPS = (6.0 / 29.0) ** 3
_KAPPA = 1.0 / (3.0 * (6.0 / 29.0) ** 2)


def colour_range(colors: np.ndarray, dtype: np.dtype | None = None) -> float:
    """The value of full intensity of ``colors`` (stored as ``dtype``, default theirs: a
    caller that converted them to float first gives the original), read from their largest
    value: 0–255 for 8-bit values, 0–65535 for 16-bit ones (a PLY's ``ushort`` colours);
    floats are 0–1 up to a largest value of 2 (a fused or averaged colour a hair over 1, an
    exposure-corrected render's 1.02: dividing those by 255 made every point black), 0–255 up
    to 255, else 0–65535. Larger values are refused: they are no colours."""
    kind = np.asarray(colors).dtype if dtype is None else np.dtype(dtype)
    integer = np.issubdtype(kind, np.integer) or np.issubdtype(kind, np.bool_)
    top = float(np.nanmax(colors)) if np.size(colors) else 0.0
    if top > 65535.0:
        raise InputError(f"colour values reach {top:g}: not 0-1, 0-255 or 0-65535 colours")
    if top > 255.0:
        return 65535.0
    if integer or top > 2.0:
        return 255.0
    return 1.0


def srgb_to_lab(rgb: np.ndarray, max_value: float | None = None) -> np.ndarray:
    """(..., 3) sRGB colours → (..., 3) float64 CIELAB (L*, a*, b*), D65 white.

    max_value: the value of full intensity. ``None`` infers it (:func:`colour_range`). Values
    are clipped to [0, max_value].
    """
    a = np.asarray(rgb)
    if a.shape[-1:] != (3,):
        raise InputError(f"colours must have shape (..., 3), got {a.shape}")
    if max_value is None:
        max_value = colour_range(a)
    if not max_value > 0:
        raise InputError(f"max_value must be positive, got {max_value}")
    c = np.clip(a.astype(np.float64) / float(max_value), 0.0, 1.0)
    lin = np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)
    xyz = lin @ SRGB_TO_XYZ.T / D65_WHITE
    f = np.where(xyz > _EPS, np.cbrt(xyz), xyz * _KAPPA + 4.0 / 29.0)
    lab = np.empty_like(f)
    lab[..., 0] = 116.0 * f[..., 1] - 16.0
    lab[..., 1] = 500.0 * (f[..., 0] - f[..., 1])
    lab[..., 2] = 200.0 * (f[..., 1] - f[..., 2])
    return lab
