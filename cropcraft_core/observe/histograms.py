"""Histogram statistics of a row-camera depth map (paper "Loss Function", supplementary "Mask and
Histogram Details").

For an (H, W) z-depth map, an (H, W) foreground mask and the row camera, :func:`compute_stats`
returns four statistics of the foreground pixels:

* **depth** — histogram of the z-depth ``d`` (metres along the optical axis; for the straight-down
  row camera ``d = render_height - height above ground``). Soybean: 20 bins over
  [0.1 m, render height]; maize: 10 bins over [2 m, render height] in the paper, here from just
  above the observed canopy's top where that is lower (``LossPreset.depth_top_margin``,
  resolved by the observation: a 0.3 m plant's bins are 4 cm, not 0.3 m).
* **lateral** — histogram of ``|y|``, the lateral offset from the row line in the row camera's
  frame: the pixel is unprojected, ``y_cam = (v + 0.5 - cy) / fy * d`` (metres, not pixels;
  the same value ``camera.unproject`` gives in camera coordinates). 10 bins over
  [0, render height / 2].
* **sobel** — histogram of ``|Sx| + |Sy|``, OpenCV's unnormalised 3×3 Sobel derivatives of the
  Gaussian-blurred depth (kernel 25 soybean, 55 maize). 10 bins over [0, 0.004].
* **mask_area** — the foreground fraction of the image's pixels.

Bins follow ``numpy.histogram(x, bins=n, range=(lo, hi))`` exactly: equal widths, half-open
except the last bin, which includes ``hi``; values outside ``[lo, hi]`` are not counted.

Background before blurring. Pixels outside the mask (no surface in a prediction, soil or other
rows in an observation) are set to the ground's depth, ``render_height`` (the ground is the plane
z_cam = render_height for the straight-down camera), before the blur, on both sides alike. So
the derivative image is that of "the foreground over bare flat ground", identical in kind for the
NeRF observation and the background-free procedural render, and NaN never enters the blur. Only
foreground pixels are counted; the image border is replicated (``BORDER_REPLICATE``).

Normalisation (``LossPreset.normalisation``). The default, ``"image"``, divides every histogram
count by the image's pixel count N = W·H, and the mask area is the foreground count / N. Why:

* every term of the loss is then the paper's raw-count term divided by the same constant N², so
  the paper's λ weights keep exactly their relative meaning (dividing each histogram by its own
  foreground count would not: it changes the depth/lateral/sobel terms but not the mask term);
* each histogram sums to at most the mask area (≤ 1), so every term is bounded (L_depth,
  L_lateral, L_sobel ≤ 2, L_mask ≤ 1) and, up to pixel rounding, independent of the resolution
  (``camera.scaled(0.5)`` gives about the same numbers);
* an empty predicted mask (nothing in view) gives all-zero histograms and a large, finite loss
  instead of 0/0;
* the scale matches the paper: per-bin differences of a few 10⁻³–10⁻² give losses of order
  10⁻², the paper's average final soybean loss being 0.011 (an order-of-magnitude argument,
  not a reproduction of that number).

``"foreground"`` divides by the foreground count instead (pure distributions, each summing to
≤ 1; all zeros for an empty mask): the shape of the canopy without its amount, which is then left
to the mask term alone.

Speed: a numba pass that fills the background, one cv2 Gaussian blur, two cv2 Sobels and one
numba pass that bins all three histograms: about 10 ms for a 994×738 soybean map on 2 busy CPU
cores, ~4 ms without the derivative histogram (maize's default, λ_sobel = 0; with it, the 55-px
blur makes maize ~17 ms). The binning computes the edges it compares against (they are
``numpy.linspace``'s, ``k * step + lo``) so that its loop vectorises: 3–3.6 ms a fit's map
on one thread beside a two-process benchmark, where looking them up took 6–7 ms (alone:
1.9 against 3.1 ms); the same counts.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

import cv2
import numba
import numpy as np

from cropcraft_core.errors import ConfigError, InputError
from cropcraft_core.geometry.camera import PinholeCamera
from cropcraft_core.observe.presets import ObservePreset


@dataclass(frozen=True, eq=False)
class HistogramStats:
    """Histogram statistics of one depth map.

    depth: (n_depth,) float64 normalised counts of z-depth bins.
    lateral: (n_lateral,) float64 normalised counts of |y| bins.
    sobel: (n_sobel,) float64 normalised counts of depth-derivative-magnitude bins.
    mask_area: foreground pixels / image pixels, in [0, 1].
    n_foreground: number of foreground pixels.
    n_pixels: number of image pixels (W·H).
    spec: the preset's :meth:`~cropcraft_core.observe.ObservePreset.stats_spec` (bin ranges,
    blur, normalisation, render height); statistics are comparable only if their specs agree.
    has_sobel: false if the depth-derivative histogram was skipped (then ``sobel`` is zeros).
    """

    depth: np.ndarray
    lateral: np.ndarray
    sobel: np.ndarray
    mask_area: float
    n_foreground: int
    n_pixels: int
    spec: tuple
    has_sobel: bool = True

    def __post_init__(self) -> None:
        for name in ("depth", "lateral", "sobel"):
            a = np.array(getattr(self, name), dtype=np.float64)
            if a.ndim != 1 or not np.all(np.isfinite(a)):
                raise InputError(f"histogram {name!r} must be a finite 1-D array")
            a.flags.writeable = False
            object.__setattr__(self, name, a)
        object.__setattr__(self, "mask_area", float(self.mask_area))
        object.__setattr__(self, "spec", _freeze(self.spec))

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready record (floats survive ``json`` exactly)."""
        return {
            "depth": self.depth.tolist(),
            "lateral": self.lateral.tolist(),
            "sobel": self.sobel.tolist(),
            "mask_area": self.mask_area,
            "n_foreground": self.n_foreground,
            "n_pixels": self.n_pixels,
            "spec": _thaw(self.spec),
            "has_sobel": self.has_sobel,
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> HistogramStats:
        try:
            return cls(
                np.asarray(d["depth"], dtype=np.float64),
                np.asarray(d["lateral"], dtype=np.float64),
                np.asarray(d["sobel"], dtype=np.float64),
                float(d["mask_area"]),
                int(d["n_foreground"]),
                int(d["n_pixels"]),
                _freeze(d["spec"]),
                bool(d.get("has_sobel", True)),
            )
        except (KeyError, TypeError, ValueError) as e:
            raise InputError(f"histogram statistics record is malformed: {e}") from None

    def equals(self, other: HistogramStats) -> bool:
        """Exact equality of every array, count and spec."""
        return (
            self.spec == other.spec
            and self.mask_area == other.mask_area
            and self.n_foreground == other.n_foreground
            and self.n_pixels == other.n_pixels
            and self.has_sobel == other.has_sobel
            and all(
                np.array_equal(getattr(self, k), getattr(other, k))
                for k in ("depth", "lateral", "sobel")
            )
        )


def mean_stats(stats: Sequence[HistogramStats]) -> HistogramStats:
    """Bin-by-bin mean of statistics computed with one spec (several canopies of a prediction,
    or several row cameras of an observation). ``ConfigError`` for none or mixed specs."""
    stats = list(stats)
    if not stats:
        raise ConfigError("mean_stats needs at least one set of statistics")
    first = stats[0]
    if any(s.spec != first.spec for s in stats[1:]):
        raise ConfigError("mean_stats: the statistics were computed with different presets")
    if len(stats) == 1:
        return first
    return replace(
        first,
        depth=np.mean([s.depth for s in stats], axis=0),
        lateral=np.mean([s.lateral for s in stats], axis=0),
        sobel=np.mean([s.sobel for s in stats], axis=0),
        mask_area=float(np.mean([s.mask_area for s in stats])),
        n_foreground=int(round(np.mean([s.n_foreground for s in stats]))),
        has_sobel=all(s.has_sobel for s in stats),
    )


def _freeze(x: Any) -> Any:
    """Nested lists → nested tuples (JSON round trip of a spec)."""
    if isinstance(x, list | tuple):
        return tuple(_freeze(v) for v in x)
    return x


def _thaw(x: Any) -> Any:
    if isinstance(x, tuple):
        return [_thaw(v) for v in x]
    return x


# --------------------------------------------------------------------------- geometry helpers
def lateral_factor(camera: PinholeCamera) -> np.ndarray:
    """(H,) float64 ``(v + 0.5 - cy) / fy`` per image row: ``y_cam = factor[v] * z_depth``."""
    return (np.arange(camera.height, dtype=np.float64) + 0.5 - camera.cy) / camera.fy


def check_depth(depth: Any, camera: PinholeCamera, name: str = "depth") -> np.ndarray:
    """Validate an (H, W) depth map against the camera; return it C-contiguous, float32 kept as
    float32 (renders), anything else as float64."""
    d = np.asarray(depth)
    if d.ndim != 2:
        raise InputError(f"{name} must be a 2-D (H, W) array, got shape {d.shape}")
    if d.shape != (camera.height, camera.width):
        raise InputError(
            f"{name} is {d.shape[1]}×{d.shape[0]} (W×H) but the camera is "
            f"{camera.width}×{camera.height}"
        )
    if not (np.issubdtype(d.dtype, np.floating) or np.issubdtype(d.dtype, np.integer)):
        raise InputError(f"{name} must be numeric, got dtype {d.dtype}")
    return np.ascontiguousarray(d, dtype=np.float32 if d.dtype == np.float32 else np.float64)


def check_mask(mask: Any, shape: tuple[int, int], name: str = "mask") -> np.ndarray:
    """Validate an (H, W) mask of booleans (or 0/1 integers); return it C-contiguous bool."""
    m = np.asarray(mask)
    if m.shape != shape:
        raise InputError(f"{name} has shape {m.shape} but the depth map has shape {shape}")
    if m.dtype != np.bool_:
        if not np.issubdtype(m.dtype, np.integer) or (m.size and (m.min() < 0 or m.max() > 1)):
            raise InputError(f"{name} must be boolean (or 0/1 integers), got dtype {m.dtype}")
        m = m.astype(bool)
    return np.ascontiguousarray(m)


# --------------------------------------------------------------------------- numba kernels
@numba.njit(cache=True, nogil=True)
def _fill(depth, mask, ground, out):  # pragma: no cover - compiled
    """out = depth - ground on valid foreground, 0 (the ground) elsewhere; returns
    (foreground count, count of masked pixels whose depth is not finite and positive)."""
    h, w = depth.shape
    n_fg = 0
    n_bad = 0
    for i in range(h):
        for j in range(w):
            if mask[i, j]:
                d = depth[i, j]
                if d > 0.0 and d < np.inf:
                    out[i, j] = d - ground
                    n_fg += 1
                else:
                    out[i, j] = 0.0
                    n_bad += 1
            else:
                out[i, j] = 0.0
    return n_fg, n_bad


@numba.njit(cache=True, inline="always")
def _bin(x, lo, hi, norm, edges, n):  # pragma: no cover - compiled
    """numpy.histogram's bin of ``x`` for n equal bins over [lo, hi] = [edges[0], edges[n]]
    (index from ``(x - lo) * norm``, then corrected against the exact edges the way numpy does),
    or n (the overflow slot) if x is outside or NaN. Selects, not branches: numba turns ``&`` on
    comparisons and data-dependent branches into much slower code here."""
    ok = x >= lo and x <= hi
    x = x if ok else lo
    k = int(min(max((x - lo) * norm, 0.0), n - 1.0))
    e0 = edges[k]
    e1 = edges[k + 1]
    k = k - 1 if x < e0 else k
    k = k + 1 if (x >= e1) and (k != n - 1) else k
    return k if ok else n


@numba.njit(cache=True, nogil=True)
def _histograms_by_edges(depth, mask, yfac, dx, dy, d_edges, l_edges, s_edges, with_sobel):
    # pragma: no cover - compiled
    """Counts of the three histograms over the masked pixels, one pass over the image, bins
    looked up in the edge arrays: :func:`_histograms` where the edges are not the arithmetic
    ``lo + k * step`` (a numpy whose ``linspace`` computes them otherwise). The caller
    guarantees that every masked pixel has a finite positive depth (``_fill`` counts
    violations)."""
    h, w = depth.shape
    nd = d_edges.shape[0] - 1
    nl = l_edges.shape[0] - 1
    ns = s_edges.shape[0] - 1
    hd = np.zeros(nd + 1, np.int64)
    hl = np.zeros(nl + 1, np.int64)
    hs = np.zeros(ns + 1, np.int64)
    d_lo, d_hi = d_edges[0], d_edges[nd]
    l_lo, l_hi = l_edges[0], l_edges[nl]
    s_lo, s_hi = s_edges[0], s_edges[ns]
    d_norm = nd / (d_hi - d_lo)
    l_norm = nl / (l_hi - l_lo)
    s_norm = ns / (s_hi - s_lo)
    for i in range(h):
        fy = abs(yfac[i])
        for j in range(w):
            if not mask[i, j]:
                continue
            d = np.float64(depth[i, j])
            hd[_bin(d, d_lo, d_hi, d_norm, d_edges, nd)] += 1
            hl[_bin(fy * d, l_lo, l_hi, l_norm, l_edges, nl)] += 1
            if with_sobel:
                s = abs(np.float64(dx[i, j])) + abs(np.float64(dy[i, j]))
                hs[_bin(s, s_lo, s_hi, s_norm, s_edges, ns)] += 1
    return hd[:nd], hl[:nl], hs[:ns]


@numba.njit(cache=True, inline="always")
def _bin_linear(x, lo, hi, norm, step, n):  # pragma: no cover - compiled
    """:func:`_bin` for edges that are ``k * step + lo`` (``k < n``) and ``hi``, what
    ``numpy.linspace`` makes: the two edges it checks against are computed, not looked up,
    so a loop of these vectorises (a gather from the edge array keeps LLVM from it)."""
    ok = (x >= lo) & (x <= hi)
    x = x if ok else lo
    k = int(min(max((x - lo) * norm, 0.0), n - 1.0))
    e0 = np.float64(k) * step + lo
    e1 = np.float64(k + 1) * step + lo if k + 1 < n else hi
    k = k - 1 if x < e0 else k
    k = k + 1 if (x >= e1) & (k != n - 1) else k
    return k if ok else n


@numba.njit(cache=True, nogil=True)
def _histograms(depth, mask, yfac, dx, dy, d_par, l_par, s_par, with_sobel):
    # pragma: no cover - compiled
    """Counts of the three histograms over the masked pixels. ``*_par``: (lo, hi, step, n) of
    each histogram's linear edges (:func:`_linear_edges`). The caller guarantees that every
    masked pixel has a finite positive depth (``_fill`` counts violations).

    Row by row, written for LLVM's vectoriser: one loop computes every pixel's bins (the
    overflow slot n for pixels outside the mask; flat images addressed by unsigned offsets,
    selects instead of branches), a second adds them up, spread over four copies of each
    histogram so that neighbouring pixels, which mostly share a bin, do not wait on each
    other's increments. The same counts as :func:`_histograms_by_edges`."""
    h, w = depth.shape
    d_lo, d_hi, d_step, nd = d_par[0], d_par[1], d_par[2], int(d_par[3])
    l_lo, l_hi, l_step, nl = l_par[0], l_par[1], l_par[2], int(l_par[3])
    s_lo, s_hi, s_step, ns = s_par[0], s_par[1], s_par[2], int(s_par[3])
    d_norm = nd / (d_hi - d_lo)
    l_norm = nl / (l_hi - l_lo)
    s_norm = ns / (s_hi - s_lo)
    md, ml, ms = np.uint64(nd + 1), np.uint64(nl + 1), np.uint64(ns + 1)
    cd = np.zeros(4 * (nd + 1), np.int64)
    cl = np.zeros(4 * (nl + 1), np.int64)
    cs = np.zeros(4 * (ns + 1), np.int64)
    df = depth.reshape(-1)
    mf = mask.reshape(-1)
    xf = dx.reshape(-1)
    yf = dy.reshape(-1)
    bd = np.empty(w, np.int64)
    bl = np.empty(w, np.int64)
    bs = np.empty(w, np.int64)
    uw = np.uint64(w)
    three = np.uint64(3)
    for i in range(h):
        fy = abs(yfac[i])
        base = np.uint64(i) * uw
        for j in range(uw):
            o = base + j
            m = mf[o]
            d = np.float64(df[o])
            kd = _bin_linear(d, d_lo, d_hi, d_norm, d_step, nd)
            kl = _bin_linear(fy * d, l_lo, l_hi, l_norm, l_step, nl)
            bd[j] = kd if m else nd
            bl[j] = kl if m else nl
        for j in range(uw):
            lane = j & three
            cd[lane * md + np.uint64(bd[j])] += 1
            cl[lane * ml + np.uint64(bl[j])] += 1
        if with_sobel:
            for j in range(uw):
                o = base + j
                s = abs(np.float64(xf[o])) + abs(np.float64(yf[o]))
                ks = _bin_linear(s, s_lo, s_hi, s_norm, s_step, ns)
                bs[j] = ks if mf[o] else ns
            for j in range(uw):
                cs[(j & three) * ms + np.uint64(bs[j])] += 1
    hd = cd.reshape(4, nd + 1).sum(axis=0)
    hl = cl.reshape(4, nl + 1).sum(axis=0)
    hs = cs.reshape(4, ns + 1).sum(axis=0)
    return hd[:nd], hl[:nl], hs[:ns]


# --------------------------------------------------------------------------- public
def blur_depth(depth: np.ndarray, sigma_px: float) -> np.ndarray:
    """(H, W) float32 ``depth`` smoothed by a Gaussian of ``sigma_px`` pixels over its finite
    pixels only: each finite pixel becomes the Gaussian-weighted mean of the finite depths
    around it (its own included), the others stay NaN, so the set of rendered pixels (the
    predicted mask) is unchanged and a leaf's edge averages only leaf depths, never the
    background's. ``sigma_px`` 0 returns the depth as float32 unchanged.

    A model of how a fused reconstruction softens the leaves' depth near their edges
    (``ObservePreset.prediction_blur_m``)."""
    if not math.isfinite(sigma_px) or sigma_px < 0:
        raise ConfigError(f"blur sigma must be a finite number >= 0, got {sigma_px!r}")
    d = np.asarray(depth, np.float32)
    if sigma_px == 0:
        return d
    finite = np.isfinite(d)
    weight = finite.astype(np.float32)
    num = cv2.GaussianBlur(np.where(finite, d, 0.0).astype(np.float32), (0, 0), sigma_px)
    den = cv2.GaussianBlur(weight, (0, 0), sigma_px)
    out = np.full(d.shape, np.nan, np.float32)
    # den > 0 wherever the pixel itself is finite (its own weight is the kernel's peak)
    np.divide(num, den, out=out, where=finite)
    return out


def sobel_magnitude(depth: np.ndarray, mask: np.ndarray, preset: ObservePreset) -> np.ndarray:
    """(H, W) float32 ``|Sx| + |Sy|`` of the blurred, ground-filled depth, the value that
    :func:`compute_stats` bins (for inspection and plots).

    depth: (H, W) z-depth, metres. mask: (H, W) bool foreground; other pixels (and masked pixels
    without a finite positive depth) are set to the ground depth ``render_height`` first.
    """
    d = np.ascontiguousarray(depth, dtype=np.float64)
    m = check_mask(mask, d.shape)
    filled = np.empty(d.shape, np.float32)
    _fill(d, m, float(preset.render_height), filled)
    dx, dy = _derivatives(filled, preset)
    return np.abs(dx) + np.abs(dy)


def _derivatives(filled: np.ndarray, preset: ObservePreset) -> tuple[np.ndarray, np.ndarray]:
    k = preset.loss.blur_kernel
    if k > 1:
        blurred = cv2.GaussianBlur(
            filled, (k, k), preset.loss.blur_sigma, borderType=cv2.BORDER_REPLICATE
        )
    else:
        blurred = filled
    dx = cv2.Sobel(blurred, cv2.CV_32F, 1, 0, ksize=3, borderType=cv2.BORDER_REPLICATE)
    dy = cv2.Sobel(blurred, cv2.CV_32F, 0, 1, ksize=3, borderType=cv2.BORDER_REPLICATE)
    return dx, dy


_EDGE_CACHE: dict[tuple[float, float, int], tuple[np.ndarray, np.ndarray | None]] = {}


def _made_edges(lo: float, hi: float, n: int) -> tuple[np.ndarray, np.ndarray | None]:
    """The n + 1 edges over [lo, hi] (``numpy.linspace``) and their :func:`_linear_edges`,
    made once per range."""
    key = (lo, hi, n)
    got = _EDGE_CACHE.get(key)
    if got is None:
        e = np.linspace(lo, hi, n + 1)
        got = (e, _linear_edges(e))
        if len(_EDGE_CACHE) < 256:
            _EDGE_CACHE[key] = got
    return got


def _edges(lo: float, hi: float, n: int) -> np.ndarray:
    return _made_edges(lo, hi, n)[0]


def _linear_edges(edges: np.ndarray) -> np.ndarray | None:
    """(lo, hi, step, n) as float64 if ``edges`` (n + 1 of them) are exactly
    ``k * step + lo`` for k < n and ``hi`` last, with ``step = (hi - lo) / n``, as
    ``numpy.linspace`` computes them; else None (then the bins are looked up in ``edges``)."""
    n = len(edges) - 1
    lo, hi = float(edges[0]), float(edges[n])
    step = (hi - lo) / n
    made = np.arange(n + 1, dtype=np.float64) * step + lo
    made[n] = hi
    return np.array([lo, hi, step, n], np.float64) if np.array_equal(made, edges) else None


def bin_edges(preset: ObservePreset) -> dict[str, np.ndarray]:
    """{"depth", "lateral", "sobel"} → (n + 1,) float64 bin edges (``numpy.linspace``)."""
    return {
        "depth": _edges(*preset.depth_range),
        "lateral": _edges(*preset.lateral_range),
        "sobel": _edges(*preset.sobel_range),
    }


def compute_stats(
    depth: np.ndarray,
    camera: PinholeCamera,
    mask: np.ndarray,
    preset: ObservePreset,
    *,
    sobel: bool | None = None,
) -> HistogramStats:
    """Histogram statistics of the foreground of one row-camera depth map.

    depth: (H, W) z-depth in metres (float32 or float64), ``camera.height × camera.width``;
    non-finite where nothing is seen.
    camera: the row camera the map was rendered with (only its intrinsics are used here).
    mask: (H, W) bool foreground. Every masked pixel must have a finite, positive depth; an
    empty mask is allowed (a prediction with nothing in view) and gives all-zero histograms.
    preset: bins, blur and normalisation (see the module docstring).
    sobel: compute the depth-derivative histogram (blur + Sobel, most of the cost). ``None``
    (default) = only if ``preset.loss.lambda_sobel > 0``; when skipped, ``stats.sobel`` is all
    zeros and ``stats.has_sobel`` is false (maize's λ_sobel is 0).

    Raises ``InputError`` for wrong shapes or dtypes, or masked pixels without a valid depth.
    """
    if not isinstance(preset, ObservePreset):
        raise InputError(f"preset must be an ObservePreset, got {type(preset).__name__}")
    if not isinstance(camera, PinholeCamera):
        raise InputError(f"camera must be a PinholeCamera, got {type(camera).__name__}")
    d = check_depth(depth, camera)
    m = check_mask(mask, d.shape)
    with_sobel = preset.loss.lambda_sobel > 0 if sobel is None else bool(sobel)
    filled = np.empty(d.shape, np.float32)
    n_fg, n_bad = _fill(d, m, float(preset.render_height), filled)
    if n_bad:
        raise InputError(
            f"mask marks {n_bad} pixel(s) whose depth is not a finite positive number; "
            "take the mask AND np.isfinite(depth)"
        )
    if with_sobel:
        dx, dy = _derivatives(filled, preset)
    else:
        dx = dy = filled  # not read
    made = [_made_edges(*r) for r in (preset.depth_range, preset.lateral_range, preset.sobel_range)]
    edges = [e for e, _ in made]
    linear = [par for _, par in made]
    yfac = lateral_factor(camera)
    if all(par is not None for par in linear):
        hd, hl, hs = _histograms(d, m, yfac, dx, dy, *linear, with_sobel)
    else:
        hd, hl, hs = _histograms_by_edges(d, m, yfac, dx, dy, *edges, with_sobel)
    n_pix = d.size
    denom = n_pix if preset.loss.normalisation == "image" else max(n_fg, 1)
    return HistogramStats(
        depth=hd / denom,
        lateral=hl / denom,
        sobel=hs / denom,
        mask_area=n_fg / n_pix,
        n_foreground=int(n_fg),
        n_pixels=int(n_pix),
        spec=preset.stats_spec(),
        has_sobel=with_sobel,
    )


__all__ = [
    "HistogramStats",
    "bin_edges",
    "check_depth",
    "check_mask",
    "compute_stats",
    "lateral_factor",
    "sobel_magnitude",
]
