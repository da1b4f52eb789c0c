"""`cropcraft fit --geometry`: fit a metric z-up mesh or point cloud, end to end through the CLI."""

import json
import os

import numpy as np
import pytest

from cropcraft_core.config import default_layout
from cropcraft_core.errors import InputError
from cropcraft_core.export import read_ply, write_ply
from cropcraft_core.fit.geometry import (
    LEAF_RGB,
    SOIL_RGB,
    load_geometry,
    observe_geometry,
    sample_mesh,
    splat_depth,
    splat_radius,
)
from cropcraft_core.geometry import PinholeCamera
from cropcraft_core.metrics import canopy_metrics
from cropcraft_core.procedural import generate_canopy, plot_region
from cropcraft_core.render import render_depth
from cropcraft_core.surfaces.tsdf import write_colored_ply
from flows.cli import main


@pytest.fixture(scope="module")
def canopy_ply(tmp_path_factory):
    lay = default_layout("soybean", plot_length=2.0, plot_width=2.4)
    c = generate_canopy(
        "soybean", {"num_nodes": 7, "leaf_length": 1.1}, lay, seed=3, region=plot_region(lay, 0.3)
    )
    path = tmp_path_factory.mktemp("geo") / "canopy.ply"
    write_ply(path, c.mesh)
    return path


def test_young_bare_canopy_gets_a_ground(tmp_path):
    lay = default_layout("soybean", plot_length=1.0, plot_width=1.6)
    c = generate_canopy("soybean", {"num_nodes": 2}, lay, seed=1, region=plot_region(lay, 0))
    write_ply(tmp_path / "young.ply", c.mesh)
    geo = load_geometry(tmp_path / "young.ply", n_points=20_000)
    assert "ground" in geo.meta and geo.meta["colours"] == "by height"
    # a grid of 30 % as many points at the mesh's lowest points' z, spanning its footprint
    z0 = np.percentile(geo.points[:20_000, 2], 0.1)
    grid = geo.points[20_000:]
    assert len(grid) == 6_000 and np.all(grid[:, 2] == z0)
    footprint = np.ptp(c.mesh.vertices[:, :2], axis=0)
    assert np.all(np.ptp(grid[:, :2], axis=0) > 0.9 * footprint)
    # coloured by height: soil within 3 cm of the ground, leaf above
    low = geo.points[:, 2] < z0 + 0.03
    assert np.all(geo.colors[low] == SOIL_RGB) and np.all(geo.colors[~low] == LEAF_RGB)
    assert (~low).sum() > 10_000  # the canopy itself stands above the band


def _write_points(path, points):
    """An ASCII PLY point cloud of float x y z (NaN kept as written)."""
    head = (
        f"ply\nformat ascii 1.0\nelement vertex {len(points)}\n"
        "property float x\nproperty float y\nproperty float z\nend_header\n"
    )
    path.write_text(head + "".join(f"{x:.6f} {y:.6f} {z:.6f}\n" for x, y, z in points))
    return path


