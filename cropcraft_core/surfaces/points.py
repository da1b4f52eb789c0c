"""CPU visible surfaces as points: the stereo depth maps, filtered by visibility, splatted.

Pipeline (``PointSurfaces.fit``):

1–3. **Stereo** exactly as the tsdf backend (``stereo_depth_maps``: neighbours, plane-sweep
   stereo, consistency and box filters), with the same settings.
4. **Visibility.** Every filtered depth's point X is checked against every other view j's
   filtered depth map D_j at X's pixel: j *agrees* (|D_j − z_j(X)| ≤ ``visibility_rel`` · z_j),
   j *sees past* X (D_j > (1 + ``visibility_rel``) · z_j: X lies in what j saw as empty space),
   or j's surface is nearer (X is hidden from j, which says nothing). X stays where the views
   seeing past it number at most ``visibility_ratio`` times those agreeing with it. In a canopy
   stereo's errors are mostly surfaces in front of the true one: a matching window on a leaf's
   edge reaches over the gap beside it, the leaf fattens, and every view that looks down the
   gap sees past the fattened edge. A low leaf seen through a gap by a few views is hidden from
   the others, not contradicted, so it stays.
5. **Points.** Every surviving depth is a point with its photo's colour and a footprint radius,
   ``splat_radius`` times the side of its pixel at its depth.
6. **Rendering** splats the points as discs into a z-buffer, averages the depth and colour of the
   fragments within ``splat_blend`` (relative) of each pixel's nearest, and closes empty pixels
   that have ≥ 30 % of their ``splat_close`` × ``splat_close`` neighbourhood covered (the gaps
   between neighbouring splats; a real gap that small is a few millimetres wide). With
   ``splat_density`` set, every disc is first capped at the points' own spacing in the rendered
   view (``density_radii``). From a drone the source footprint is wide (1.5 cm radius from
   13 m) and every leaf edge fattens by it over the soil beside it; the cap keeps the edge
   where the points end. From a phone walking round the plot it hurts: the oblique views put
   points under the leaves, the count includes them, and what lies below shows through the
   smaller discs of the top leaves (``benchmarks/RESULTS.md``, *Maize through the photo
   pipeline*).

Why not fuse (the tsdf backend): a TSDF averages the views' signed distances per voxel, so a leaf
edge fattened in some views closes the gap beside it wherever those views outnumber the ones
seeing through, and its truncation spreads a skirt past the edge. In a dense canopy (true poses,
row camera at 1.25 m) 17 % of the row view sees a low leaf through a gap that the fused surface
covers with a leaf 0.3 m higher (median), and for 40 % of those pixels a filtered depth map
held the low leaf. Splatting the same depth maps without the visibility step is worse (the
fattened edges close the gaps: mask area +17 %). With it the observation's depth histogram is
closer to the true mesh's than the fused surface's on four of five synthetic canopies (L1 0.249
→ 0.133 on that one), but the fits of it miss the same two canopies as the fused surface's, and
the sparse canopies' leaf edges erode (mask area −17 % on the sparsest), so tsdf stays the
default (``benchmarks/RESULTS.md``, *LAI through the whole photo pipeline*). Through SfM the
points read two of three canopies' LAI closer, but the demo's (metric poses) +21.6 % against
the fusion's −0.3 % (*#sparse-77*).

``save`` writes ``points.ply`` (binary: float32 x y z, uint8 r g b, float32 radius).
"""

from __future__ import annotations

import time
from pathlib import Path

import cv2
import numpy as np
from numba import njit, prange

from cropcraft_core.errors import InputError
from cropcraft_core.geometry.camera import PinholeCamera
from cropcraft_core.surfaces.base import (
    Progress,
    SurfaceBackend,
    SurfacesError,
    check_inputs,
    in_bbox,
    subsample,
)
from cropcraft_core.surfaces.tsdf import (
    _resize_rgb,
    ply_count,
    read_ply,
    stereo_depth_maps,
    write_atomic,
)

POINTS_FILE = "points.ply"
#: share of a pixel's ``splat_close`` neighbourhood that must be covered to close it
CLOSE_MIN_COVER = 0.3
#: largest splat radius drawn (pixels)
MAX_SPLAT_PX = 64.0


# --------------------------------------------------------------------------- visibility


