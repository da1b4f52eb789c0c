"""CPU visible surfaces: plane-sweep multi-view stereo, consistency filtering, TSDF fusion.

Pipeline (``TsdfSurfaces.fit``):

1. **Neighbours.** For every reference view, the source views whose triangulation angle at the
   reference view's look-at point is closest to ~12° (at least ~2°, the point in their frustum),
   ``config.neighbours`` of them.
2. **Plane-sweep stereo** per reference view at ``config.mvs_scale`` of the photo size:
   ``config.n_depths`` plane hypotheses, by default horizontal world planes z = h uniform in height
   (``config.sweep='horizontal'``: ground and near-horizontal leaves seen obliquely match on their
   own plane, the smoothing favours flat surfaces) over the heights the scene occupies, found by a
   coarse first pass over the bounding box's heights (``config.sweep_heights='auto'``,
   ``occupied_heights``), else fronto-parallel planes uniform in inverse depth; each
   source image is warped onto each plane by the plane-induced homography and compared with the
   reference by windowed normalised cross-correlation (box filters), on RGB (the mean of the
   channels' NCC; ``config.colour``) or grey. The per-source scores are aggregated by the mean of
   the best ``config.best_sources`` (by default the best half: robust to occlusion in some
   sources); semi-global matching along 4 paths (``config.sgm_p1``/``sgm_p2``); the best plane
   per pixel wins, refined to sub-plane precision by a parabola. Pixels whose score is below
   ``config.min_ncc`` are dropped.
3. **Consistency.** A depth survives where at least ``config.min_consistent`` neighbour depth maps
   agree with its reprojection within ``config.consistency_rel`` relative z-depth (and, with
   ``config.consistency_a_tol``, in colour: the CIELAB a* of the two pixels within it); depths
   outside the bounding box are dropped.
4. **Fusion.** Open3D's ``VoxelBlockGrid`` integrates the filtered depth maps with colour into a
   TSDF (``config.voxel_size``, truncation ``config.trunc_voxels`` voxels); marching cubes extracts
   a triangle mesh with vertex colours, cropped to the bounding box, from the cells whose voxels
   were all fused from two or more depth maps (``config.weight_threshold``), and (with
   ``config.fill_one_view``) a second, *fill* mesh: the faces that the cells with one or more
   depth maps add to it. Each depth map is fused into the voxel blocks near its own surfaces;
   with ``config.carve_free_space`` into every block any of them allocated, so the free space
   a view sees in front of its surfaces carves what others put there (opt-in: measured in
   ``benchmarks/RESULTS.md#carving``).
5. **Rendering** casts one ray per pixel centre at the mesh (Open3D ``RaycastingScene``), and the
   rays it leaves empty at the fill mesh, and interpolates the vertex colours with the hit's
   barycentric coordinates. In a dense canopy the low leaves seen through gaps are matched by few
   views; much of what survives the consistency filter reaches each voxel from one depth map only,
   so the two-view surface has holes there that the fill closes, while the leaf edges' one-view
   skirts stay behind the two-view surface wherever it has one.

``save`` writes the mesh as ``surface.ply`` and the fill as ``surface_fill.ply`` (binary, float32
positions, uint8 colours).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d
from numba import njit, prange

from cropcraft_core.errors import InputError
from cropcraft_core.geometry.camera import PinholeCamera
from cropcraft_core.render.raycast import build_scene
from cropcraft_core.rowfit.lab import srgb_to_lab
from cropcraft_core.surfaces.base import (
    Progress,
    SurfaceBackend,
    SurfacesConfig,
    SurfacesError,
    check_inputs,
    depth_limits,
    in_bbox,
    subsample,
)

MESH_FILE = "surface.ply"
FILL_FILE = "surface_fill.ply"
# Pixel-centre shift between PinholeCamera (centres at +0.5) and OpenCV/Open3D index coordinates.
_T_IDX = np.array([[1.0, 0.0, 0.5], [0.0, 1.0, 0.5], [0.0, 0.0, 1.0]])
_T_IDX_INV = np.linalg.inv(_T_IDX)


# --------------------------------------------------------------------------- neighbours


def look_at_point(camera: PinholeCamera, bbox: np.ndarray | None) -> np.ndarray:
    """(3,) the point the optical axis meets at the middle height of ``bbox`` (or 1.5 m ahead
    when there is no box or the axis does not go down to it)."""
    axis = camera.cam_to_world[:3, 2]
    c = camera.center
    if bbox is not None and axis[2] < -1e-3:
        zm = 0.5 * (bbox[0, 2] + bbox[1, 2])
        t = (zm - c[2]) / axis[2]
        if t > 0:
            return c + t * axis
    return c + 1.5 * axis


def select_neighbours(
    cameras: list[PinholeCamera], k: int, bbox: np.ndarray | None, best_angle_deg: float = 12.0
) -> list[list[int]]:
    """For every camera, the indices of up to ``k`` source views for stereo, best first.

    Score of source j for reference i: a Gaussian of the triangulation angle at i's look-at point
    around ``best_angle_deg`` (σ 5° below it, 15° above), zero below 2° or where the point is
    outside j's frustum or the optical axes differ by more than 70°.
    """
    n = len(cameras)
    centres = np.array([c.center for c in cameras])
    axes = np.array([c.cam_to_world[:3, 2] for c in cameras])
    out = []
    for i, ci in enumerate(cameras):
        p = look_at_point(ci, bbox)
        a = centres[i] - p
        b = centres - p
        cosang = (b @ a) / (np.linalg.norm(b, axis=1) * np.linalg.norm(a) + 1e-12)
        ang = np.degrees(np.arccos(np.clip(cosang, -1, 1)))
        sigma = np.where(ang < best_angle_deg, 5.0, 15.0)
        score = np.exp(-((ang - best_angle_deg) ** 2) / (2 * sigma**2))
        score[ang < 2.0] = 0.0
        score[(axes @ axes[i]) < math.cos(math.radians(70))] = 0.0
        for j in range(n):
            if score[j] > 0:
                uv, z = cameras[j].project(p[None])
                u, v = uv[0]
                if not (z[0] > 0 and 0 <= u < cameras[j].width and 0 <= v < cameras[j].height):
                    score[j] = 0.0
        score[i] = 0.0
        order = [int(j) for j in np.argsort(-score, kind="stable") if score[j] > 0][:k]
        out.append(order)
    return out


# --------------------------------------------------------------------------- stereo


def stereo_scale(camera: PinholeCamera, cfg: SurfacesConfig) -> float:
    """The scale a photo of ``camera`` is matched at: ``cfg.mvs_scale``, or less, so that its
    longest side stays within ``cfg.mvs_max_side`` pixels (stereo's memory grows with the
    photo's pixels)."""
    scale = float(cfg.mvs_scale)
    if cfg.mvs_max_side is not None:
        scale = min(scale, int(cfg.mvs_max_side) / max(camera.width, camera.height))
    return scale


def to_grey(image: np.ndarray, camera: PinholeCamera, scale: float) -> np.ndarray:
    """(h, w) float32 grey image in [0, 1] at ``scale`` of (H, W, 3) uint8 ``image`` (area
    resampling), matching ``camera.scaled(scale)``."""
    small = camera.scaled(scale)
    g = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    if (small.width, small.height) != (camera.width, camera.height):
        g = cv2.resize(g, (small.width, small.height), interpolation=cv2.INTER_AREA)
    return g.astype(np.float32) / 255.0


def to_colour(image: np.ndarray, camera: PinholeCamera, scale: float) -> np.ndarray:
    """(h, w, 3) float32 RGB in [0, 1] at ``scale`` of (H, W, 3) uint8 ``image`` (area
    resampling), matching ``camera.scaled(scale)``."""
    return _resize_rgb(image, camera.scaled(scale)).astype(np.float32) / 255.0


def _resize_rgb(image: np.ndarray, camera: PinholeCamera) -> np.ndarray:
    if image.shape[:2] == (camera.height, camera.width):
        return image
    return cv2.resize(image, (camera.width, camera.height), interpolation=cv2.INTER_AREA)


def plane_homography(
    ref: PinholeCamera, src: PinholeCamera, normal: np.ndarray, offset: float
) -> np.ndarray:
    """(3, 3) homography taking reference pixel index coordinates to source pixel index
    coordinates (OpenCV: pixel centres at integers) for points X on the plane
    ``normal · X = offset`` (X, normal (3,) in reference camera coordinates, offset in metres;
    the fronto-parallel plane at z-depth d is normal (0, 0, 1), offset d)."""
    rel = src.world_to_cam @ ref.cam_to_world  # ref camera → src camera
    r, t = rel[:3, :3], rel[:3, 3]
    h = src.K @ (r + np.outer(t, np.asarray(normal, np.float64)) / offset) @ np.linalg.inv(ref.K)
    return _T_IDX_INV @ h @ _T_IDX


def sweep_planes(
    ref: PinholeCamera,
    n_planes: int,
    near: float,
    far: float,
    heights: tuple[float, float] | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The plane hypotheses of one reference view.

    Fronto-parallel (``heights`` None): ``n_planes`` planes uniform in inverse z-depth over
    [near, far]. Horizontal (``heights`` = (z_lo, z_hi), world metres): planes z = h uniform in h
    over that range (below the camera), so that neighbouring pixels on the ground or on a flat leaf
    share a hypothesis and the spacing is uniform in height.

    Returns (normals (P, 3) and offsets (P,) of the planes ``normal · X = offset`` in reference
    camera coordinates, params (P,): the swept parameter, inverse depth or height, uniform).
    """
    n = int(n_planes)
    if heights is None:
        inv = np.linspace(1.0 / near, 1.0 / far, n)
        normals = np.tile([0.0, 0.0, 1.0], (n, 1))
        return normals, 1.0 / inv, inv
    cz = float(ref.center[2])
    lo, hi = float(heights[0]), min(float(heights[1]), cz - 0.05)
    if hi <= lo:
        raise InputError(f"camera at z = {cz:.2f} m is not above the height range {heights}")
    hs = np.linspace(lo, hi, n)
    up = ref.cam_to_world[2, :3]  # world z of camera coordinates: z_w = up · X + c_z
    return np.tile(up, (n, 1)), hs - cz, hs


def plane_depth(ref: PinholeCamera, params: np.ndarray, horizontal: bool) -> np.ndarray:
    """(h, w) float32 z-depth of reference pixels on the plane of (fractional) swept parameter
    ``params`` (h, w) (inverse depth, or height for horizontal planes); NaN where the ray does
    not go down to a horizontal plane."""
    if not horizontal:
        return (1.0 / params).astype(np.float32)
    dz = ref.ray_directions(normalized=False)[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        d = (params - ref.center[2]) / dz
    return np.where((dz < -1e-6) & (d > 0), d, np.nan).astype(np.float32)


def plane_sweep(
    ref_img: np.ndarray,
    ref: PinholeCamera,
    src_imgs: list[np.ndarray],
    srcs: list[PinholeCamera],
    near: float,
    far: float,
    n_depths: int = 128,
    window: int = 7,
    p1: float = 0.05,
    p2: float = 1.0,
    heights: tuple[float, float] | None = None,
    best_sources: int = 0,
    shiftable: bool = False,
) -> tuple[np.ndarray, np.ndarray]:
    """Plane-sweep stereo of one reference view with semi-global cost aggregation.

    ref_img: (h, w) or (h, w, c) float32 reference image matching ``ref``; src_imgs: (h_j, w_j[,
    c]) images matching ``srcs``. Hypotheses: ``n_depths`` planes (``sweep_planes``:
    fronto-parallel uniform in inverse depth over [near, far], or horizontal z = h over
    ``heights``). Matching cost: 1 − NCC over a ``window`` × ``window`` window (the mean over
    channels; with ``shiftable``, per source the best of the windows that contain the pixel, so
    a pixel beside a depth edge can match on a window wholly on its own side), the mean of the
    ``best_sources`` best sources (0: the best half, ``best_of``);
    aggregated along 4 image paths (SGM, penalties ``p1`` for a one-plane step, ``p2`` for a
    jump). Returns (depth (h, w) float32 z-depth, refined to sub-plane precision by a parabola,
    NaN where no plane is valid; score (h, w) float32, the aggregated NCC at the winning plane,
    −1 where no source sees the pixel or the winner is the first or last plane).
    """
    ref_img = ref_img if ref_img.ndim == 3 else ref_img[..., None]
    src_imgs = [g if g.ndim == 3 else g[..., None] for g in src_imgs]
    h, w, nc = ref_img.shape
    normals, offsets, params = sweep_planes(ref, n_depths, near, far, heights)
    homs = np.array(
        [
            [plane_homography(ref, c, nv, o) for c in srcs]
            for nv, o in zip(normals, offsets, strict=True)
        ]
    )
    hs = max(g.shape[0] for g in src_imgs)
    ws = max(g.shape[1] for g in src_imgs)
    stack = np.zeros((len(srcs), nc, hs, ws), np.float32)
    for s, g in enumerate(src_imgs):
        stack[s, :, : g.shape[0], : g.shape[1]] = np.moveaxis(g, 2, 0)
    hw = np.array([g.shape[:2] for g in src_imgs], np.int64)
    vol = np.empty((h, w, len(params)), np.float32)
    _sweep_ncc(
        np.ascontiguousarray(np.moveaxis(ref_img, 2, 0), np.float32), stack, hw, homs,
        int(window) // 2, int(window) // 2 if shiftable else 0, best_of(len(srcs), best_sources),
        vol,
    )  # fmt: skip
    agg = _sgm(1.0 - vol, float(p1), float(p2)) if p2 > 0 else 1.0 - vol
    n_p = len(params)
    best = np.argmin(agg, axis=2)
    s0 = np.take_along_axis(agg, best[..., None], 2)[..., 0]
    lo = np.take_along_axis(agg, np.maximum(best - 1, 0)[..., None], 2)[..., 0]
    hi = np.take_along_axis(agg, np.minimum(best + 1, n_p - 1)[..., None], 2)[..., 0]
    denom = lo - 2 * s0 + hi
    with np.errstate(divide="ignore", invalid="ignore"):
        off = np.where(denom > 1e-9, 0.5 * (lo - hi) / denom, 0.0)
    inner = (best > 0) & (best < n_p - 1)
    off = np.where(inner, np.clip(off, -0.5, 0.5), 0.0)
    q = params[0] + (best + off) * (params[1] - params[0])
    depth = plane_depth(ref, q, heights is not None)
    score = np.take_along_axis(vol, best[..., None], 2)[..., 0]
    score = np.where(inner & np.isfinite(depth), score, -1.0).astype(np.float32)
    return depth, score


def best_of(n_sources: int, best_sources: int) -> int:
    """How many best-scoring sources a plane's score averages: ``best_sources`` (0: half of
    ``n_sources``, rounded up), at least 1 and at most ``n_sources``."""
    k = (n_sources + 1) // 2 if best_sources <= 0 else best_sources
    return max(1, min(int(k), n_sources))


# No fastmath: with it, this parallel kernel compiled in the process and the same kernel loaded
# from numba's cache (every later run) round differently (numba/numba#10617: fresh and cached
# parallel code are optimised differently), so a scene's first reconstruction on a machine
# differed from its reruns in the last bits of the matching scores, and a tie in the fit can
# turn on those (benchmarks/RESULTS.md, *#compile-state*). Without it the two agree to the bit.
# error_model="numpy": a float division is IEEE's, with no zero check, so the loops below can be
# vectorised; every divisor that is read is nonzero (RESULTS, *#stereo-simd-85*).
@njit(cache=True, parallel=True, fastmath=False, error_model="numpy")
def _sweep_ncc(ref, srcs, src_hw, homs, half, shift, m_best, out):  # pragma: no cover - numba
    """ref (C, h, w) float32; srcs (S, C, hs, ws) float32, C-contiguous; src_hw (S, 2) int64 real
    sizes; homs (D, S, 3, 3) float64 ref index pixel -> src index pixel; out (h, w, D) float32
    aggregated NCC (per source the mean over the C channels of their NCC, with ``shift`` > 0 the
    best of that over the windows centred up to ``shift`` pixels away in x and y; the mean of the
    best m_best sources; -1 where fewer sources see the pixel).

    Windows are (2 half + 1)² pixels clipped at the image border; a source pixel that does not
    see the plane counts as 0 in its neighbours' windows. Each thread takes whole planes and
    streams each source through it a row at a time (RESULTS, *#stereo-stream*): the row is
    warped (bilinear), its products q, q², q·r summed into column sums over the window's rows
    (the row leaving the window subtracted again), and the output row's window sums read from
    running sums along those columns, so the working set is a few rows and every pass but the
    warp runs along contiguous rows."""
    n_c, h, w = ref.shape
    n_d, n_s = homs.shape[0], homs.shape[1]
    wp = srcs.shape[3]
    plane = srcs.shape[2] * wp
    flat = srcs.reshape(n_s * n_c * plane)
    # unsigned offsets: numba adds a negative-index check to every signed index
    uwp = np.uint64(wp)
    uplane = np.uint64(plane)
    one = np.uint64(1)
    nwin = 2 * half + 1
    uhalf = np.uint64(half)
    inv_nx = np.empty(w)  # 1 / the window's width at each column
    for x in range(w):
        inv_nx[x] = 1.0 / (min(w, x + half + 1) - max(0, x - half))
    # the reference's window mean and 1 / standard deviation, the same for every plane and source
    ref_m = np.empty((h, n_c, w))
    ref_is = np.empty((h, n_c, w))
    for y in range(h):
        y0 = max(0, y - half)
        y1 = min(h, y + half + 1)
        for c in range(n_c):
            for x in range(w):
                x0 = max(0, x - half)
                x1 = min(w, x + half + 1)
                t1 = 0.0
                t2 = 0.0
                for yy in range(y0, y1):
                    for xx in range(x0, x1):
                        r = np.float64(ref[c, yy, xx])
                        t1 += r
                        t2 += r * r
                inv = inv_nx[x] / (y1 - y0)
                mr = t1 * inv
                vr = max(t2 * inv - mr * mr + 1e-5, 1e-5)
                ref_m[y, c, x] = mr
                ref_is[y, c, x] = 1.0 / np.sqrt(vr)
    for k in prange(n_d):
        scores = np.empty((n_s, h, w), np.float32)
        seen = np.empty((h, w), np.bool_)
        qring = np.empty((nwin, n_c, w), np.float32)  # the warped rows of the current window
        col = np.empty((n_c, 3, w))  # column sums of q, q², q·r over the window's rows
        pre = np.zeros((3, w + 1))  # running sums of those along the output row (pre[:, 0] = 0)
        p0 = pre[0]
        p1 = pre[1]
        p2 = pre[2]
        acc = np.empty(w)
        su = np.empty(w)  # a row's source coordinates, and whether the plane lies in front
        sv = np.empty(w)
        front = np.empty(w, np.bool_)
        tmp = np.empty((h, w), np.float32)
        rank = np.empty(w, np.int32)
        tot = np.empty(w)
        for s in range(n_s):
            hs, ws = src_hw[s, 0], src_hw[s, 1]
            wsm = ws - 1.0
            hsm = hs - 1.0
            m = homs[k, s]
            h00, h01, h02 = m[0, 0], m[0, 1], m[0, 2]
            h10, h11, h12 = m[1, 0], m[1, 1], m[1, 2]
            h20, h21, h22 = m[2, 0], m[2, 1], m[2, 2]
            base = np.uint64(s * n_c * plane)
            col[:, :, :] = 0.0
            for y in range(h + half):
                if y < h:
                    # warp row y of the source onto the plane (0 where it does not see it)
                    wq = qring[y % nwin]
                    ax = h01 * y + h02
                    bx = h11 * y + h12
                    cz = h21 * y + h22
                    # the projective division in a loop of its own (vectorised), then the
                    # bilinear lookups (gathers); the coordinates where pz <= 1e-9 are not read
                    for x in range(w):
                        pz = h20 * x + cz
                        ip = 1.0 / pz
                        su[x] = (h00 * x + ax) * ip
                        sv[x] = (h10 * x + bx) * ip
                        front[x] = pz > 1e-9
                    for x in range(w):
                        ok = False
                        if front[x]:
                            u = su[x]
                            v = sv[x]
                            if u >= 0.0 and v >= 0.0 and u <= wsm and v <= hsm:
                                x0 = min(int(u), ws - 2)
                                y0 = min(int(v), hs - 2)
                                fx = np.float32(u - x0)
                                fy = np.float32(v - y0)
                                gx = np.float32(1.0) - fx
                                gy = np.float32(1.0) - fy
                                i = base + np.uint64(y0 * wp + x0)
                                for c in range(n_c):
                                    j = i + uwp
                                    a = flat[i] * gx + flat[i + one] * fx
                                    b = flat[j] * gx + flat[j + one] * fx
                                    wq[c, x] = a * gy + b * fy
                                    i += uplane
                                ok = True
                        if not ok:
                            for c in range(n_c):
                                wq[c, x] = 0.0
                        seen[y, x] = ok
                    _add_row(col, wq, ref, y, 1.0)
                yo = y - half
                if yo < 0:
                    continue
                # output row yo: the window's rows max(0, yo - half) .. min(h - 1, yo + half)
                inv_ny = 1.0 / (min(h, yo + half + 1) - max(0, yo - half))
                acc[:] = 0.0
                for c in range(n_c):
                    c0 = col[c, 0]
                    c1 = col[c, 1]
                    c2 = col[c, 2]
                    r0 = 0.0
                    r1 = 0.0
                    r2 = 0.0
                    for x in range(w):
                        r0 += c0[x]
                        r1 += c1[x]
                        r2 += c2[x]
                        p0[x + 1] = r0
                        p1[x + 1] = r1
                        p2[x + 1] = r2
                    rm = ref_m[yo, c]
                    ri = ref_is[yo, c]
                    for x in range(min(half, w)):  # windows clipped on the left
                        x1 = min(w, x + half + 1)
                        acc[x] += _ncc(p0[x1] - p0[0], p1[x1] - p1[0], p2[x1] - p2[0],
                                       inv_nx[x] * inv_ny, rm[x], ri[x])  # fmt: skip
                    # unsigned indices: with signed ones numba wraps negative indices, and that
                    # branch keeps LLVM from vectorising the loop
                    for x in range(half, w - half):
                        ux = np.uint64(x)
                        a0 = ux - uhalf
                        a1 = ux + uhalf + one
                        acc[ux] += _ncc(p0[a1] - p0[a0], p1[a1] - p1[a0], p2[a1] - p2[a0],
                                        inv_nx[ux] * inv_ny, rm[ux], ri[ux])  # fmt: skip
                    for x in range(max(half, w - half), w):  # clipped on the right
                        x0 = max(0, x - half)
                        acc[x] += _ncc(p0[w] - p0[x0], p1[w] - p1[x0], p2[w] - p2[x0],
                                       inv_nx[x] * inv_ny, rm[x], ri[x])  # fmt: skip
                sy = scores[s, yo]
                sn = seen[yo]
                for x in range(w):
                    sy[x] = acc[x] / n_c if sn[x] else -1.0
                ylo = yo - half  # the row leaving the window
                if ylo >= 0:
                    _add_row(col, qring[ylo % nwin], ref, ylo, -1.0)
            if shift > 0:
                # shiftable windows: the best of the windows that contain the pixel (a max
                # filter of the centred windows' scores), rows then columns
                for y in range(h):
                    for x in range(w):
                        b = -1.0
                        for xx in range(max(0, x - shift), min(w, x + shift + 1)):
                            if scores[s, y, xx] > b:
                                b = scores[s, y, xx]
                        tmp[y, x] = b
                for y in range(h):
                    for x in range(w):
                        if not seen[y, x]:
                            continue
                        b = -1.0
                        for yy in range(max(0, y - shift), min(h, y + shift + 1)):
                            if tmp[yy, x] > b:
                                b = tmp[yy, x]
                        scores[s, y, x] = b
        # aggregate: the mean of the best m_best sources. A source counts where fewer than
        # m_best others beat it (ties to the lower index): counted along the row, without the
        # data-dependent branches of a selection
        for y in range(h):
            tot[:] = 0.0
            for s in range(n_s):
                mine = scores[s, y]
                rank[:] = 0
                for t in range(s):
                    other = scores[t, y]
                    for x in range(w):
                        rank[x] += np.int32(other[x] >= mine[x])
                for t in range(s + 1, n_s):
                    other = scores[t, y]
                    for x in range(w):
                        rank[x] += np.int32(other[x] > mine[x])
                for x in range(w):
                    tot[x] += mine[x] if rank[x] < m_best else np.float32(0.0)
            for x in range(w):
                out[y, x, k] = tot[x] / m_best


@njit(cache=True, inline="always", error_model="numpy")
def _add_row(col, wq, ref, y, sign):  # pragma: no cover - numba
    """col (C, 3, w) += sign × (q, q², q·r) of the warped row wq (C, w) against ref's row y."""
    for c in range(wq.shape[0]):
        qr = wq[c]
        rr = ref[c, y]
        c0 = col[c, 0]
        c1 = col[c, 1]
        c2 = col[c, 2]
        for x in range(wq.shape[1]):
            q = np.float64(qr[x])
            c0[x] += sign * q
            c1[x] += sign * (q * q)
            c2[x] += sign * (q * rr[x])


@njit(cache=True, inline="always", error_model="numpy")
def _ncc(s0, s1, s2, inv, rm, ri):  # pragma: no cover - numba
    """NCC of a window from its sums of q, q², q·r, 1 / its pixel count, the reference's window
    mean and 1 / standard deviation (variances floored at 1e-5, as the reference's; the floor a
    select rather than ``max``, which vectorises)."""
    mw = s0 * inv
    vw = s1 * inv - mw * mw + 1e-5
    vw = vw if vw > 1e-5 else 1e-5
    return (s2 * inv - rm * mw) * (ri / np.sqrt(vw))


@njit(cache=True)
def _path(cost, agg, y0, x0, dy, dx, p1, p2):  # pragma: no cover - numba
    h, w, n_d = cost.shape
    prev = np.empty(n_d)
    cur = np.empty(n_d)
    y = np.int64(y0)
    x = np.int64(x0)
    first = True
    pmin = 0.0
    while 0 <= y < h and 0 <= x < w:
        if first:
            for d in range(n_d):
                cur[d] = cost[y, x, d]
            first = False
        else:
            for d in range(n_d):
                best = prev[d]
                if d > 0 and prev[d - 1] + p1 < best:
                    best = prev[d - 1] + p1
                if d < n_d - 1 and prev[d + 1] + p1 < best:
                    best = prev[d + 1] + p1
                if pmin + p2 < best:
                    best = pmin + p2
                cur[d] = cost[y, x, d] + best - pmin
        pmin = 1e30
        for d in range(n_d):
            agg[y, x, d] += cur[d]
            prev[d] = cur[d]
            if cur[d] < pmin:
                pmin = cur[d]
        y += dy
        x += dx


@njit(cache=True, parallel=True)
def _sgm(cost, p1, p2):  # pragma: no cover - numba
    """cost (h, w, D) float32 → (h, w, D) float32 sum of 4 path aggregations (SGM)."""
    h, w, n_d = cost.shape
    agg = np.zeros((h, w, n_d), np.float32)
    for y in prange(h):
        _path(cost, agg, y, 0, 0, 1, p1, p2)
        _path(cost, agg, y, w - 1, 0, -1, p1, p2)
    for x in prange(w):
        _path(cost, agg, 0, x, 1, 0, p1, p2)
        _path(cost, agg, h - 1, x, -1, 0, p1, p2)
    return agg


# --------------------------------------------------------------------------- consistency


def _pixels(
    camera: PinholeCamera, points: np.ndarray, shape: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Where the (n, 3) world ``points`` fall in an (h, w) image of ``camera``: (n,) bool in
    the image and in front of it, (n,) row and column (valid where that is True), (n,) the
    points' z-depths."""
    uv, z = camera.project(points)
    ok = np.isfinite(uv).all(axis=1) & (z > 0)
    u = np.floor(np.where(ok, uv[:, 0], -1)).astype(np.int64)
    v = np.floor(np.where(ok, uv[:, 1], -1)).astype(np.int64)
    h, w = shape
    ok &= (u >= 0) & (u < w) & (v >= 0) & (v < h)
    return ok, v, u, z


def sample_depth(
    depth: np.ndarray, camera: PinholeCamera, points: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(n,) value of the (h, w) depth map ``depth`` (matching ``camera``) at the pixel each of
    the (n, 3) world ``points`` projects to (NaN off the image or behind the camera), and (n,)
    the points' own z-depths in that camera."""
    ok, v, u, z = _pixels(camera, points, depth.shape)
    out = np.full(len(points), np.nan)
    out[ok] = depth[v[ok], u[ok]]
    return out, z


def consistency_count(
    depths: list[np.ndarray],
    cams: list[PinholeCamera],
    i: int,
    others: list[int],
    rel: float,
    a_star: list[np.ndarray] | None = None,
    a_tol: float | None = None,
) -> np.ndarray:
    """(h, w) int: for every valid pixel of depth map i, how many of the depth maps ``others``
    see its 3D point at the same z-depth within ``rel`` (relative). With ``a_star`` (per view,
    the (h, w) CIELAB a* of its image at its depth map's size) and ``a_tol``, a view counts
    only where its pixel's a* is also within ``a_tol`` of the depth's own pixel's
    (``SurfacesConfig.consistency_a_tol``)."""
    d = depths[i]
    valid = np.isfinite(d)
    count = np.zeros(d.shape, np.int32)
    if not valid.any():
        return count
    colour = a_star is not None and a_tol is not None
    pts = cams[i].unproject(d)[valid]
    a_ref = a_star[i][valid] if colour else None
    for j in others:
        ok, v, u, z = _pixels(cams[j], pts, depths[j].shape)
        agree = np.zeros(len(pts), bool)
        dj = depths[j][v[ok], u[ok]]
        with np.errstate(invalid="ignore"):
            agree[ok] = np.abs(dj - z[ok]) <= rel * z[ok]
        if colour:
            agree[ok] &= np.abs(a_star[j][v[ok], u[ok]] - a_ref[ok]) <= a_tol
        count[valid] += agree
    return count


# --------------------------------------------------------------------------- the stereo stage


@dataclass
class StereoDepths:
    """Per-view depth maps of the stereo stage (steps 1–3), shared by the tsdf and points
    backends. cameras: the photos' cameras at ``mvs_scale`` (the maps' size); raw: stereo's
    z-depth maps (NaN where no plane matched); filtered: after the consistency and box filters;
    limits: each view's (near, far) z-depth; heights: the (low, high) world heights the
    horizontal planes spanned (None: fronto-parallel planes)."""

    cameras: list[PinholeCamera]
    raw: list[np.ndarray]
    filtered: list[np.ndarray]
    limits: list[tuple[float, float]]
    stereo_s: float
    consistency_s: float
    heights: tuple[float, float] | None = None
    range_s: float = 0.0

    def timings(self) -> dict[str, float]:
        out = {
            "stereo": self.stereo_s,
            "consistency": self.consistency_s,
            "valid_fraction": float(np.mean([np.isfinite(d).mean() for d in self.filtered])),
        }
        if self.heights is not None:
            out.update(sweep_low=float(self.heights[0]), sweep_high=float(self.heights[1]))
        if self.range_s:
            out["sweep_range"] = self.range_s
        return out


#: The height-range pass (``occupied_heights``) matches at this share of ``mvs_scale`` with
#: this share of ``n_depths`` planes: ~1/8 of the main pass's work.
RANGE_PASS_SCALE = 0.5
RANGE_PASS_PLANES = 0.5
#: The soil: the pass's consistent points with a* at least ``SurfacesConfig.soil_a_min``,
#: binned by height; the lowest layer of them that stands out is the ground (``soil_height``).
SOIL_BIN_M = 0.02
SOIL_MIN_POINTS = 100
SOIL_PEAK_RATIO = 3.0
SOIL_LAYER_M = 0.1
SOIL_BELOW_M = 0.3
#: The range reaches this far below the ground and above the ``RANGE_TOP_PERCENTILE`` of all
#: the pass's points: ``RANGE_MARGIN_PLANES`` of the pass's plane spacings, at least
#: ``RANGE_MARGIN_M``.
RANGE_TOP_PERCENTILE = 99.9
RANGE_MARGIN_PLANES = 3.0
RANGE_MARGIN_M = 0.1


def _match_views(
    views: list[np.ndarray],
    small: list[PinholeCamera],
    nbrs: list[list[int]],
    limits: list[tuple[float, float]],
    heights: tuple[float, float] | None,
    box: np.ndarray | None,
    cfg: SurfacesConfig,
    n_depths: int,
    say: Progress,
    stage: str,
    a_star: list[np.ndarray] | None = None,
) -> tuple[list[np.ndarray], list[np.ndarray], float]:
    """Plane-sweep stereo of every view, then the consistency and box filters: (raw maps,
    filtered maps, seconds of stereo). ``views``: the images at ``small``'s size, grey or
    colour as the caller prepared them (``cfg.colour`` is not read here); ``a_star``: their
    CIELAB a* where ``cfg.consistency_a_tol`` is set (:func:`a_star_maps`)."""
    t0 = time.perf_counter()
    raw: list[np.ndarray] = []
    for i in range(len(small)):
        if not nbrs[i]:
            raw.append(np.full(views[i].shape[:2], np.nan, np.float32))
            continue
        near, far = limits[i]
        depth, score = plane_sweep(
            views[i], small[i], [views[j] for j in nbrs[i]], [small[j] for j in nbrs[i]],
            near, far, int(n_depths), int(cfg.window), float(cfg.sgm_p1),
            float(cfg.sgm_p2), heights, int(cfg.best_sources), bool(cfg.shiftable_windows),
        )  # fmt: skip
        # -1: no match (no source saw the pixel, or the best plane was the first or last), which
        # min_ncc = -1, the setting's least, kept
        depth[(score < cfg.min_ncc) | (score <= -1.0)] = np.nan
        if cfg.depth_range is not None:  # horizontal planes span the box's heights, not it
            depth[(depth < near) | (depth > far)] = np.nan
        raw.append(depth)
        say(stage, (i + 1) / len(small))
    stereo_s = time.perf_counter() - t0
    filtered = []
    for i in range(len(small)):
        d = raw[i].copy()
        if cfg.min_consistent > 0:
            # the views this one was matched with and those matched with it
            others = sorted(set(nbrs[i]) | {j for j in range(len(small)) if i in nbrs[j]})
            cnt = consistency_count(
                raw, small, i, others, cfg.consistency_rel, a_star, cfg.consistency_a_tol
            )
            d[cnt < cfg.min_consistent] = np.nan
        if box is not None:
            pts = small[i].unproject(d)
            inside = np.all((pts >= box[0]) & (pts <= box[1]), axis=-1)
            d[~inside] = np.nan
        filtered.append(d)
    return raw, filtered, stereo_s


def a_star_maps(colours: list[np.ndarray], cfg: SurfacesConfig) -> list[np.ndarray] | None:
    """Per view, the (h, w) float32 CIELAB a* of its (h, w, 3) RGB in [0, 1], where
    ``cfg.consistency_a_tol`` is set; else None (the consistency filter then reads geometry
    only)."""
    if cfg.consistency_a_tol is None:
        return None
    return [srgb_to_lab(c, 1.0)[..., 1].astype(np.float32) for c in colours]


def occupied_heights(
    imgs: list[np.ndarray],
    cams: list[PinholeCamera],
    nbrs: list[list[int]],
    limits: list[tuple[float, float]],
    box: np.ndarray,
    cfg: SurfacesConfig,
    say: Progress,
) -> tuple[float, float]:
    """The world heights the scene occupies, from a coarse stereo pass over the box's heights
    (``RANGE_PASS_SCALE`` of the photos' stereo size, ``RANGE_PASS_PLANES`` of the planes):
    from just below the soil (the height where soil-coloured points pile up, ``SOIL_*``) to just
    above the top of all its points, inside the box. Where no soil layer stands out, the range
    starts at the box's bottom.

    Why: the box's heights are generous because levelling's ground can sit on the leaves when
    SfM saw no soil (soybean's box reaches 1.2 m below it, maize's 3.5 m). Planes under the soil
    are not only wasted: in a dense canopy, views looking into the foliage find wrong matches on
    them that other views confirm. Walking round a 1.1 m soybean canopy (true poses), the sweep
    from 1.2 m below the ground left a third of the row view without a surface; from 0.15 m
    below, an eighth (``benchmarks/RESULTS.md``, *The sweep's height range*). The bottom comes
    from the soil, not from a low percentile of all the points, because those wrong matches
    fill the heights below the soil about as densely as the few soil points seen through a
    closed canopy."""
    lo, hi = float(box[0, 2]), float(box[1, 2])
    scales = [stereo_scale(c, cfg) * RANGE_PASS_SCALE for c in cams]
    small = [c.scaled(s) for c, s in zip(cams, scales, strict=True)]
    colours = [to_colour(im, c, s) for im, c, s in zip(imgs, cams, scales, strict=True)]
    n = max(16, int(round(int(cfg.n_depths) * RANGE_PASS_PLANES)))
    # matched on colour whatever ``cfg.colour`` says: the soil is found by its colour
    _, filtered, _ = _match_views(
        colours, small, nbrs, limits, (lo, hi), box, cfg, n, say, "stereo range",
        a_star_maps(colours, cfg),
    )  # fmt: skip
    ok = [np.isfinite(d) for d in filtered]
    z = np.concatenate(
        [c.unproject(d)[m][:, 2] for c, d, m in zip(small, filtered, ok, strict=True)]
    )
    if not len(z):
        return lo, hi
    rgb = np.concatenate([g[m] for g, m in zip(colours, ok, strict=True)])
    top = min(hi, max(float(c.center[2]) for c in cams))
    margin = max(RANGE_MARGIN_M, RANGE_MARGIN_PLANES * (top - lo) / (n - 1))
    high = min(hi, float(np.percentile(z, RANGE_TOP_PERCENTILE)) + margin)
    ground = soil_height(z[srgb_to_lab(rgb, 1.0)[:, 1] >= cfg.soil_a_min], lo, hi)
    low = lo if ground is None else max(lo, ground - margin)
    return (low, high) if high > low else (lo, hi)


def soil_height(z: np.ndarray, lo: float, hi: float) -> float | None:
    """The lowest layer where the soil-coloured points ``z`` pile up: in ``SOIL_BIN_M`` bins
    between ``lo`` and ``hi`` (smoothed over three), the first bin holding ``SOIL_MIN_POINTS``
    and ``SOIL_PEAK_RATIO`` times the mean of the bins ``SOIL_BELOW_M`` under it (the wrong
    matches below the soil are spread thin, the soil is a layer), moved to the fullest bin
    within ``SOIL_LAYER_M`` above it; its centre, or None where no bin qualifies. A bin within
    ``SOIL_BELOW_M`` of ``lo`` has no full reference and never qualifies (a box that tight
    already starts at the soil). The lowest, not the fullest: leaf edges mixed with the soil
    behind them in the photos' pixels can outnumber the soil seen through a canopy, at the
    leaves' heights."""
    edges = np.arange(lo, hi + SOIL_BIN_M, SOIL_BIN_M)
    if len(z) < SOIL_MIN_POINTS or len(edges) < 4:
        return None
    h, _ = np.histogram(z, bins=edges)
    sm = np.convolve(h, np.ones(3), mode="same")
    below = int(round(SOIL_BELOW_M / SOIL_BIN_M))
    # each bin against the mean of the bins up to SOIL_BELOW_M under it (the adjacent one left
    # out: the smoothing spreads a layer into it)
    csum = np.r_[0.0, np.cumsum(sm)]
    idx = np.arange(len(sm))
    a, b = np.maximum(idx - below, 0), np.maximum(idx - 1, 0)
    ref = (csum[b] - csum[a]) / np.maximum(b - a, 1)
    # only a bin with the whole reference under it can stand out: the lowest bins have nothing
    # (or little) under them, and the thin spread of wrong matches down to the box's bottom
    # passed there as a layer wherever three bins held SOIL_MIN_POINTS
    full = idx >= below
    (strong,) = np.nonzero(full & (sm >= SOIL_MIN_POINTS) & (sm >= SOIL_PEAK_RATIO * ref))
    if not len(strong):
        return None
    k0 = int(strong[0])
    k = k0 + int(np.argmax(sm[k0 : k0 + int(round(SOIL_LAYER_M / SOIL_BIN_M)) + 1]))
    return float(0.5 * (edges[k] + edges[k + 1]))


def cut_box_limits(
    cams: list[PinholeCamera],
    box: np.ndarray,
    depth_range: tuple[float, float] | None,
    before: list[tuple[float, float]],
) -> list[tuple[float, float]]:
    """Each camera's :func:`depth_limits` in ``box`` cut to the canopy's heights, or its
    limits ``before`` (in the whole box) where it does not see the cut box: a photo at the
    edge of a low nadir capture sees the whole box's soil but not the canopy's slab, and it
    stopped the run (a phone held 1.7 m over the plot, 200 photos; session 97). Its depths then
    lie outside the slab, where the box filter drops them."""
    out = []
    for c, old in zip(cams, before, strict=True):
        try:
            out.append(depth_limits(c, box, depth_range))
        except InputError:
            out.append(old)
    return out


def stereo_depth_maps(
    imgs: list[np.ndarray],
    cams: list[PinholeCamera],
    box: np.ndarray | None,
    cfg: SurfacesConfig,
    say: Progress,
) -> StereoDepths:
    """Steps 1–3 of the module's pipeline on checked inputs (``check_inputs``): neighbours,
    plane-sweep stereo of every view, consistency and bounding-box filtering. With
    ``config.sweep_heights = 'auto'`` the box's heights are first cut to those
    ``occupied_heights`` finds."""
    scales = [stereo_scale(c, cfg) for c in cams]
    small = [c.scaled(s) for c, s in zip(cams, scales, strict=True)]
    nbrs = select_neighbours(cams, int(cfg.neighbours), box)
    limits = [depth_limits(c, box, cfg.depth_range) for c in cams]
    heights = None
    range_s = 0.0
    if cfg.sweep == "horizontal" and box is not None:
        heights = (float(box[0, 2]), float(box[1, 2]))
        if cfg.sweep_heights == "auto":
            t = time.perf_counter()
            heights = occupied_heights(imgs, cams, nbrs, limits, box, cfg, say)
            range_s = time.perf_counter() - t
            # the box down to those heights for everything after: the neighbours are chosen by
            # their triangulation angle at the middle of its height (the canopy's, not a point
            # in the soil), the filters and the fusion's depth limits follow it
            box = box.copy()
            box[:, 2] = heights
            nbrs = select_neighbours(cams, int(cfg.neighbours), box)
            limits = cut_box_limits(cams, box, cfg.depth_range, limits)
    photos = list(zip(imgs, cams, scales, strict=True))
    # RGB copies only where the match or the colour check reads them (memory: 500 drone photos)
    need_rgb = cfg.colour or cfg.consistency_a_tol is not None
    colours = [to_colour(*p) for p in photos] if need_rgb else []
    views = colours if cfg.colour else [to_grey(*p) for p in photos]
    t1 = time.perf_counter()
    raw, filtered, stereo_s = _match_views(
        views, small, nbrs, limits, heights, box, cfg, int(cfg.n_depths), say, "stereo",
        a_star_maps(colours, cfg),
    )  # fmt: skip
    say("consistency", 1.0)
    return StereoDepths(
        small, raw, filtered, limits, stereo_s, time.perf_counter() - t1 - stereo_s,
        heights, range_s,
    )  # fmt: skip


# --------------------------------------------------------------------------- the backend


def _o3d_intrinsic(cam: PinholeCamera) -> o3d.core.Tensor:
    """``cam.K`` for Open3D's integration, unchanged: it reads a voxel's depth from pixel
    ``int(u)`` (truncation), i.e. pixel i spans [i, i + 1), as :class:`PinholeCamera`'s pixels
    do. Shifting the centres by half a pixel put a fused plane 1.1 mm below the truth at
    480 x 360 (4.8 mm at 160 x 120)."""
    return o3d.core.Tensor(np.ascontiguousarray(cam.K), o3d.core.float64)


def _touched_blocks(
    grid: o3d.t.geometry.VoxelBlockGrid, cam: PinholeCamera, depth: np.ndarray, trunc: float
) -> o3d.core.Tensor | None:
    """The grid blocks within ``trunc`` voxels of every finite depth of ``cam``'s map (None:
    none). From the unprojected points, not from the depth image, whose form samples only
    every fourth pixel: a quarter of a small map's depths fell in blocks never allocated, and a
    map whose few depths all lay off that grid stopped the fusion with Open3D's "No block is
    touched"."""
    pts = cam.unproject(depth)[np.isfinite(depth)]
    if not len(pts):
        return None
    cloud = o3d.t.geometry.PointCloud(o3d.core.Tensor(np.ascontiguousarray(pts, np.float32)))
    return grid.compute_unique_block_coordinates(cloud, trunc)


#: The fused surfaces' softening of the leaves near their edges, in voxels
#: (:attr:`TsdfSurfaces.edge_blur`): the fit blurs its predictions by it with
#: ``observe.prediction_blur=auto`` (not the default; benchmarks/RESULTS.md, *#blur*). The
#: fused leaves' depth derivatives are gentler than the real ones (a canopy's Sobel histogram
#: low and flat where its true mesh's peaks high; the occlusion steps themselves stay sharp),
#: and a canopy of many small leaves mimics that. At 0.8 voxel (6 mm at the default 7.5 mm voxel;
#: 4.9-10.8 px at the row camera over six canopies) the true parameters of one such canopy beat
#: its answer again under the reconstruction's observation; fitted, three of six canopies read
#: LAI closer to the truth and three further. Measured against the same draw (the true mesh
#: blurred, ``bench pipeline``'s blur match), five of those six observations, that canopy's
#: included, are closest to their truth unblurred; only the 1.1 m canopy's (which lost its deep
#: leaves) is closer at 6 mm: the scale is no general softening (RESULTS, *#blur-match*).
EDGE_BLUR_VOXELS = 0.8


class TsdfSurfaces(SurfaceBackend):
    """CPU default: multi-view stereo fused into a TSDF; renders by ray casting its mesh."""

    name = "tsdf"

    @property
    def edge_blur(self) -> float:
        """:data:`EDGE_BLUR_VOXELS` voxels: marching cubes over averaged signed distances
        bends a leaf's surface near its edge across about a voxel."""
        return EDGE_BLUR_VOXELS * float(self.config.voxel_size)

    def __init__(self, config: SurfacesConfig | None = None) -> None:
        super().__init__(config or SurfacesConfig(backend="tsdf"))
        self.vertices = np.zeros((0, 3))
        self.faces = np.zeros((0, 3), np.int32)
        self.vertex_colors = np.zeros((0, 3))
        self.fill_vertices = np.zeros((0, 3))
        self.fill_faces = np.zeros((0, 3), np.int32)
        """faces of the surface fused from one depth map that the two-view mesh lacks, rendered
        where it leaves a ray empty (``config.fill_one_view``)"""
        self.fill_colors = np.zeros((0, 3))
        self.depth_maps: list[np.ndarray] = []
        """after ``fit``: per view the (h, w) float32 z-depth map fused (at ``mvs_scale``)"""
        self.raw_depth_maps: list[np.ndarray] = []
        """after ``fit``: per view the (h, w) float32 stereo depth before consistency filtering"""
        self._scene = None
        self._fill_scene = None

    # ------------------------------------------------------------------ fit
    def fit(self, images, cameras, bbox=None, progress: Progress | None = None) -> None:
        imgs, cams, box = check_inputs(images, cameras, bbox)
        say = progress or (lambda stage, frac: None)
        st = stereo_depth_maps(imgs, cams, box, self.config, say)
        t = time.perf_counter()
        self.bbox = box
        self._fuse(imgs, st.cameras, st.filtered, st.limits)
        say("fusion", 1.0)
        if len(self.faces) == 0:  # before the cameras: a failed fit is not a fitted backend
            raise SurfacesError(
                "multi-view stereo found no consistent surface: check the poses, the bounding box "
                "and the image overlap (or lower surfaces min_consistent / min_ncc)"
            )
        self.cameras = cams
        self.depth_maps = st.filtered
        self.raw_depth_maps = st.raw
        self.timings = {**st.timings(), "fusion": time.perf_counter() - t}
        stages = ("sweep_range", "stereo", "consistency", "fusion")
        self.timings["total"] = sum(self.timings.get(k, 0.0) for k in stages)

    def _fuse(self, imgs, small, depths, limits) -> None:
        cfg = self.config
        vs = float(cfg.voxel_size)
        trunc = float(cfg.trunc_voxels)
        block_res = 8
        frames = []
        probe = o3d.t.geometry.VoxelBlockGrid(
            ("tsdf", "weight", "color"),
            (o3d.core.float32, o3d.core.float32, o3d.core.float32),
            ((1), (1), (3)), vs, block_res, 16,
        )  # fmt: skip
        coords = []
        for im, cam, d, (_, far) in zip(imgs, small, depths, limits, strict=True):
            # integration reads depths in (0, far]: the blocks are those of the same depths
            d = np.where(np.isfinite(d) & (d > 0) & (d <= far), d, np.nan).astype(np.float32)
            bc = _touched_blocks(probe, cam, d, trunc)
            if bc is None:
                continue
            depth_img = o3d.t.geometry.Image(np.ascontiguousarray(np.nan_to_num(d, nan=0.0)))
            rgb = np.ascontiguousarray(_resize_rgb(im, cam).astype(np.float32) / 255.0)
            intr = _o3d_intrinsic(cam)
            extr = o3d.core.Tensor(cam.world_to_cam, o3d.core.float64)
            coords.append(bc.numpy())
            frames.append((depth_img, o3d.t.geometry.Image(rgb), intr, extr, far, bc))
        if not frames:
            raise SurfacesError(
                "no view has a usable depth map: nothing to fuse (the depths searched: "
                "surfaces.depth_range, else the scene box's in each view, else 0.2-8 m without "
                "a box)"
            )
        blocks = np.unique(np.concatenate(coords), axis=0)
        vbg = o3d.t.geometry.VoxelBlockGrid(
            ("tsdf", "weight", "color"),
            (o3d.core.float32, o3d.core.float32, o3d.core.float32),
            ((1), (1), (3)), vs, block_res, int(len(blocks) * 1.2) + 64,
        )  # fmt: skip
        # carving: each view also fuses the free space it sees into the others' blocks
        every = (
            o3d.core.Tensor(np.ascontiguousarray(blocks, dtype=np.int32))
            if cfg.carve_free_space
            else None
        )
        for depth_img, color_img, intr, extr, far, bc in frames:
            vbg.integrate(
                bc if every is None else every, depth_img, color_img, intr, extr, 1.0, far, trunc
            )
        v, f, c = _o3d_mesh(vbg.extract_triangle_mesh(weight_threshold=float(cfg.weight_threshold)))
        fill = None
        if cfg.fill_one_view:
            # weight > 0: every voxel of the cell fused from at least one depth map
            vl, fl, cl = _o3d_mesh(vbg.extract_triangle_mesh(weight_threshold=0.0))
            fill = (vl, fl[~faces_shared(vl, fl, v, f)], cl)
        self._set_mesh(v, f, c, fill)

    def _set_mesh(self, v, f, c, fill=None) -> None:
        """Store the surface and its fill (``(v, f, c)`` or None: none) exactly as ``save`` writes
        them (float32 positions, 8-bit colours), so that a saved and reloaded surface renders
        identically; faces leaving the bounding box (grown by two voxels) are dropped."""
        pad = 2 * float(self.config.voxel_size)
        self.vertices, self.faces, self.vertex_colors = _stored(v, f, c, self.bbox, pad)
        self.fill_vertices, self.fill_faces, self.fill_colors = _stored(
            *(fill or _empty_mesh()), self.bbox, pad
        )
        self._scene = None
        self._fill_scene = None

    # ------------------------------------------------------------------ queries
    def _raycaster(self, fill: bool = False):
        if fill:
            if self._fill_scene is None:
                self._fill_scene = build_scene(self.fill_vertices, self.fill_faces)
            return self._fill_scene
        if self._scene is None:
            self._scene = build_scene(self.vertices, self.faces)
        return self._scene

    def render(self, camera: PinholeCamera) -> tuple[np.ndarray, np.ndarray]:
        return self._cast(camera, with_fill=True)

    def render_supported(self, camera: PinholeCamera) -> np.ndarray:
        """z-depth of the two-view mesh alone (without the one-view fill)."""
        return self._cast(camera, with_fill=False)[0]

    def _cast(self, camera: PinholeCamera, with_fill: bool) -> tuple[np.ndarray, np.ndarray]:
        self._require_fitted()
        if not isinstance(camera, PinholeCamera):
            raise InputError(f"camera must be a PinholeCamera, got {type(camera).__name__}")
        h, w = camera.height, camera.width
        d = camera.ray_directions(normalized=False).reshape(-1, 3)
        rays = np.empty((len(d), 6), np.float32)
        rays[:, :3] = camera.center
        rays[:, 3:] = d
        depth = np.full(len(d), np.nan, np.float32)
        rgb = np.zeros((len(d), 3))
        todo = np.arange(len(d))
        passes = [(False, self.faces, self.vertex_colors)]
        if with_fill:
            passes.append((True, self.fill_faces, self.fill_colors))
        for fill, faces, col in passes:
            if not len(todo) or not len(faces):
                continue
            ans = self._raycaster(fill).cast_rays(o3d.core.Tensor(rays[todo]))
            t = ans["t_hit"].numpy()
            prim = ans["primitive_ids"].numpy().astype(np.int64)
            hit = np.isfinite(t) & (prim != o3d.t.geometry.RaycastingScene.INVALID_ID)
            idx = todo[hit]
            depth[idx] = t[hit]
            uv = ans["primitive_uvs"].numpy()[hit].astype(np.float64)
            tri = faces[prim[hit]]
            rgb[idx] = (
                (1 - uv[:, :1] - uv[:, 1:]) * col[tri[:, 0]]
                + uv[:, :1] * col[tri[:, 1]]
                + uv[:, 1:] * col[tri[:, 2]]
            )
            todo = todo[~hit]
        rgb8 = np.clip(np.rint(rgb * 255.0), 0, 255).astype(np.uint8).reshape(h, w, 3)
        return depth.reshape(h, w), rgb8

    def point_cloud(self, n_max: int = 100_000) -> tuple[np.ndarray, np.ndarray]:
        """Vertices of the fused (two-view) mesh inside the bounding box (about one per voxel of
        surface), with their fused colours; the fill is left out."""
        self._require_fitted()
        keep = in_bbox(self.vertices, self.bbox)
        return subsample(self.vertices[keep], self.vertex_colors[keep], n_max, self.config.seed)

    def mesh(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(vertices (n, 3) float64 m, faces (m, 3) int32, vertex colours (n, 3) float in
        [0, 1]) of the fused (two-view) surface; ``fill_vertices/faces/colors`` hold its fill."""
        self._require_fitted()
        return self.vertices, self.faces, self.vertex_colors

    # ------------------------------------------------------------------ persistence
    def _save_payload(self, folder: Path) -> dict:
        write_colored_ply(folder / MESH_FILE, self.vertices, self.faces, self.vertex_colors)
        out = {"mesh": MESH_FILE, "vertices": len(self.vertices), "faces": len(self.faces)}
        if len(self.fill_faces):
            write_colored_ply(
                folder / FILL_FILE, self.fill_vertices, self.fill_faces, self.fill_colors
            )
            out.update(fill_mesh=FILL_FILE, fill_faces=len(self.fill_faces))
        return out

    def _load_payload(self, folder: Path, meta: dict) -> None:
        self.depth_maps = []
        v, f, c = read_colored_ply(folder / meta.get("mesh", MESH_FILE))
        fill = read_colored_ply(folder / meta["fill_mesh"]) if meta.get("fill_mesh") else None
        self._set_mesh(v, f, c, fill)


def _empty_mesh() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(vertices (0, 3), faces (0, 3) int32, colours (0, 3)): no surface."""
    return np.zeros((0, 3)), np.zeros((0, 3), np.int32), np.zeros((0, 3))


def _o3d_mesh(mesh) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(vertices float64, faces (m, 3) int32, colours float64) of an Open3D tensor mesh."""
    v = mesh.vertex.positions.numpy().astype(np.float64)
    if not len(v):
        return _empty_mesh()
    f = mesh.triangle.indices.numpy().astype(np.int32).reshape(-1, 3)
    return v, f, mesh.vertex.colors.numpy().astype(np.float64)


def _stored(v, f, c, bbox, pad: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A mesh as it is saved: faces inside ``bbox`` grown by ``pad`` (all of them without a box),
    unused vertices dropped, float32 positions, colours rounded to 8 bits."""
    v = np.asarray(v, np.float64).reshape(-1, 3)
    f = np.asarray(f, np.int32).reshape(-1, 3)
    if bbox is not None and len(f):
        inside = np.all((v >= bbox[0] - pad) & (v <= bbox[1] + pad), axis=1)
        f = f[inside[f].all(axis=1)]
    if not len(f):
        return _empty_mesh()
    used, inv = np.unique(f, return_inverse=True)
    v, c = v[used], np.asarray(c, np.float64)[used]
    return (
        np.asarray(v, np.float32).astype(np.float64),
        inv.reshape(-1, 3).astype(np.int32),
        np.rint(np.clip(c, 0.0, 1.0) * 255.0) / 255.0,
    )


def faces_shared(v: np.ndarray, f: np.ndarray, v_other: np.ndarray, f_other: np.ndarray):
    """(m,) bool: which faces of mesh (v, f) are also faces of (v_other, f_other), matched by
    their vertices' exact float32 positions (orientation and vertex order ignored). Two marching
    cubes extractions of one TSDF place a shared cell's triangles at identical positions."""
    if not len(f) or not len(f_other):
        return np.zeros(len(f), bool)
    pos = np.ascontiguousarray(np.concatenate([v, v_other]).astype(np.float32))
    _, ids = np.unique(pos.view(np.dtype((np.void, 12))).ravel(), return_inverse=True)
    ids = ids.ravel()
    a = np.sort(ids[: len(v)][f], axis=1)
    b = np.sort(ids[len(v) :][f_other], axis=1)
    _, inv = np.unique(np.concatenate([a, b]), axis=0, return_inverse=True)
    inv = inv.ravel()
    return np.isin(inv[: len(a)], inv[len(a) :])


# --------------------------------------------------------------------------- PLY with colours


def write_colored_ply(path: Path, v: np.ndarray, f: np.ndarray, c: np.ndarray) -> Path:
    """Binary little-endian PLY: vertices (n, 3) as float32 x y z + uint8 r g b from colours
    (n, 3) in [0, 1]; faces (m, 3) as int32 lists. Written atomically."""
    header = (
        "ply\nformat binary_little_endian 1.0\ncomment cropcraft visible surfaces, metres, z up\n"
        f"element vertex {len(v)}\nproperty float x\nproperty float y\nproperty float z\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\n"
        f"element face {len(f)}\nproperty list uchar int vertex_indices\nend_header\n"
    ).encode("ascii")
    vd = np.empty(len(v), [("p", "<f4", (3,)), ("c", "u1", (3,))])
    vd["p"] = v
    vd["c"] = np.clip(np.rint(np.asarray(c) * 255.0), 0, 255)
    fd = np.empty(len(f), [("n", "u1"), ("i", "<i4", (3,))])
    fd["n"] = 3
    fd["i"] = f
    return write_atomic(path, header + vd.tobytes() + fd.tobytes())


def write_atomic(path: Path, data: bytes) -> Path:
    """Write ``data`` to ``path`` through a temporary file beside it, so that a reader never
    sees half a file."""
    tmp = path.with_name(path.name + ".tmp")
    try:
        tmp.write_bytes(data)
        tmp.replace(path)
    except OSError as e:
        raise SurfacesError(f"cannot write {path}: {e}") from None
    return path


def read_colored_ply(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Read what ``write_colored_ply`` wrote: (vertices (n, 3) float64, faces (m, 3) int32,
    colours (n, 3) float64 in [0, 1])."""
    head, body = read_ply(path)
    nv, nf = ply_count(path, head, "vertex"), ply_count(path, head, "face")
    vdt = np.dtype([("p", "<f4", (3,)), ("c", "u1", (3,))])
    fdt = np.dtype([("n", "u1"), ("i", "<i4", (3,))])
    if len(body) != nv * vdt.itemsize + nf * fdt.itemsize:
        raise InputError(f"{path}: size does not match its header (truncated?)")
    vd = np.frombuffer(body, vdt, nv)
    fd = np.frombuffer(body, fdt, nf, offset=nv * vdt.itemsize)
    faces = fd["i"].astype(np.int32)
    if faces.size and (faces.min() < 0 or faces.max() >= nv):
        raise InputError(f"{path}: faces index vertices outside 0..{nv - 1} (damaged?)")
    return vd["p"].astype(np.float64), faces, vd["c"].astype(np.float64) / 255.0


def read_ply(path: Path) -> tuple[list[str], bytes]:
    """(header lines, body bytes) of a binary PLY file; ``InputError`` naming the file when it
    cannot be read or is no PLY."""
    try:
        data = Path(path).read_bytes()
    except OSError as e:
        raise InputError(f"cannot read {path}: {e}") from None
    end = data.find(b"end_header\n")
    if not data.startswith(b"ply") or end < 0:
        raise InputError(f"{path} is not a PLY file")
    return data[:end].decode("ascii", "replace").splitlines(), data[end + len(b"end_header\n") :]


def ply_count(path: Path, head: list[str], element: str) -> int:
    """The count of ``element`` in a PLY header (``InputError`` naming the file if absent)."""
    try:
        return int(next(x for x in head if x.startswith(f"element {element} ")).split()[2])
    except (StopIteration, ValueError, IndexError):
        raise InputError(f"{path}: malformed PLY header (no {element} count)") from None