def test_coloured_point_cloud_keeps_its_colours_and_fits_the_rows(canopy_ply, tmp_path):
    """A scan (coloured points, no faces): its own colours split ground from plant, its depth
    is splatted, and the rows and camera come out as for the mesh."""
    import open3d as o3d

    canopy = read_ply(canopy_ply)
    rng = np.random.default_rng(0)
    plant = sample_mesh(canopy, 400_000, rng)
    plant = plant[plant[:, 2] > 0.03]  # above the soil band: the scan's ground is its own
    lo, hi = plant[:, :2].min(0), plant[:, :2].max(0)
    soil = np.column_stack([rng.uniform(lo, hi, (20_000, 2)), np.zeros(20_000)])
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.concatenate([plant, soil])))
    pc.colors = o3d.utility.Vector3dVector(
        np.concatenate([np.tile(LEAF_RGB, (len(plant), 1)), np.tile(SOIL_RGB, (20_000, 1))])
    )
    path = tmp_path / "scan.ply"
    assert o3d.io.write_point_cloud(str(path), pc)
    geo = load_geometry(path)
    assert geo.meta["kind"] == "points" and "colours" not in geo.meta and geo.mesh is None
    assert len(geo.points) == len(plant) + 20_000  # no ground grid added: the scan has one
    obs, rowfit = observe_geometry(path, "soybean", row_spacing=0.76)
    assert obs.meta["kind"] == "points"
    assert abs(rowfit.best_row.azimuth_deg) < 3.0
    y = rowfit.camera.center[1]
    assert min(abs(y - k * 0.76) for k in (-1, 0, 1)) < 0.06
    # the splatted depth lies on the mesh's depth from the same camera where both see a surface
    m = rowfit.world_from_scene
    ref = render_depth(canopy.vertices @ m[:3, :3].T + m[:3, 3], canopy.faces, obs.camera).depth
    both = obs.mask & np.isfinite(ref)
    err = np.abs(obs.depth[both] - ref[both])
    # (sparse points let farther ones show between the nearest: not every pixel is exact)
    assert obs.stats.mask_area > 0.3 and np.median(err) < 0.002 and (err < 0.01).mean() > 0.6
    # compare.png shows the observation's canopy as the report does: its soil was coloured as
    # far canopy beside a prediction without soil (session 93's report audit)
    from PIL import Image

    from cropcraft_core.fit import FitConfig
    from cropcraft_core.fit.geometry import fit_geometry
    from cropcraft_core.render.preview import depth_to_rgb

    cfg = FitConfig(n_seeds=1, n_evals=8, n_initial=6, combine="mean")
    fit_geometry(path, "soybean", tmp_path / "out", config=cfg)
    soil = ~obs.mask & np.isfinite(obs.depth)
    assert soil.mean() > 0.05
    left = np.asarray(Image.open(tmp_path / "out" / "compare.png").convert("RGB"))
    left = left[:, : obs.depth.shape[1]]
    none = depth_to_rgb(np.array([[np.nan]]), 0.0, 1.0)[0, 0]
    rows, cols = np.nonzero(soil)
    keep = rows > 50  # below the panel's labels
    assert np.all(left[rows[keep], cols[keep]] == none)


def test_bad_geometry_is_named(tmp_path):
    pts = np.random.default_rng(0).uniform(0, 1, (500, 3))
    with pytest.raises(InputError, match="few.ply: only 50 points; a point cloud needs at least"):
        load_geometry(_write_points(tmp_path / "few.ply", pts[:50]))
    # a cloud's non-finite points (an organised scan's empty returns) are dropped, counted
    nan = pts.copy()
    nan[7, 2] = np.nan
    geo = load_geometry(_write_points(tmp_path / "nan.ply", nan))
    assert geo.meta["dropped_non_finite"] == 1 and np.isfinite(geo.points).all()
    # a face element of no faces (MeshLab's point clouds, the surfaces stage's own writer):
    # its vertices are a point cloud, in their own colours
    empty = write_colored_ply(tmp_path / "empty.ply", pts, np.zeros((0, 3), np.int32), pts)
    geo = load_geometry(empty)
    assert geo.meta["kind"] == "points" and "colours" not in geo.meta


def test_a_point_cloud_in_grey_is_coloured_by_height_and_its_ground_is_robust(tmp_path):
    """Grey or black colours (a scanner's intensity, zeros for none) are no colours; an
    uncoloured cloud's ground grid lies at its lowest points, not at one stray return."""
    rng = np.random.default_rng(1)
    pts = np.column_stack([rng.uniform(0, 1, (5000, 2)), rng.uniform(0.0, 0.5, 5000)])
    pts[0, 2] = -0.4  # one return under the soil
    head = (
        f"ply\nformat ascii 1.0\nelement vertex {len(pts)}\nproperty double x\n"
        "property double y\nproperty double z\nproperty uchar red\nproperty uchar green\n"
        "property uchar blue\nend_header\n"
    )
    body = "".join(f"{x} {y} {z} 128 128 128\n" for x, y, z in pts)
    (tmp_path / "grey.ply").write_text(head + body)
    geo = load_geometry(tmp_path / "grey.ply")
    assert geo.meta["colours"] == "by height" and "grey" in geo.meta["colours_ignored"]
    ground = geo.points[len(pts) :, 2]
    assert np.all(ground == ground[0]) and -0.01 < ground[0] < 0.01