@njit(cache=True, parallel=True)
def _visibility_counts(pts, own, proj, stack, hw, rel, agree, past):  # pragma: no cover - numba
    """pts (n, 3) world points of view ``own``; proj (V, 3, 4) pixel projection matrices
    (K · [R | t], so the third coordinate is z-depth); stack (V, H, W) float32 depth maps (NaN
    empty, padded); hw (V, 2) their real sizes. Adds to agree / past (n,) the views agreeing
    with each point and those seeing past it."""
    n_v = proj.shape[0]
    for n in prange(pts.shape[0]):
        x, y, z = pts[n, 0], pts[n, 1], pts[n, 2]
        a = 0
        p = 0
        for j in range(n_v):
            if j == own:
                continue
            m = proj[j]
            zc = m[2, 0] * x + m[2, 1] * y + m[2, 2] * z + m[2, 3]
            if zc <= 0.0:
                continue
            u = (m[0, 0] * x + m[0, 1] * y + m[0, 2] * z + m[0, 3]) / zc
            v = (m[1, 0] * x + m[1, 1] * y + m[1, 2] * z + m[1, 3]) / zc
            if u < 0.0 or v < 0.0 or u >= hw[j, 1] or v >= hw[j, 0]:
                continue
            d = stack[j, int(v), int(u)]
            if not np.isfinite(d):
                continue
            if abs(d - zc) <= rel * zc:
                a += 1
            elif d > (1.0 + rel) * zc:
                p += 1
        agree[n] += a
        past[n] += p


def _projections(cams: list[PinholeCamera]) -> np.ndarray:
    return np.array([c.K @ c.world_to_cam[:3] for c in cams])


def visibility_filter(
    depths: list[np.ndarray], cams: list[PinholeCamera], rel: float, ratio: float
) -> list[np.ndarray]:
    """The depth maps (each (h, w) float32 z-depth matching its camera, NaN empty) with every
    depth removed whose point more views see past than ``ratio`` times the views agreeing with
    it (module docstring, step 4); the others' NaN stay."""
    h = max(d.shape[0] for d in depths)
    w = max(d.shape[1] for d in depths)
    stack = np.full((len(depths), h, w), np.nan, np.float32)
    for i, d in enumerate(depths):
        stack[i, : d.shape[0], : d.shape[1]] = d
    hw = np.array([d.shape for d in depths], np.int64)
    proj = _projections(cams)
    out = []
    for i, (d, cam) in enumerate(zip(depths, cams, strict=True)):
        ok = np.isfinite(d)
        pts = np.ascontiguousarray(cam.unproject(d)[ok])
        agree = np.zeros(len(pts), np.int64)
        past = np.zeros(len(pts), np.int64)
        _visibility_counts(pts, i, proj, stack, hw, float(rel), agree, past)
        vals = d[ok].astype(np.float32)
        vals[past > ratio * agree] = np.nan
        kept = np.full(d.shape, np.nan, np.float32)
        kept[ok] = vals
        out.append(kept)
    return out


# --------------------------------------------------------------------------- splatting


@njit(cache=True)
def _splat(uv, z, r, col, zmin, acc, cacc, wacc, blend):  # pragma: no cover - numba
    """One pass of discs (centres uv (n, 2) pixel coordinates, z-depth z, radius r pixels,
    colours col (n, 3)): blend < 0 writes each pixel's nearest depth into zmin; else it sums the
    depth and colour of fragments within ``blend`` (relative) of zmin into acc / cacc / wacc."""
    h, w = zmin.shape
    for i in range(len(z)):
        u, v, ri = uv[i, 0], uv[i, 1], r[i]
        cu, cv = int(np.floor(u)), int(np.floor(v))
        x0, x1 = max(0, int(np.floor(u - ri))), min(w - 1, int(np.floor(u + ri)))
        y0, y1 = max(0, int(np.floor(v - ri))), min(h - 1, int(np.floor(v + ri)))
        for y in range(y0, y1 + 1):
            for x in range(x0, x1 + 1):
                dx, dy = x + 0.5 - u, y + 0.5 - v
                if dx * dx + dy * dy > ri * ri and not (x == cu and y == cv):
                    continue
                if blend < 0.0:
                    if z[i] < zmin[y, x]:
                        zmin[y, x] = z[i]
                elif z[i] <= zmin[y, x] * (1.0 + blend):
                    acc[y, x] += z[i]
                    wacc[y, x] += 1.0
                    for c in range(3):
                        cacc[y, x, c] += col[i, c]


