"""`cropcraft fit --geometry`: fit a metric z-up mesh or point cloud, end to end through the CLI."""

import json

import numpy as np
import pytest

from cropcraft_core.config import default_layout
from cropcraft_core.export import write_ply
from cropcraft_core.fit.geometry import load_geometry, observe_geometry, splat_depth
from cropcraft_core.geometry import PinholeCamera
from cropcraft_core.procedural import generate_canopy, plot_region
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
    assert geo.points[:, 2].min() < 1e-3


def test_canopy_rows_and_camera(canopy_ply):
    obs, rowfit = observe_geometry(canopy_ply, "soybean", n_points=50_000, row_spacing=0.76)
    # rows run along x at y = k * 0.76: the camera looks along a row, over one of them
    assert abs(rowfit.best_row.azimuth_deg) < 3.0
    y = rowfit.camera.center[1]
    assert min(abs(y - k * 0.76) for k in (-1, 0, 1)) < 0.06
    assert obs.stats.mask_area > 0.2


def test_cli_fit_writes_bundle_and_compare(canopy_ply, tmp_path):
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
        ]
    )
    assert rc == 0
    for name in ("canopy.ply", "canopy.helios.xml", "metrics.json", "compare.png", "fit.json"):
        assert (out / name).exists(), name
    fit = json.loads((out / "fit.json").read_text())
    assert fit["fit"]["method"] == "bo" and len(fit["fit"]["seed_losses"]) == 1


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
    assert m["method"] == "poisson" and m["lai"] > 0


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
    assert not (tmp_path / "o" / "metrics.json").exists()