def test_georeferenced_coordinates_in_single_precision_are_refused(tmp_path):
    """float32 resolves 0.25 m at 4,000 km: such a plot has lost its leaves (doubles are fine)."""
    pts = np.random.default_rng(2).uniform(0, 1, (500, 3)) + [500_000.0, 4_000_000.0, 0.0]
    head = (
        f"ply\nformat binary_little_endian 1.0\nelement vertex {len(pts)}\nproperty float x\n"
        "property float y\nproperty float z\nend_header\n"
    )
    (tmp_path / "utm.ply").write_bytes(head.encode() + pts.astype("<f4").tobytes())
    with pytest.raises(InputError, match="utm.ply: coordinates stored as 32-bit floats reach"):
        load_geometry(tmp_path / "utm.ply")
    big = head.replace("binary_little_endian", "binary_big_endian")  # '>f4' is not == float32
    (tmp_path / "utm_be.ply").write_bytes(big.encode() + pts.astype(">f4").tobytes())
    with pytest.raises(InputError, match="utm_be.ply: coordinates stored as 32-bit floats"):
        load_geometry(tmp_path / "utm_be.ply")
    # as text (ASCII PLY), the digits are all there: read in double precision
    assert len(load_geometry(_write_points(tmp_path / "utm.txt.ply", pts)).points) >= 500
    # one empty return stored as inf in a local-frame cloud is no survey (session 92's audit:
    # "reach inf ... a georeferenced survey?"); it is dropped as a NaN is
    local = (pts - [500_000.0, 4_000_000.0, 0.0]).astype("<f4")
    local[7, 0] = np.inf
    (tmp_path / "inf.ply").write_bytes(head.encode() + local.tobytes())
    geo = load_geometry(tmp_path / "inf.ply")
    assert geo.meta["dropped_non_finite"] == 1 and np.isfinite(geo.points).all()


def test_a_cloud_in_feet_is_named_by_its_row_spacing(canopy_ply):
    """The rows 3.28 times the layout's spacing apart: the fit says so (it fitted silently)."""
    from cropcraft_core.fit.geometry import Geometry, geometry_warnings

    geo = load_geometry(canopy_ply, n_points=100_000)
    feet = Geometry(None, geo.points * 3.28084, geo.colors, dict(geo.meta, kind="points"))
    obs, _ = observe_geometry(feet, "soybean")
    said = geometry_warnings(obs.meta)
    assert any("is the geometry in metres" in w for w in said), said
    obs, _ = observe_geometry(geo, "soybean")
    assert not any("metres" in w or "spacing" in w for w in geometry_warnings(obs.meta))
    assert obs.meta["row_spacing_measured_m"] == pytest.approx(0.76, rel=0.15)


def test_a_geometry_in_centimetres_or_millimetres_is_named_before_the_fit(canopy_ply):
    """A cloud in centimetres fitted for 93 s and then failed blaming --plot and --density; in
    millimetres it read "no rows found" (session 92's geometry audit)."""
    from cropcraft_core.fit.geometry import Geometry

    geo = load_geometry(canopy_ply, n_points=50_000)
    for factor, unit in ((100, "centimetres"), (1000, "millimetres")):
        scaled = Geometry(None, geo.points * factor, geo.colors, dict(geo.meta, kind="points"))
        with pytest.raises(InputError, match=f"(?i)is it in metres.*in {unit}[a-z ]* 0.5"):
            observe_geometry(scaled, "soybean")
    tall = Geometry(None, geo.points * 6, geo.colors, dict(geo.meta, kind="points"))  # 3.4 m
    with pytest.raises(InputError, match="a soybean canopy can \\(or is it maize\\?\\)"):
        observe_geometry(tall, "soybean")
    observe_geometry(tall, "maize")  # a maize canopy may stand that tall


def test_a_single_row_says_its_spacing_is_assumed(tmp_path):
    """One planted row fitted with no word (session 92's geometry audit: LAI +58 %): its
    spacing cannot be measured, and the fit's canopy puts the layout's rows beside it."""
    from cropcraft_core.fit.geometry import geometry_warnings

    argv = ["generate", "soybean", "--seed", "1", "--plot", "0.76,2", "--out", str(tmp_path)]
    assert main(argv) == 0
    obs, _ = observe_geometry(load_geometry(tmp_path / "canopy.ply"), "soybean")
    said = geometry_warnings(obs.meta)
    assert any("shows one row, so the row spacing could not be measured" in w for w in said)
    assert "row_spacing_measured_m" not in obs.meta