def density_radii(uv: np.ndarray, shape: tuple[int, int], coverage: float, window: int):
    """(n,) float64 disc radii (pixels) for points at pixel coordinates uv (n, 2) of an image of
    ``shape`` (h, w): ``coverage`` / √(π ρ), ρ the points per pixel in the ``window`` ×
    ``window`` pixels around each point (a point outside the image takes its nearest border
    pixel's). Discs of that radius cover 1 − exp(−coverage²) of an area sampled at random
    with density ρ (63 % at 1; ``_close`` fills most of the rest)."""
    h, w = shape
    iu = np.clip(np.floor(uv[:, 0]), 0, w - 1).astype(np.int64)
    iv = np.clip(np.floor(uv[:, 1]), 0, h - 1).astype(np.int64)
    inside = (uv[:, 0] >= 0) & (uv[:, 1] >= 0) & (uv[:, 0] < w) & (uv[:, 1] < h)
    count = np.bincount(iv[inside] * w + iu[inside], minlength=h * w).reshape(h, w)
    rho = cv2.boxFilter(count.astype(np.float32), -1, (window, window), normalize=True)
    return coverage / np.sqrt(np.pi * np.maximum(rho[iv, iu], 1e-6).astype(np.float64))


def splat(
    points: np.ndarray,
    colors: np.ndarray,
    radii: np.ndarray,
    camera: PinholeCamera,
    blend: float,
    close: int,
    density: float | None = None,
    window: int = 9,
) -> tuple[np.ndarray, np.ndarray]:
    """(depth (H, W) float32 z-depth, NaN empty; rgb (H, W, 3) uint8) of points (n, 3) with
    colours (n, 3) uint8 and world radii (n,) seen by ``camera`` (module docstring, step 6).
    ``density``: cap every disc at :func:`density_radii` with that coverage (None: no cap)."""
    h, w = camera.height, camera.width
    uv, z = camera.project(points)
    with np.errstate(invalid="ignore"):
        ok = (z > 0) & (np.abs(uv) < 1e6).all(axis=1)
    uv, z = np.ascontiguousarray(uv[ok]), z[ok]
    # a disc larger than MAX_SPLAT_PX pixels is a point almost at the camera: cap its cost
    r = np.minimum(np.asarray(radii)[ok] * camera.fx / z, MAX_SPLAT_PX).astype(np.float64)
    if density is not None:
        r = np.minimum(r, density_radii(uv, (h, w), float(density), int(window)))
    col = np.asarray(colors)[ok].astype(np.float64)
    z = z.astype(np.float32)
    zmin = np.full((h, w), np.inf, np.float32)
    acc, wacc, cacc = np.zeros((h, w)), np.zeros((h, w)), np.zeros((h, w, 3))
    _splat(uv, z, r, col, zmin, acc, cacc, wacc, -1.0)
    _splat(uv, z, r, col, zmin, acc, cacc, wacc, float(blend))
    seen = wacc > 0
    depth = np.where(seen, acc / np.maximum(wacc, 1.0), np.nan).astype(np.float32)
    rgb = cacc / np.maximum(wacc, 1.0)[..., None]
    if close > 1:
        depth, rgb = _close(depth, rgb, int(close))
    return depth, np.clip(np.rint(rgb), 0, 255).astype(np.uint8)


