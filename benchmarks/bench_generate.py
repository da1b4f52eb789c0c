"""Forward-model speed: generate a canopy and cast one 994 × 738 depth map of it.

    .venv/bin/python -m benchmarks.bench_generate [--json FILE] [--repeats N]

Cases (issue targets on the 2-core machine: generation ≤ 25 ms median, depth ≤ 60 ms):
- soybean, 2 m × 2 m plot, largest parameters;
- maize, 4 m × 4 m plot, largest parameters.
The depth map is rendered by our numba rasteriser and, in the same run, by the reference tool
(Open3D's RaycastingScene, scene build timed separately), with the fraction of pixels on which
the two agree.
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

from benchmarks.options import at_least, output_file, write_json
from cropcraft_core.config import default_layout, param_space
from cropcraft_core.geometry import PinholeCamera
from cropcraft_core.procedural import generate_canopy, plot_region

TARGET_GENERATE_MS = 25.0
TARGET_DEPTH_MS = 60.0


def _median_ms(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return 1e3 * statistics.median(times)


def run(repeats: int = 15) -> list[dict]:
    from cropcraft_core.render.raster import render_depth
    from cropcraft_core.render.raycast import build_scene, raycast_depth

    cases = [("soybean", 2.0, 1.0), ("maize", 4.0, 5.0)]
    rows = []
    for crop, size, cam_h in cases:
        params = {s.name: s.high for s in param_space(crop)}
        lay = default_layout(crop, plot_length=size, plot_width=size)
        region = plot_region(lay, 0.0)

        def gen(crop=crop, params=params, lay=lay, region=region):
            return generate_canopy(crop, params, lay, seed=0, region=region)

        canopy = gen()
        mesh = canopy.mesh
        cam = PinholeCamera.look_down(height_m=cam_h)
        render_depth(mesh.vertices, mesh.faces, cam)  # JIT warm-up (cached on disk)
        gen_ms = _median_ms(gen, repeats)
        ours_ms = _median_ms(lambda m=mesh, c=cam: render_depth(m.vertices, m.faces, c), repeats)
        t = time.perf_counter()
        build_scene(mesh.vertices, mesh.faces)
        build_ms = 1e3 * (time.perf_counter() - t)
        ref_ms = _median_ms(lambda m=mesh, c=cam: raycast_depth(m, c), max(3, repeats // 3))
        a = render_depth(mesh.vertices, mesh.faces, cam)
        b = raycast_depth(mesh, cam)
        ha, hb = np.isfinite(a.depth), np.isfinite(b.depth)
        both = ha & hb
        agree = float(np.mean(ha == hb))
        rel = float(np.median(np.abs(a.depth[both] - b.depth[both]) / b.depth[both]))
        rows.append(
            {
                "case": f"{crop} {size:g}x{size:g} m, max params",
                "faces": int(mesh.n_faces),
                "generate_ms": gen_ms,
                "depth_ms_ours": ours_ms,
                "depth_ms_open3d": ref_ms,
                "open3d_scene_build_ms": build_ms,
                "hit_agreement": agree,
                "median_rel_depth_diff": rel,
                "generate_target_ms": TARGET_GENERATE_MS,
                "depth_target_ms": TARGET_DEPTH_MS,
            }
        )
    return rows


def print_table(rows: list[dict]) -> None:
    head = (
        f"{'case':<32}{'faces':>9}{'generate ms':>13}{'depth ms':>10}{'Open3D ms':>11}"
        f"{'(+build)':>10}{'agree':>8}  verdict"
    )
    print(head)
    print("-" * len(head))
    for r in rows:
        ok = r["generate_ms"] <= TARGET_GENERATE_MS and r["depth_ms_ours"] <= TARGET_DEPTH_MS
        print(
            f"{r['case']:<32}{r['faces']:>9}{r['generate_ms']:>13.1f}{r['depth_ms_ours']:>10.1f}"
            f"{r['depth_ms_open3d']:>11.1f}{r['open3d_scene_build_ms']:>10.1f}"
            f"{r['hit_agreement']:>8.4f}  {'meets' if ok else 'MISSES'} "
            f"≤{TARGET_GENERATE_MS:g}/≤{TARGET_DEPTH_MS:g} ms"
        )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="cropcraft bench generate", description=__doc__.splitlines()[0]
    )
    ap.add_argument("--json", type=output_file)
    ap.add_argument("--repeats", type=at_least(1), default=15)
    a = ap.parse_args(argv)
    rows = run(a.repeats)
    print_table(rows)
    if a.json:
        write_json(a.json, rows)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