def test_an_uncoloured_geometry_on_a_slope_stands_on_its_tilted_ground(canopy_ply, tmp_path):
    """A mesh (or uncoloured scan) tilted 5 degrees, as on a slope or from a scanner not
    levelled, got a flat ground grid at its lowest point and colours by absolute height: most
    of its soil read as leaves (session 92's geometry audit: LAI 2.06 for 1.25, no word).
    Its heights are now taken above the plane of its lowest points, and it is seen as the
    level one is; a level geometry is read as before, to the bit."""
    import dataclasses

    mesh = read_ply(canopy_ply)
    t = np.radians(5.0)
    turn = np.array([[1, 0, 0], [0, np.cos(t), -np.sin(t)], [0, np.sin(t), np.cos(t)]])
    write_ply(tmp_path / "slope.ply", dataclasses.replace(mesh, vertices=mesh.vertices @ turn.T))
    level = load_geometry(canopy_ply, n_points=100_000)
    slope = load_geometry(tmp_path / "slope.ply", n_points=100_000)
    assert level.meta["ground"].startswith("ground grid added at the lowest points, z = ")
    assert "tilted 5.0 degrees" in slope.meta["ground"]
    soil = [float(np.all(g.colors == SOIL_RGB, axis=1)[:100_000].mean()) for g in (level, slope)]
    assert soil[1] == pytest.approx(soil[0], abs=0.01)  # the same stems' feet, not the slope
    masks = [observe_geometry(g, "soybean")[0].mask.mean() for g in (level, slope)]
    assert masks[1] == pytest.approx(masks[0], abs=0.03)  # the audit's: 0.75 for 0.65


def test_an_uncoloured_scan_upside_down_is_named(canopy_ply, tmp_path):
    """A scan with its soil (uncoloured) read z up is fitted quietly; the same scan z down (its
    flat soil on top) warns, as it would lay the ground on the canopy's tops. A bare canopy
    mesh has no such layer either way up."""
    from cropcraft_core.fit.geometry import geometry_warnings

    rng = np.random.default_rng(0)
    canopy = read_ply(canopy_ply)
    pts = sample_mesh(canopy, 60_000, rng)
    lo, hi = pts[:, :2].min(0), pts[:, :2].max(0)
    soil = np.column_stack(
        [rng.uniform(lo[0], hi[0], 30_000), rng.uniform(lo[1], hi[1], 30_000), np.zeros(30_000)]
    )
    scan = np.concatenate([pts, soil + rng.normal(0, 0.004, soil.shape)])
    up = load_geometry(_write_points(tmp_path / "up.ply", scan))
    down = load_geometry(_write_points(tmp_path / "down.ply", scan * [1, -1, -1]))
    assert "orientation_warning" not in up.meta
    assert "Is the geometry z down?" in down.meta["orientation_warning"]
    assert "Is the geometry z down?" in geometry_warnings(down.meta)[0]
    for flip in ([1, 1, 1], [1, -1, -1]):  # bare
        bare = load_geometry(_write_points(tmp_path / "bare.ply", pts * flip))
        assert "orientation_warning" not in bare.meta


def test_an_uncoloured_geometry_exported_y_up_is_named(canopy_ply, tmp_path):
    """An uncoloured cloud exported y up (its plot's width read as its height) fitted LAI 6.8
    for 1.26 with one word, that LAI was "likely underestimated" (session 92's geometry audit).
    It stands taller than the model's tallest soybean canopy, and says it may not be z up; the
    same cloud z up says nothing of it."""
    from cropcraft_core.fit.geometry import geometry_warnings

    pts = sample_mesh(read_ply(canopy_ply), 60_000, np.random.default_rng(0))
    up = _write_points(tmp_path / "up.ply", pts)
    y_up = _write_points(tmp_path / "y_up.ply", pts[:, [0, 2, 1]] * [1, 1, -1])
    obs, _ = observe_geometry(load_geometry(up), "soybean")
    assert "orientation_warning" not in obs.meta
    obs, _ = observe_geometry(load_geometry(y_up), "soybean")
    said = geometry_warnings(obs.meta)
    assert "taller than the 1.85 m of the model's tallest soybean canopy" in said[0]
    assert "is the geometry z up?" in said[0] and "(x, -z, y)" in said[0]
    # turned as it says, it is the z-up cloud again
    turned = (pts[:, [0, 2, 1]] * [1, 1, -1])[:, [0, 2, 1]] * [1, -1, 1]
    assert np.allclose(turned, pts)