def _close(depth: np.ndarray, rgb: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
    """Empty pixels with ≥ ``CLOSE_MIN_COVER`` of their size × size neighbourhood covered take
    the neighbourhood's mean depth and colour."""
    ok = np.isfinite(depth)
    k = (size, size)
    n = cv2.boxFilter(ok.astype(np.float32), -1, k, normalize=False)
    s = cv2.boxFilter(np.where(ok, depth, 0.0).astype(np.float32), -1, k, normalize=False)
    cs = cv2.boxFilter((rgb * ok[..., None]).astype(np.float32), -1, k, normalize=False)
    fill = ~ok & (n >= CLOSE_MIN_COVER * size * size)
    nn = np.maximum(n, 1.0)
    depth = np.where(fill, s / nn, depth).astype(np.float32)
    rgb = np.where(fill[..., None], cs / nn[..., None], rgb)
    return depth, rgb


# --------------------------------------------------------------------------- the backend


class PointSurfaces(SurfaceBackend):
    """Visibility-filtered multi-view stereo points, rendered by splatting (CPU)."""

    name = "points"

    def __init__(self, config=None) -> None:
        super().__init__(config)
        self.points = np.zeros((0, 3))
        self.colors = np.zeros((0, 3), np.uint8)
        self.radii = np.zeros(0, np.float32)
        self.depth_maps: list[np.ndarray] = []
        """after ``fit``: per view the (h, w) float32 depth maps the points come from"""
        self.raw_depth_maps: list[np.ndarray] = []
        """after ``fit``: per view the (h, w) float32 stereo depth before any filtering"""

    def fit(self, images, cameras, bbox=None, progress: Progress | None = None) -> None:
        imgs, cams, box = check_inputs(images, cameras, bbox)
        cfg = self.config
        say = progress or (lambda stage, frac: None)
        st = stereo_depth_maps(imgs, cams, box, cfg, say)
        t = time.perf_counter()
        kept = visibility_filter(
            st.filtered, st.cameras, float(cfg.visibility_rel), float(cfg.visibility_ratio)
        )
        pts, cols, rad = [], [], []
        for im, cam, d in zip(imgs, st.cameras, kept, strict=True):
            ok = np.isfinite(d)
            pts.append(cam.unproject(d)[ok])
            cols.append(_resize_rgb(im, cam)[ok])
            rad.append(float(cfg.splat_radius) * d[ok] / cam.fx)
        say("visibility", 1.0)
        self.bbox = box
        self._set_points(np.concatenate(pts), np.concatenate(cols), np.concatenate(rad))
        if not len(self.points):  # before the cameras: a failed fit is not a fitted backend
            raise SurfacesError(
                "multi-view stereo found no consistent, visible surface: check the poses, the "
                "bounding box and the image overlap (or lower surfaces min_consistent / min_ncc)"
            )
        self.cameras = cams
        self.depth_maps = kept
        self.raw_depth_maps = st.raw
        self.timings = {**st.timings(), "visibility": time.perf_counter() - t}
        stages = ("sweep_range", "stereo", "consistency", "visibility")
        self.timings["total"] = sum(self.timings.get(k, 0.0) for k in stages)

    def _set_points(self, points, colors, radii) -> None:
        """Store the points exactly as ``save`` writes them (float32 positions and radii)."""
        self.points = np.asarray(points, np.float32).astype(np.float64).reshape(-1, 3)
        self.colors = np.asarray(colors, np.uint8).reshape(-1, 3)
        self.radii = np.asarray(radii, np.float32).reshape(-1)

    def render(self, camera: PinholeCamera) -> tuple[np.ndarray, np.ndarray]:
        self._require_fitted()
        if not isinstance(camera, PinholeCamera):
            raise InputError(f"camera must be a PinholeCamera, got {type(camera).__name__}")
        cfg = self.config
        return splat(
            self.points,
            self.colors,
            self.radii,
            camera,
            cfg.splat_blend,
            cfg.splat_close,
            cfg.splat_density,
            cfg.splat_density_window,
        )

    def point_cloud(self, n_max: int = 100_000) -> tuple[np.ndarray, np.ndarray]:
        """The points inside the bounding box with their colours (a seeded subset)."""
        self._require_fitted()
        keep = in_bbox(self.points, self.bbox)
        cols = self.colors[keep].astype(np.float64) / 255.0
        return subsample(self.points[keep], cols, n_max, self.config.seed)

    # ------------------------------------------------------------------ persistence
    def _save_payload(self, folder: Path) -> dict:
        write_points_ply(folder / POINTS_FILE, self.points, self.colors, self.radii)
        return {"points_file": POINTS_FILE, "points": len(self.points)}

    def _load_payload(self, folder: Path, meta: dict) -> None:
        self.depth_maps, self.raw_depth_maps = [], []
        self._set_points(*read_points_ply(folder / meta.get("points_file", POINTS_FILE)))


_VERTEX = np.dtype([("p", "<f4", (3,)), ("c", "u1", (3,)), ("r", "<f4")])


def write_points_ply(path: Path, points: np.ndarray, colors: np.ndarray, radii: np.ndarray):
    """Binary little-endian PLY of points (n, 3) (float32 x y z), colours (n, 3) uint8 and
    radii (n,) (float32 ``radius``, metres). Written atomically."""
    header = (
        "ply\nformat binary_little_endian 1.0\ncomment cropcraft visible surfaces, metres, z up\n"
        f"element vertex {len(points)}\nproperty float x\nproperty float y\nproperty float z\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\nproperty float radius\n"
        "end_header\n"
    ).encode("ascii")
    v = np.empty(len(points), _VERTEX)
    v["p"], v["c"], v["r"] = points, colors, radii
    return write_atomic(path, header + v.tobytes())


def read_points_ply(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Read what ``write_points_ply`` wrote: (points (n, 3) float64, colours (n, 3) uint8,
    radii (n,) float32)."""
    head, body = read_ply(path)
    n = ply_count(path, head, "vertex")
    if "property float radius" not in head:
        raise InputError(f"{path}: not a points file (no radius property)")
    if len(body) != n * _VERTEX.itemsize:
        raise InputError(f"{path}: size does not match its header (truncated?)")
    v = np.frombuffer(body, _VERTEX, n)
    return v["p"].astype(np.float64), v["c"].copy(), v["r"].copy()
