"""Depth-render benchmark: numba rasterizer vs Open3D ``RaycastingScene``.

Run with ``.venv/bin/python -m benchmarks.bench_render [--triangles N] [--runs R]``.

The scene is a canopy-like soup of small leaf-sized triangles (edges of ~1–2 cm, mostly facing
up) scattered over a 2 m × 2 m plot at heights 0–0.8 m, seen by the paper's row camera
(994 × 738, vfov 50°) straight down from 1 m. Times are medians over the runs; the Open3D scene
build is timed separately from the ray casting.
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

from benchmarks.options import at_least
from cropcraft_core.geometry.camera import PinholeCamera
from cropcraft_core.render.raster import render_depth
from cropcraft_core.render.raycast import build_scene, cast_rays


def canopy_soup(
    n_triangles: int = 150_000,
    extent_m: float = 2.0,
    max_height_m: float = 0.8,
    edge_m: float = 0.015,
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """A random canopy-like triangle soup.

    Returns (vertices (3 n_triangles, 3) float64, faces (n_triangles, 3) int32): independent
    triangles of about ``edge_m`` size, centres uniform over an ``extent_m`` square centred on the
    origin and heights in [0, max_height_m], normals tilted from vertical by up to ~60°.
    """
    rng = np.random.default_rng(seed)
    centre = np.column_stack(
        [
            rng.uniform(-extent_m / 2, extent_m / 2, n_triangles),
            rng.uniform(-extent_m / 2, extent_m / 2, n_triangles),
            rng.uniform(0.0, max_height_m, n_triangles),
        ]
    )
    # A random in-plane frame per triangle: normal tilted from +z, then two tangents.
    tilt = rng.uniform(0, np.radians(60), n_triangles)
    az = rng.uniform(0, 2 * np.pi, n_triangles)
    normal = np.column_stack([np.sin(tilt) * np.cos(az), np.sin(tilt) * np.sin(az), np.cos(tilt)])
    helper = np.where(np.abs(normal[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]])
    t1 = np.cross(normal, helper)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(normal, t1)
    # Three corners at random angles on a circle of radius ~edge/√3 (roughly equilateral-ish).
    ang = (
        rng.uniform(0, 2 * np.pi, (n_triangles, 1))
        + np.array([0, 2.1, 4.2])
        + rng.normal(0, 0.3, (n_triangles, 3))
    )
    rad = edge_m / np.sqrt(3) * rng.uniform(0.6, 1.4, (n_triangles, 3))
    corners = centre[:, None, :] + rad[..., None] * (
        np.cos(ang)[..., None] * t1[:, None, :] + np.sin(ang)[..., None] * t2[:, None, :]
    )
    vertices = corners.reshape(-1, 3)
    faces = np.arange(3 * n_triangles, dtype=np.int32).reshape(-1, 3)
    return vertices, faces


def _median_time(fn, runs: int) -> tuple[float, object]:
    times, out = [], None
    for _ in range(runs):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), out


#: README's target: a 994×738 depth map of a 150k-face canopy in at most 60 ms.
TARGET_MS = 60.0
TARGET_FACES = 150_000


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="cropcraft bench render", description=__doc__.splitlines()[0])
    ap.add_argument("--triangles", type=at_least(1), default=150_000)
    ap.add_argument("--runs", type=at_least(1), default=10)
    ap.add_argument("--seed", type=at_least(0), default=0)
    args = ap.parse_args(argv)

    vertices, faces = canopy_soup(args.triangles, seed=args.seed)
    camera = PinholeCamera.look_down(height_m=1.0)
    print(f"{len(faces)} triangles, {camera.width}x{camera.height} px, camera 1 m above the ground")

    t0 = time.perf_counter()
    render_depth(vertices, faces, camera)  # JIT compile or load from the numba cache
    first = time.perf_counter() - t0
    t_raster, res = _median_time(lambda: render_depth(vertices, faces, camera), args.runs)

    origin = camera.center

    def build():  # Embree builds its BVH lazily on the first query: include it
        scene = build_scene(vertices - origin, faces)
        cast_rays(scene, np.zeros(3), [0.0, 0.0, 1.0])
        return scene

    t_build, scene = _median_time(build, args.runs)
    dirs = camera.ray_directions(normalized=False).reshape(-1, 3)
    t_cast, (t_hit, prim) = _median_time(lambda: cast_rays(scene, np.zeros(3), dirs), args.runs)

    ref_depth = t_hit.reshape(camera.height, camera.width)
    ref_hit = np.isfinite(ref_depth)
    hit = res.mask
    same_status = np.mean(hit == ref_hit)
    both = hit & ref_hit
    rel = np.abs(res.depth[both] - ref_depth[both]) / ref_depth[both]
    depth_ok = np.mean(rel <= 1e-4) if both.any() else 1.0
    same_face = (
        np.mean(res.face_id[both] == prim.reshape(ref_depth.shape)[both]) if both.any() else 1.0
    )
    max_rel = f"{rel.max():.2e}" if rel.size else "no pixel hit by both"

    rows = [
        ("numba rasterizer (render_depth)", t_raster),
        ("open3d scene build (incl. BVH)", t_build),
        ("open3d cast_rays", t_cast),
        ("open3d build + cast", t_build + t_cast),
    ]
    print(f"\nmedian of {args.runs} runs (first numba call incl. JIT/cache load: {first:.2f} s)")
    print(f"{'renderer':<34}{'ms':>10}")
    for name, t in rows:
        print(f"{name:<34}{t * 1e3:>10.1f}")
    print(f"\ncoverage: raster {hit.mean():.4f}, open3d {ref_hit.mean():.4f}")
    print(f"same hit/miss status:               {same_status:.5f}")
    print(f"depth rel. err <= 1e-4 (both hit):  {depth_ok:.5f} (max {max_rel})")
    print(f"same face id (both hit):            {same_face:.5f}")
    if len(faces) >= TARGET_FACES:  # README's target is for a canopy of 150k faces
        met = t_raster * 1e3 <= TARGET_MS
        print(
            f"\nnumba rasteriser {t_raster * 1e3:.1f} ms for {len(faces):,} faces (target <= "
            f"{TARGET_MS:g} ms at {TARGET_FACES:,}): {'met' if met else 'NOT met'}"
        )


if __name__ == "__main__":
    main()