def test_a_point_cloud_is_splatted_as_wide_as_its_points_lie_apart(canopy_ply):
    """The same canopy as a sparse and a dense cloud covers about as much of the row view as
    its mesh (a fixed 2 px splat: 6 % against 65 % for a 52k-point cloud)."""
    from cropcraft_core.fit.geometry import Geometry

    mesh_geo = load_geometry(canopy_ply, n_points=100_000)
    obs_mesh, rowfit = observe_geometry(mesh_geo, "soybean")
    canopy = read_ply(canopy_ply)
    rng = np.random.default_rng(3)
    covers = {}
    for n in (30_000, 400_000):
        pts = np.concatenate([sample_mesh(canopy, n, rng), mesh_geo.points[100_000:]])
        cloud = Geometry(None, pts, None, {"kind": "points"})
        cloud.colors = np.where((pts[:, 2] < 0.03)[:, None], SOIL_RGB, LEAF_RGB)
        obs, _ = observe_geometry(cloud, "soybean")
        covers[n] = float(obs.mask.mean())
        assert ("warning" in obs.meta["splat"]) == (n == 30_000)
    for cover in covers.values():
        assert abs(cover - float(obs_mesh.mask.mean())) < 0.12, (covers, obs_mesh.mask.mean())


def test_canopy_rows_and_camera(canopy_ply):
    obs, rowfit = observe_geometry(canopy_ply, "soybean", n_points=50_000, row_spacing=0.76)
    # rows run along x at y = k * 0.76: the camera looks along a row, over one of them
    assert abs(rowfit.best_row.azimuth_deg) < 3.0
    y = rowfit.camera.center[1]
    assert min(abs(y - k * 0.76) for k in (-1, 0, 1)) < 0.06
    assert obs.stats.mask_area > 0.2


def test_pooled_row_cameras_beyond_the_geometry_are_left_out(canopy_ply):
    """``preset_overrides`` with ``views_along``/``views_across`` pool the observation over row
    cameras; on this 2.4 m wide plot the best row is an outer one, so the row beyond it lies
    outside the geometry: its three views are left out (their ground over 18 % beyond the
    scan), and the pool is the mean of the six single-camera observations kept."""
    from cropcraft_core.fit.geometry import _observe
    from cropcraft_core.observe import mean_stats

    views = {"views_along": 3, "views_across": 1}
    obs, rowfit = observe_geometry(
        canopy_ply, "soybean", n_points=50_000, row_spacing=0.76, preset_overrides=views
    )
    left = obs.meta["views_left_out"]
    assert len(obs.meta["views"]) + len(left) == 9 and len(left) == 3
    assert len({dy for _, dy, _ in left}) == 1 and all(share > 0.18 for *_, share in left)
    assert all(share <= 0.18 for share in obs.meta["views_outside"])
    geo = load_geometry(canopy_ply, 50_000, 0)
    kept = [
        _observe(geo, rowfit, "soybean", rowfit.camera.shifted(dx, dy)).stats
        for dx, dy in obs.meta["views"]
    ]
    expected = mean_stats(kept)
    for k in ("depth", "lateral", "sobel"):
        np.testing.assert_allclose(getattr(obs.stats, k), getattr(expected, k), atol=1e-12)
    assert obs.stats.mask_area == pytest.approx(expected.mask_area, abs=1e-12)
    assert obs.preset.n_views == 9  # what was asked; meta says what was pooled
    np.testing.assert_array_equal(obs.depth, _observe(geo, rowfit, "soybean", rowfit.camera).depth)


def test_cli_fit_writes_bundle_and_compare(canopy_ply, tmp_path, capsys):
    out = tmp_path / "fit"
    rc = main(
        [
            "fit",
            "soybean",
            "--geometry",
            str(canopy_ply),
            "--out",
            str(out),
            "--seeds",
            "1",
            "--evals",
            "10",
            "--initial",
            "6",
            "--param",
            "num_nodes=7",
            "--param",
            "leaf_length=0.8:1.2",
        ]
    )
    assert rc == 0
    for name in ("canopy.ply", "canopy.helios.xml", "metrics.json", "compare.png", "fit.json"):
        assert (out / name).exists(), name
    umask = os.umask(0)
    os.umask(umask)  # every file the usual mode: previews were mkstemp's 0600 (owner only)
    assert {p.stat().st_mode & 0o777 for p in out.iterdir()} == {0o666 & ~umask}
    fit = json.loads((out / "fit.json").read_text())
    assert fit["fit"]["method"] == "bo" and len(fit["fit"]["seed_losses"]) == 1
    assert fit["fit"]["params"]["num_nodes"] == 7.0  # known: not fitted
    assert 0.8 <= fit["fit"]["params"]["leaf_length"] <= 1.2
    assert fit["fit"]["config"]["box"] == {"num_nodes": 7.0, "leaf_length": [0.8, 1.2]}
    assert "views" not in fit["observation"]  # the paper's single row camera
    # the opt-in arm: pooled row cameras, the unbiased loss over three canopies
    pooled = tmp_path / "pooled"
    argv = ["fit", "soybean", "--geometry", str(canopy_ply), "--out", str(pooled)]
    argv += ["--seeds", "2", "--evals", "8", "--initial", "6", "--combine", "median"]
    argv += ["--preset", "views_along=3", "--preset", "views_across=1"]
    assert "LAI over" not in capsys.readouterr().out  # one seed: no seeds' spread
    assert "seeds" not in json.loads((out / "metrics.json").read_text())
    assert main([*argv, "--canopies", "3", "--estimator", "unbiased"]) == 0
    fit = json.loads((pooled / "fit.json").read_text())
    # two seeds: each one's answer measured beside the answer, in metrics.json and printed
    seeds = json.loads((pooled / "metrics.json").read_text())["seeds"]
    assert seeds["n_seeds"] == 2 and len(seeds["traits"]["lai"]["values"]) == 2
    lai = seeds["traits"]["lai"]
    assert f"LAI over the 2 seeds' answers: median {lai['median']:.3f}" in capsys.readouterr().out
    assert fit["fit"]["config"]["loss_estimator"] == "unbiased"
    assert fit["fit"]["config"]["canopies_per_eval"] == 3
    seen = fit["observation"]
    assert len(seen["views"]) + len(seen["views_left_out"]) == 9 and seen["views_left_out"]


def test_cli_fit_over_the_neighbour_rows_writes_their_answers_beside_the_best_rows(
    canopy_ply, tmp_path, capsys
):
    """``--neighbour-rows 1``: the rows either side of the best one that the geometry covers are
    fitted alone and laid beside its answer in rows.json; the bundle is the rows' mean answer;
    a row beyond the scan is listed and left out."""
    out = tmp_path / "rows"
    argv = ["fit", "soybean", "--geometry", str(canopy_ply), "--out", str(out)]
    argv += ["--seeds", "2", "--evals", "8", "--initial", "6", "--rows-answer", "mean"]
    # each row's seeds by their median: the default rule's re-scoring and polish on fresh
    # canopies at the full-size row camera took 4 of this test's 4.5 minutes, and the rules
    # have tests of their own (test_select)
    argv += ["--combine", "median"]
    argv += ["--workers", "2", "--neighbour-rows", "2"]  # every row's seeds in two processes
    assert main(argv) == 0
    table = json.loads((out / "rows.json").read_text())
    fit = json.loads((out / "fit.json").read_text())
    metrics = json.loads((out / "metrics.json").read_text())
    tried = {t["index"]: t for t in table["tried"]}
    assert sorted(tried) == [-2, -1, 1, 2]
    fitted = [r["index"] for r in table["rows"]]
    assert fitted == sorted([0, *(k for k in tried if tried[k]["kept"])])
    assert len(fitted) > 1
    # the plot is 2.4 m wide and the best row one of its outer rows: two rows lie beyond it
    assert sum(t["kept"] for t in tried.values()) == 2
    assert all((t["outside_fraction"] > 0.18) != t["kept"] for t in tried.values())
    best = next(r for r in table["rows"] if r["index"] == 0)
    assert best["params"] == fit["best_row_fit"]["params"]
    for name, value in fit["fit"]["params"].items():  # the answer: the rows' mean
        assert value == pytest.approx(np.mean([r["params"][name] for r in table["rows"]]))
    assert table["answer_params"] == fit["fit"]["params"]
    params = json.loads((out / "params.json").read_text())
    assert params["params"] == pytest.approx(fit["fit"]["params"])
    # the traits are the answer's canopy's, rebuilt from params.json (the rows' mean)
    from cropcraft_core.config.layout import CanopyLayout

    lay = CanopyLayout(**params["layout"])
    answer = generate_canopy("soybean", params["params"], lay, seed=params["seed"])
    assert metrics["lai"] == pytest.approx(canopy_metrics(answer, gap_fraction=False)["lai"])
    assert "seeds" not in metrics  # the rows' mean: rows.json has their spread
    assert "LAI by row" in capsys.readouterr().out
    assert len(fit["best_row_fit"]["seed_losses"]) == 2
    assert main([*argv[:-1], "9"]) == 2
    assert main([*argv, "--workers", "0"]) == 2
    assert "--workers must be at least 1, got 0" in capsys.readouterr().err


def test_cli_poisson_baseline(canopy_ply, tmp_path):
    out = tmp_path / "poisson"
    assert (
        main(
            [
                "fit",
                "soybean",
                "--geometry",
                str(canopy_ply),
                "--out",
                str(out),
                "--method",
                "poisson",
            ]
        )
        == 0
    )
    m = json.loads((out / "metrics.json").read_text())
    assert m["method"] == "poisson"
    # LAI: the kept surface's area over the points' xy box, the surface the one written
    mesh = read_ply(out / "canopy.ply")
    assert m["leaf_area_m2"] == pytest.approx(mesh.face_areas().sum(), rel=1e-6)
    assert m["lai"] == pytest.approx(m["leaf_area_m2"] / m["ground_area_m2"])
    source = read_ply(canopy_ply).vertices
    box = np.prod(np.ptp(source[:, :2], axis=0))
    assert m["ground_area_m2"] == pytest.approx(box, rel=0.05)
    # the soil cut: nothing kept within 0.2 m of the ground (the canopy stands on z = 0)
    assert mesh.vertices[mesh.faces].mean(1)[:, 2].min() > 0.2
    # every surface counted as leaf: above the canopy's leaf LAI (1.82 against 1.38 when
    # measured), but of its order
    lay = default_layout("soybean", plot_length=2.0, plot_width=2.4)
    truth = generate_canopy("soybean", {"num_nodes": 7, "leaf_length": 1.1}, lay, seed=3)
    true_lai = canopy_metrics(truth, gap_fraction=False)["lai"]
    assert 1.0 * true_lai < m["lai"] < 4.0 * true_lai
    assert m["n_faces"] <= 50_000  # the paper's 50K faces
    assert sum(m["leaf_angle_hist"]) == pytest.approx(1.0)


def test_poissons_box_is_the_points_footprint_and_for_maize_a_4_m_column():
    """The paper's baseline: soybean in the method's box, maize in a 4 m x 4 m column."""
    from cropcraft_core.fit.geometry import poisson_region

    pts = np.random.default_rng(0).uniform([-3.0, -6.0, 0.0], [7.0, 2.0, 2.0], (2000, 3))
    lo, hi = poisson_region(pts, "soybean")
    assert np.allclose(lo, pts[:, :2].min(0)) and np.allclose(hi, pts[:, :2].max(0))
    lo, hi = poisson_region(pts, "maize")
    assert np.allclose(hi - lo, 4.0) and np.allclose(0.5 * (lo + hi), [2.0, -2.0], atol=0.05)


def test_poisson_is_the_same_wherever_the_points_lie(canopy_ply, tmp_path):
    """Open3D's Poisson about the points' centre: at UTM coordinates (in doubles) it kept
    55k of 409k faces; an earlier fit's files in the folder are not left beside its own."""
    from cropcraft_core.fit.geometry import poisson_baseline

    geo = load_geometry(canopy_ply, n_points=60_000)
    here = poisson_baseline(geo.points, "soybean", depth=7)
    there = poisson_baseline(geo.points + [500_000.0, 4_000_000.0, 0.0], "soybean", depth=7)
    assert abs(there.n_faces / here.n_faces - 1) < 0.02
    assert abs(there.face_areas().sum() / here.face_areas().sum() - 1) < 0.02
    out = tmp_path / "fit"
    out.mkdir()
    for name in ("params.json", "compare.png", "rows.json", "canopy.glb"):
        (out / name).write_text("an earlier fit's")
    (out / "notes.txt").write_text("mine")
    argv = ["fit", "soybean", "--geometry", str(canopy_ply), "--out", str(out)]
    assert main([*argv, "--method", "poisson"]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["canopy.ply", "metrics.json", "notes.txt"]


def test_a_cloud_merged_with_itself_is_splatted_as_wide_as_the_cloud():
    """Exact duplicates (two passes or overlapping tiles concatenated) read a spacing of 0 and
    splatted the cloud 1 px wide: 1.4 % of the view covered instead of all of it."""
    cam = PinholeCamera.look_down(height_m=1.0, size=(200, 150))
    rng = np.random.default_rng(0)
    g = np.stack(np.meshgrid(np.arange(-1, 1, 0.03), np.arange(-1, 1, 0.03)), -1).reshape(-1, 2)
    pts = np.column_stack([g + rng.normal(0, 0.003, g.shape), np.full(len(g), 0.5)])
    once, twice = splat_radius(pts, cam), splat_radius(np.concatenate([pts, pts[::-1]]), cam)
    assert once[0] > 1 and twice == pytest.approx(once, rel=0.05)
    assert np.isfinite(splat_depth(np.concatenate([pts, pts]), cam, twice[0])).mean() > 0.99


def test_splat_depth_of_a_plane():
    cam = PinholeCamera.look_down(height_m=1.0, size=(64, 48))
    g = np.stack(np.meshgrid(np.linspace(-1, 1, 300), np.linspace(-1, 1, 300)), -1).reshape(-1, 2)
    pts = np.column_stack([g, np.full(len(g), 0.3)])
    d = splat_depth(pts, cam)
    assert np.isfinite(d).mean() > 0.99
    assert np.nanmax(np.abs(d - 0.7)) < 1e-5


def test_cli_fit_bad_inputs(tmp_path, capsys):
    assert (
        main(
            [
                "fit",
                "soybean",
                "--geometry",
                str(tmp_path / "none.ply"),
                "--out",
                str(tmp_path / "o"),
            ]
        )
        == 2
    )
    assert "none.ply: no such file" in capsys.readouterr().err
    bad = tmp_path / "bad.ply"
    bad.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 10\n")
    assert main(["fit", "soybean", "--geometry", str(bad), "--out", str(tmp_path / "o")]) == 2
    assert "bad.ply" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()  # a failed fit leaves no empty --out behind
    args = ["fit", "maize", "--geometry", str(bad), "--out", str(tmp_path / "o")]
    assert main([*args, "--param", "num_nodes=30"]) == 2
    assert "num_nodes: [30, 30] reaches outside the model's range [1, 18]" in (
        capsys.readouterr().err
    )
    assert main([*args, "--param", "num_nodes=4:6:8"]) == 2
    assert "more than two numbers" in capsys.readouterr().err
    assert main([*args, "--preset", "views_along=2"]) == 2
    assert "views_along" in capsys.readouterr().err
    assert main([*args, "--preset", "view_along=3"]) == 2
    assert "view_along" in capsys.readouterr().err


def test_a_mesh_with_a_non_finite_vertex_is_named(tmp_path):
    """Sampling a mesh weighs its faces by area: a NaN corner made numpy's 'probabilities
    contain NaN', not the error naming the file."""
    text = (
        "ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\n"
        "property float z\nelement face 2\nproperty list uchar int vertex_indices\nend_header\n"
        "0 0 0\n1 0 0\n1 1 nan\n0 1 0\n3 0 1 2\n3 0 2 3\n"
    )
    (tmp_path / "nan.ply").write_text(text)
    with pytest.raises(InputError, match="nan.ply: geometry has non-finite coordinates"):
        load_geometry(tmp_path / "nan.ply")


def test_compare_image_spans_the_observed_depths():
    """compare.png coloured depth over 0 to the render height: a maize canopy 3.8-4.9 m under
    its 5 m camera took the top fifth of the colour map. Now the nearest observed depth is
    the map's first colour and the farthest its last, on both panels."""
    from cropcraft_core.fit.geometry import compare_image
    from cropcraft_core.render.preview import depth_to_rgb

    d = np.full((184, 248), np.nan)
    d[60:140, 30:200] = np.linspace(3.8, 4.9, 170)[None, :]
    img = compare_image(d, d, 5.0)
    ends = depth_to_rgb(np.array([[0.0, 1.0]]), 0.0, 1.0)[0]
    for x0 in (0, 248 + 8):
        assert np.array_equal(img[100, x0 + 30], ends[0])
        assert np.array_equal(img[100, x0 + 199], ends[1])
