"""`cropcraft generate` and `cropcraft synth`: what they write and their errors (one line,
exit 2, nothing written)."""

import json
import os
import socket
import time

import pytest

from flows.cli import main

REQUIRED_METRICS = {
    "lai",
    "lai_gap_fraction",
    "leaf_area_m2",
    "ground_area_m2",
    "leaf_angle_mean_deg",
    "leaf_angle_std_deg",
    "leaf_angle_hist",
    "node_count",
    "internode_mean_m",
    "plant_height_m",
    "n_plants",
    "n_faces",
    "definitions",
}


@pytest.mark.parametrize("crop,plot", [("soybean", "1.6,1.0"), ("maize", "1.6,1.6")])
def test_generate_writes_every_file(tmp_path, crop, plot, capsys):
    out = tmp_path / "out"
    rc = main(
        [
            "generate",
            crop,
            "--param",
            "num_nodes=6",
            "--seed",
            "3",
            "--plot",
            plot,
            "--out",
            str(out),
        ]
    )
    assert rc == 0
    for name in (
        "canopy.ply",
        "canopy.obj",
        "canopy.mtl",
        "canopy.glb",
        "canopy.helios.xml",
        "params.json",
        "metrics.json",
        "preview.png",
    ):
        assert (out / name).stat().st_size > 0, name
    metrics = json.loads((out / "metrics.json").read_text())
    assert REQUIRED_METRICS <= set(metrics)
    assert metrics["definitions"]["lai"]["unit"]
    params = json.loads((out / "params.json").read_text())
    assert params["params"]["num_nodes"] == 6.0 and params["seed"] == 3
    # parameters not given take the middle of their range
    assert params["params"]["leaf_length"] == pytest.approx(1.0)
    assert "written to" in capsys.readouterr().out
    assert not [p for p in out.iterdir() if p.name.startswith(".")]  # no temporary leftovers


@pytest.mark.parametrize(
    "args,message",
    [
        (["generate", "wheat"], "unknown crop 'wheat'"),
        (["generate", "soybean", "--param", "leaf_width=1"], "unknown soybean parameter"),
        (["generate", "soybean", "--param", "num_nodes=20"], "outside its range [1, 14]"),
        (["generate", "maize", "--param", "leaf_length"], "--param expects NAME=VALUE"),
        (["generate", "soybean", "--plot", "0,2"], "plot width must be a positive number"),
        (["generate", "soybean", "--row-spacing", "-0.76"], "row spacing must be a positive"),
        (["generate", "soybean", "--density", "0"], "density must be a positive number"),
        (["synth", "wheat"], "unknown crop 'wheat'"),
        (["synth", "maize", "--param", "num_nodes=40"], "outside its range [1, 18]"),
        (["synth", "soybean", "--resolution", "640"], "--resolution expects WIDTHxHEIGHT"),
        (["synth", "soybean", "--views", "1"], "at least 2 views"),
    ],
)
def test_bad_input_writes_nothing(tmp_path, capsys, args, message):
    out = tmp_path / "out"
    assert main([*args, "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("cropcraft: error:") and message in err and "\n" not in err
    assert not out.exists()


def test_an_empty_out_or_a_bad_runner_is_refused_writing_nothing(tmp_path, capsys, monkeypatch):
    """``--out ""`` (an unset shell variable) wrote the bundle into the current folder, and a
    mistyped --runner was refused after the store's folder was made (session 91's CLI
    audit)."""
    monkeypatch.chdir(tmp_path)
    assert main(["generate", "soybean", "--out", ""]) == 2
    assert "output directory is an empty path" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []
    store = tmp_path / "new_store"
    argv = ["run", "plotA/soybean/2024-07-01", "--store", str(store), "--runner", "proceses"]
    assert main(argv) == 2
    assert "unknown runner 'proceses'" in capsys.readouterr().err and not store.exists()
    assert main(["demo", "--store", str(store), "--set", "fit.n_evalz=3"]) == 2
    assert "fit.n_evalz" in capsys.readouterr().err and not store.exists()


def test_generate_unwritable_output(tmp_path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("not a directory")
    assert main(["generate", "soybean", "--out", str(blocker / "out")]) == 2
    err = capsys.readouterr().err
    assert "cannot write output directory" in err and str(blocker) in err
    assert blocker.read_text() == "not a directory"


def test_a_failed_command_removes_only_the_empty_folders_it_made(tmp_path):
    from cropcraft_core.bundle import output_dir

    kept = tmp_path / "kept"
    kept.mkdir()
    with pytest.raises(RuntimeError), output_dir(kept / "a" / "b") as out:
        assert out.is_dir()
        raise RuntimeError("the run failed")
    assert kept.is_dir() and not (kept / "a").exists()
    with pytest.raises(RuntimeError), output_dir(kept / "a" / "b") as out:
        (out.parent / "note.txt").write_text("written during the run")
        raise RuntimeError("the run failed")
    assert not (kept / "a" / "b").exists() and (kept / "a" / "note.txt").is_file()
    with output_dir(kept / "c") as out:
        pass
    assert out.is_dir()


def test_generate_keeps_old_bundle_when_writing_fails(tmp_path, monkeypatch):
    out = tmp_path / "out"
    assert main(["generate", "soybean", "--plot", "1.6,0.5", "--out", str(out)]) == 0
    before = (out / "metrics.json").read_bytes()

    def broken(*a, **k):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr("cropcraft_core.export.write_glb", broken)
    assert main(["generate", "soybean", "--plot", "1.6,0.5", "--seed", "9", "--out", str(out)]) == 2
    assert (out / "metrics.json").read_bytes() == before
    assert not [p for p in out.iterdir() if p.name.startswith(".")]


def test_generate_replaces_the_bundle_as_one_set(tmp_path, monkeypatch, capsys):
    """A bundle is published all or nothing: a folder in the way of one file stops it before
    any file moves, and a move failing part-way (injected: a real one cannot be provoked on
    demand) puts every earlier file back; never two canopies' files side by side."""
    import os

    out = tmp_path / "out"
    args = ["generate", "soybean", "--plot", "1.6,0.5", "--out", str(out)]
    assert main(args) == 0
    files = {p.name: p.read_bytes() for p in out.iterdir()}

    (out / "preview.png").unlink()
    (out / "preview.png").mkdir()
    assert main([*args, "--seed", "9"]) == 2
    assert "preview.png: a folder of that name is in the way" in capsys.readouterr().err
    assert all((out / n).read_bytes() == b for n, b in files.items() if n != "preview.png")
    (out / "preview.png").rmdir()
    (out / "preview.png").write_bytes(files["preview.png"])

    replace = os.replace

    def failing(src, dst, *a, **k):
        if str(dst) == str(out / "metrics.json") and ".previous-" not in str(src):
            raise OSError(28, "No space left on device")
        return replace(src, dst, *a, **k)

    monkeypatch.setattr(os, "replace", failing)
    assert main([*args, "--seed", "9"]) == 2
    monkeypatch.setattr(os, "replace", replace)
    assert {p.name: p.read_bytes() for p in out.iterdir()} == files


def test_demo_inputs_are_remade_when_the_demo_scene_changes(tmp_path, monkeypatch):
    """A store holding the demo scene of other settings (an older release's) gets the current
    one, with no photo of the old scene left in the inbox; the same settings are not remade."""
    from cropcraft_core.store import SceneStore
    from flows import service_cli

    store = SceneStore.connect(str(tmp_path / "store"))
    inbox = "/".join(service_cli.DEMO_SCENE) + "/images"
    small = {"seed": 0, "views": 6, "resolution": (96, 72), "trajectory": "walk"}
    monkeypatch.setattr(service_cli, "DEMO_SYNTH", small)
    service_cli.ensure_demo_inputs(store)
    photos = [k for k in store.list(inbox) if not k.endswith(".json")]
    assert len(photos) == 6
    store.put_bytes(inbox + "/sentinel.txt", b"left by a user")
    service_cli.ensure_demo_inputs(store)  # same settings: the inbox is left as it is
    assert store.isfile(inbox + "/sentinel.txt")

    monkeypatch.setattr(service_cli, "DEMO_SYNTH", {**small, "views": 4})
    service_cli.ensure_demo_inputs(store)
    photos = [k for k in store.list(inbox) if not k.endswith(".json")]
    assert len(photos) == 4 and not store.isfile(inbox + "/sentinel.txt")
    poses = json.loads(store.get_bytes(inbox + "/transforms.json"))
    assert len(poses["frames"]) == 4
    assert store.get_json("/".join(service_cli.DEMO_SCENE) + "/truth/synth.json")["views"] == 4


def test_synth_writes_a_photo_scene_and_replaces_an_older_one_whole(tmp_path, capsys):
    """Photos, both pose formats, per-view true depth and the truth; a second scene written
    into the same folder replaces the first one's files of each kind instead of mixing."""
    out = tmp_path / "scene"
    args = ["synth", "soybean", "--out", str(out), "--resolution", "96x72", "--seed", "2"]
    assert main([*args, "--views", "5", "--param", "num_nodes=3"]) == 0
    assert len(list((out / "images").iterdir())) == 5 == len(list((out / "depth").iterdir()))
    assert len(json.loads((out / "transforms.json").read_text())["frames"]) == 5
    assert (out / "colmap" / "sparse" / "0" / "images.txt").is_file()
    truth = json.loads((out / "truth" / "params.json").read_text())
    assert truth["params"]["num_nodes"] == 3 and truth["seed"] == 2
    assert {p.name for p in (out / "truth").iterdir()} >= {"canopy.ply", "metrics.json"}
    assert "5 walk views at 96x72" in capsys.readouterr().out
    assert main([*args, "--views", "3"]) == 0
    assert len(list((out / "images").iterdir())) == 3 == len(list((out / "depth").iterdir()))
    assert len(json.loads((out / "transforms.json").read_text())["frames"]) == 3
    assert json.loads((out / "truth" / "params.json").read_text())["params"]["num_nodes"] == 7.5
    assert not [p for p in out.iterdir() if p.name.startswith(".")]


def test_camera_distance_is_a_scale_shortcut():
    from cropcraft_core.errors import ConfigError
    from flows.cli import build_parser
    from flows.service_cli import overrides_of

    args = build_parser().parse_args(["demo", "--camera-distance", "a.jpg", "b.jpg", "2.5"])
    assert overrides_of(args)["poses.camera_distance"] == ["a.jpg", "b.jpg", 2.5]
    bad = build_parser().parse_args(["demo", "--camera-distance", "a.jpg", "b.jpg", "far"])
    with pytest.raises(ConfigError, match="not a number of metres"):
        overrides_of(bad)


def test_row_spacing_is_a_layout_shortcut_and_the_summary_names_the_spacing_used(capsys):
    """0.38 m soybean rows run as the default 0.76 m ones (metric poses) put the row camera 63°
    across them with nothing said, and ``run`` had no ``--row-spacing`` as ``fit`` has (session
    96's field audit): it is the layout's shortcut, keys the rows and the canopy's stages as
    ``--set layout.row_spacing`` does, and the run's summary says which spacing it used."""
    from flows.cli import build_parser
    from flows.scene import resolve_config, stage_configs
    from flows.service_cli import _print_summary, overrides_of
    from tasks.fit_seed import row_spacing_used

    for command in (["run", "s/soybean/2024-07-01"], ["season", "s/soybean"], ["demo"]):
        args = build_parser().parse_args([*command, "--row-spacing", "0.38"])
        assert overrides_of(args) == {"layout.row_spacing": 0.38}
    # a whole number keys the stages as the flag's float does (--set's JSON 1 refitted all)
    whole = [
        resolve_config(
            "soybean",
            overrides_of(build_parser().parse_args(["run", "s/soybean/2024-07-01", *flag])),
        )
        for flag in (["--row-spacing", "1"], ["--set", "layout.row_spacing=1"])  # fmt: skip
    ]
    assert stage_configs(whole[0], "soybean") == stage_configs(whole[1], "soybean")
    # the default written out is the default, in the summary as in the report (session 96)
    written = stage_configs(resolve_config("soybean", {"layout.row_spacing": 0.76}), "soybean")
    assert row_spacing_used("soybean", written["rowfit"])["given"] is False
    cfg = resolve_config("soybean", {"layout.row_spacing": 0.38})
    same = resolve_config("soybean", overrides_of(build_parser().parse_args(
        ["run", "s/soybean/2024-07-01", "--set", "layout.row_spacing=0.38"])))  # fmt: skip
    assert stage_configs(cfg, "soybean") == stage_configs(same, "soybean")
    assert stage_configs(cfg, "soybean")["rowfit"]["layout"] == {"row_spacing": 0.38}
    assert row_spacing_used("soybean", stage_configs(cfg, "soybean")["rowfit"]) == {
        "m": 0.38,
        "given": True,
    }
    rowfit = stage_configs(resolve_config("soybean"), "soybean")["rowfit"]
    default = row_spacing_used("soybean", rowfit)
    assert default == {"m": 0.76, "given": False}
    base = {"scene": "s/soybean/2024-07-01", "store": "/x", "states": {}, "metrics": {},
            "report": "r", "bundle": "b"}  # fmt: skip
    _print_summary({**base, "row_spacing": default})
    said = capsys.readouterr().out
    assert "rows     0.76 m apart (the crop's default: give --row-spacing M where" in said
    _print_summary({**base, "row_spacing": {"m": 0.38, "given": True}})
    assert "rows     0.38 m apart (given)" in capsys.readouterr().out
    # where the scale came from, said in words: assumed_metric was in the report only
    _print_summary({**base, "scale_source": "assumed_metric"})
    assert "scale    assumed from the crop's usual capture height, measured by nothing" in (
        capsys.readouterr().out
    )


def test_param_is_a_parameter_box_shortcut_checked_against_the_crop():
    from cropcraft_core.errors import ConfigError
    from flows.cli import build_parser
    from flows.scene import resolve_config, stage_configs
    from flows.service_cli import overrides_of

    argv = ["run", "s/soybean/2024-07-01", "--param", "num_nodes=9", "--param", "leaf_length=1:1.3"]
    overrides = overrides_of(build_parser().parse_args(argv))
    assert overrides == {"fit.box.num_nodes": 9.0, "fit.box.leaf_length": [1.0, 1.3]}
    cfg = resolve_config("soybean", overrides)
    assert cfg["fit"]["box"] == {"num_nodes": 9.0, "leaf_length": [1.0, 1.3]}
    seeds = stage_configs(cfg, "soybean")["fit_seed"]
    assert seeds["box"] == cfg["fit"]["box"]
    # the whole box is hashed as before the setting existed: stored seeds stay served
    assert "box" not in stage_configs(resolve_config("soybean"), "soybean")["fit_seed"]
    # known.json's 9 and --set's [1, 1.3] are --param's 9.0 and 1:1.3: one fit, not two
    from cropcraft_core.store import config_hash

    notes = resolve_config("soybean", {"fit.box.num_nodes": 9, "fit.box.leaf_length": [1, 1.3]})
    assert config_hash(stage_configs(notes, "soybean")["fit_seed"]) == config_hash(seeds)
    with pytest.raises(ConfigError, match="unknown maize parameter 'petiole_angle'"):
        resolve_config("maize", {"fit.box.petiole_angle": 2.0})
    with pytest.raises(ConfigError, match="NAME=VALUE or NAME=LOW:HIGH"):
        overrides_of(build_parser().parse_args(["run", "s/soybean/d", "--param", "num_nodes"]))


def test_cli_gives_prefects_temporary_server_time_to_start(tmp_path):
    """Prefect waits 20 s for its temporary server; a fresh machine's first start (creating its
    database) took 19.7 s here, so `cropcraft demo` timed out. The CLI raises the wait unless
    the user set one (checked in a fresh process: Prefect reads its settings once)."""
    import os
    import subprocess
    import sys

    from flows.cli import EPHEMERAL_STARTUP_TIMEOUT_S

    key = "PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS"
    code = (
        "from flows.cli import main; "
        f"assert main(['generate', 'rice', '--out', {str(tmp_path / 'out')!r}]) == 2; "
        "from prefect.settings import get_current_settings; "
        "print(get_current_settings().server.ephemeral.startup_timeout_seconds)"
    )

    def timeout_seen(**env: str) -> int:
        base = {k: v for k, v in os.environ.items() if k != key}
        run = subprocess.run(
            [sys.executable, "-c", code], env={**base, **env}, capture_output=True, text=True
        )
        assert run.returncode == 0, run.stderr
        return int(run.stdout.strip().splitlines()[-1])

    assert EPHEMERAL_STARTUP_TIMEOUT_S >= 60
    assert timeout_seen() == EPHEMERAL_STARTUP_TIMEOUT_S
    assert timeout_seen(**{key: "45"}) == 45


@pytest.mark.parametrize("what", ["pipeline", "surfaces"])
@pytest.mark.parametrize("size", ["640", "640y480", "0x480", "640x-480"])
def test_photo_benchmarks_name_a_bad_resolution_before_making_a_scene(tmp_path, capsys, what, size):
    scene = tmp_path / "scene"
    with pytest.raises(SystemExit) as e:
        main(["bench", what, "--resolution", size, "--scene-dir", str(scene)])
    assert e.value.code == 2
    assert f"expected WIDTHxHEIGHT such as 640x480, got {size!r}" in capsys.readouterr().err
    assert not scene.exists()


def test_pipeline_benchmark_keeps_a_reused_scenes_crop(tmp_path):
    """``bench pipeline --scene-dir`` reads the crop from the scene it reuses; asking for the
    other crop names the scene file and changes nothing in it."""
    from benchmarks.bench_pipeline import scene_crop

    assert scene_crop(tmp_path, None) == "soybean"
    assert scene_crop(tmp_path, "maize") == "maize"
    f = tmp_path / "scene.json"
    f.write_text(json.dumps({"crop": "maize", "views": 3}))
    before = f.read_bytes()
    assert scene_crop(tmp_path, None) == "maize"
    assert scene_crop(tmp_path, "maize") == "maize"
    with pytest.raises(SystemExit, match=r"scene\.json: the scene is maize, not soybean"):
        scene_crop(tmp_path, "soybean")
    assert f.read_bytes() == before


def test_the_gpu_check_imports_only_what_the_gpu_host_has():
    """The nerfacto check's train half and the GPU acceptance test's module, imported in a fresh
    interpreter, load no third-party module outside ``GPU_HOST_MODULES`` (the lent GPU host's
    image and the wheels ``deploy/gpu_check_prepare.sh`` carries): an import the host lacks
    otherwise shows only after a machine's start, as pydantic did in session 82."""
    import subprocess
    import sys
    from pathlib import Path

    from benchmarks.bench_nerfacto import GPU_HOST_MODULES

    root = Path(__file__).resolve().parents[1]
    code = """
import importlib.util, json, sys
sys.path.insert(0, "tests")
import conftest  # as pytest loads it first: it pins the kernels
import benchmarks.bench_nerfacto, cropcraft_core.surfaces.nerfacto
spec = importlib.util.spec_from_file_location("test_surfaces", "tests/test_surfaces.py")
spec.loader.exec_module(importlib.util.module_from_spec(spec))
print(json.dumps(sorted({m.split(".")[0] for m in sys.modules})))
"""
    done = subprocess.run(
        [sys.executable, "-c", code], cwd=root, capture_output=True, text=True, check=False
    )
    assert done.returncode == 0, done.stderr
    loaded = set(json.loads(done.stdout.splitlines()[-1]))
    ours = {"benchmarks", "conftest", "cropcraft_core", "flows", "tests"}
    third_party = {m for m in loaded - set(sys.stdlib_module_names) - ours if not m.startswith("_")}
    assert third_party <= GPU_HOST_MODULES, sorted(third_party - GPU_HOST_MODULES)


def test_nerfacto_benchmark_scores_a_view_against_its_true_depth():
    """``bench nerfacto``'s per-view score, by hand: a 2 × 2 truth, one pixel rendered 1 cm off,
    one 10 % too far, one left empty, and one where the truth has nothing (not counted)."""
    import numpy as np

    from benchmarks.bench_nerfacto import view_scores

    true = np.array([[1.0, 2.0], [1.5, np.nan]])
    depth = np.array([[1.01, 2.2], [np.nan, 3.0]])
    s = view_scores(depth, true)
    assert s["median_abs_err_m"] == pytest.approx((0.01 + 0.2) / 2)
    assert s["median_ratio"] == pytest.approx((1.01 + 1.1) / 2)
    assert s["within"] == pytest.approx(0.5)
    assert s["holes"] == pytest.approx(1 / 3)


def test_nerfacto_compare_prints_its_figures_against_the_targets(capsys):
    """``bench nerfacto compare``'s table: each measure against #4's target (row 2° / 3 cm /
    3 %, L1 0.15, LAI 15 %), met or not."""
    from benchmarks.bench_nerfacto import print_compare

    out = {
        "backend": "nerfacto",
        "scene_dir": "SA",
        "surfaces_timings": {"nerf_iterations_done": 1001, "nerf_far_plane": 3.5,
                             "nerf_train": 483.0},
        "pace": {"rows": 500, "last_step": 5000, "median_iter_ms": 96.0,
                 "median_rays_per_s": 42_670.0},
        "views_mean": {"median_ratio": 0.998, "median_abs_err_m": 0.018, "within": 0.53,
                       "holes": 0.0},
        "points": {"n": 100, "within": 0.92, "median_dist_m": 0.0058},
        "mask_area": {"observation": 0.53, "truth": 0.60},
        "holes": 0.0,
        "row_errors": {"direction_deg": 0.66, "lateral_m": 0.036, "height_rel": 0.002},
        "hist_l1": 0.123,
        "fit": {"lai_rel_err": -0.266, "budget": "10x300", "seconds": 487.0,
                "traits": {"lai": {"estimated": 0.922, "true": 1.257}},
                "loss": {"whose": "reconstruction"}},
    }  # fmt: skip
    print_compare(out)
    text = capsys.readouterr().out
    assert "1001 iterations, far plane 3.500" in text and "92.0 % of 100 points" in text
    # 5,000 steps at 96 ms are 480 s of the 483 s
    assert (
        "training pace: 96.0 ms per iteration (42.7 K rays/s), median of 500 logged rows to "
        "step 5000; 3 s of the 483 s training outside the steps"
    ) in text
    rows = [line for line in text.splitlines() if line.strip().endswith(("yes", "NO"))]
    assert [r.split()[-1] for r in rows] == ["yes", "NO", "yes", "yes", "NO"], rows
    assert "lai 0.922 (true 1.26)" in text and "miss: reconstruction" in text


def test_nerfacto_compare_names_the_far_plane_the_run_trained_with(capsys):
    """The head line says which far plane nerfacto had: from the scene box (its value in
    nerfstudio's frame), the one set in the config (maize's paper setting, 6.0: session 83's
    first maize run was printed as nerfstudio's own), or nerfstudio's own, and the settings the
    train half's ``--surfaces`` changed."""
    from benchmarks.bench_nerfacto import print_compare

    base = {"backend": "nerfacto", "scene_dir": "M", "error": "row fit: no ground found"}
    heads = []
    for rec in (
        {"surfaces_timings": {"nerf_iterations_done": 3001}, "planes": {"near": 0.05, "far": 6.0}},
        {"surfaces_timings": {"nerf_iterations_done": 4001, "nerf_far_plane": 5.7407},
         "planes": {"near": None, "far": None},
         "surfaces": {"far_plane": None, "near_plane": None}},
        {"surfaces_timings": {"nerf_iterations_done": 500}},  # far margin off, pre-83 record
    ):  # fmt: skip
        print_compare({**base, **rec})
        heads.append(capsys.readouterr().out.splitlines()[0])
    assert heads[0].endswith("3001 iterations, far plane 6 (nerfstudio's frame, set)")
    assert heads[1].endswith(
        "4001 iterations, far plane 5.741 (nerfstudio's frame, from the scene box); "
        "settings {'far_plane': None, 'near_plane': None}"
    )
    assert heads[2].endswith("500 iterations, far plane nerfstudio's (1000)")


def test_nerfacto_benchmark_reads_the_training_pace_from_the_log():
    """``bench nerfacto train``'s pace, from an ``ns-train`` log as nerfstudio's local writer
    leaves it in a file (fixed 20-character columns, its last rows reprinted after cursor-up
    escapes, the header again, a warm-up row): each step counted once, the medians by hand;
    a viewer's extra column does not shift the reading, and a log without the table gives {}."""
    from benchmarks.bench_nerfacto import train_pace

    def row(*cells):
        return "".join(f"{c:<20} " if i else f"{c:<20}" for i, c in enumerate(cells))

    head = row("Step (% Done)", "Train Iter (time)", "ETA (time)", "Train Rays / Sec")
    up = "\x1b[1A\x1b[2K" * 3
    rows = [
        row("0 (0.00%)", "14 s, 338.214 ms", "2 d, 11 h, 44 m, 33 s", "285.71"),
        row("10 (0.20%)", "96.000 ms", "8 m, 0 s", "42.67 K"),
        row("20 (0.40%)", "100.000 ms", "8 m, 19 s", "40.96 K"),
        row("30 (0.60%)", "98.000 ms", "8 m, 9 s", "41.80 K"),
    ]
    log = "\n".join(
        ["No Nerfstudio checkpoint to load, so training from scratch.", head, "-" * len(head)]
        + rows[:2]
        + [up + head, "-" * len(head), *rows[:3], up + head, "-" * len(head), *rows]
        + ["Saving checkpoint at step 30"]
    )
    pace = train_pace(log)
    assert pace["rows"] == 4 and pace["last_step"] == 30
    # medians of 4: (98 + 100) / 2 ms (the warm-up row counts, the median passes it over);
    # the warm-up row's ETA fills its column, so its rate runs into it and is not read
    assert pace["median_iter_ms"] == pytest.approx(99.0)
    assert pace["median_rays_per_s"] == pytest.approx(41_800)

    viewer = row("Step (% Done)", "Vis Rays / Sec", "Train Iter (time)", "ETA (time)")
    log = "\n".join([viewer, row("500 (2.50%)", "1.20 M", "52.000 ms", "17 m, 20 s")])
    assert train_pace(log) == {
        "rows": 1, "last_step": 500, "median_iter_ms": pytest.approx(52.0),
        "median_rays_per_s": None,
    }  # fmt: skip
    assert train_pace("Traceback (most recent call last):\n  CUDA error") == {}


def test_nerfacto_benchmark_scores_points_against_the_true_surfaces():
    """``bench nerfacto compare``'s point-cloud score, by hand (real Open3D distances): a unit
    square leaf at z = 0.5 and the soil at z = 0; a point 1 cm above the leaf, one on the soil,
    one 5 cm above the leaf's edge and one 10 cm up in the air beside it."""
    import numpy as np

    from benchmarks.bench_nerfacto import points_vs_truth
    from cropcraft_core.geometry.mesh import CanopyMesh

    v = np.array([[0, 0, 0.5], [1, 0, 0.5], [1, 1, 0.5], [0, 1, 0.5]], np.float64)
    f = np.array([[0, 1, 2], [0, 2, 3]], np.int32)
    zero = np.zeros(2, np.int32)
    mesh = CanopyMesh(v, f, np.zeros(2, np.uint8), zero, zero)
    pts = np.array([[0.5, 0.5, 0.51], [3.0, 3.0, 0.0], [1.0, 0.5, 0.55], [2.0, 2.0, 0.1]])
    s = points_vs_truth(pts, mesh)
    assert s["n"] == 4
    assert s["within"] == pytest.approx(0.5)  # the first two
    # distances 0.01, 0, 0.05, 0.1: the median is (0.01 + 0.05) / 2
    assert s["median_dist_m"] == pytest.approx(0.03, abs=1e-6)
    assert points_vs_truth(np.zeros((0, 3)), mesh)["n"] == 0


def test_nerfacto_benchmark_shares_points_by_height_against_what_the_photos_see(tmp_path):
    """``bench nerfacto compare``'s height profile, by hand: the true surfaces the photos see are
    each view's true depth unprojected (a camera 1.5 m over flat soil sees z = 0 at every
    sampled pixel); the bands are the soil (3 cm), then 10 cm bands to the highest true point,
    then the rest (under the soil or above the canopy)."""
    from pathlib import Path

    import numpy as np

    from benchmarks.bench_nerfacto import height_profile, visible_truth_points
    from cropcraft_core.geometry.camera import PinholeCamera
    from cropcraft_core.sfm import import_transforms_json
    from cropcraft_core.surfaces.nerfacto import write_transforms

    cam = PinholeCamera.look_down((0.3, -0.2), 1.5, size=(64, 48), vfov_deg=50.0)
    write_transforms(tmp_path, [np.zeros((48, 64, 3), np.uint8)], [cam])
    ((name, _),) = import_transforms_json(tmp_path / "transforms.json")
    (tmp_path / "depth").mkdir()
    depth = np.full((48, 64), 1.5)
    depth[0, 0] = np.nan  # nothing seen there: not a point
    np.save(tmp_path / "depth" / f"{Path(name).stem}.npy", depth)
    seen = visible_truth_points(tmp_path, step=4)
    assert seen.shape == (12 * 16 - 1, 3)
    np.testing.assert_allclose(seen[:, 2], 0.0, atol=1e-9)
    # the sampled pixels' centres, as the camera's own unprojection gives them
    np.testing.assert_allclose(seen[0], cam.unproject(np.full((48, 64), 1.5))[0, 4])

    truth = np.zeros((5, 3))
    truth[:, 2] = [0.0, 0.0, 0.05, 0.15, 0.25]
    cloud = np.zeros((4, 3))
    cloud[:, 2] = [0.01, 0.5, -0.2, 0.15]
    h = height_profile(cloud, truth)
    assert h["bands"] == ["soil", "0.03-0.10", "0.10-0.20", "0.20-0.30", "other"]
    assert h["truth"] == pytest.approx([0.4, 0.2, 0.2, 0.2, 0.0])
    assert h["cloud"] == pytest.approx([0.25, 0.0, 0.25, 0.0, 0.5])


def test_nerfacto_compare_without_an_observation_reports_the_point_cloud(capsys):
    """Where the train half's row fit failed, ``compare`` still prints the views, the point
    cloud and its heights, then the row fit's error, and no targets table."""
    from benchmarks.bench_nerfacto import print_compare

    out = {
        "backend": "nerfacto", "scene_dir": "SC", "surfaces_timings": {},
        "views_mean": {"median_ratio": 0.999, "median_abs_err_m": 0.02, "within": 0.52,
                       "holes": 0.0},
        "points": {"n": 100, "within": 0.87, "median_dist_m": 0.0043},
        "heights": {"bands": ["soil", "0.03-0.10", "other"], "truth": [0.055, 0.945, 0.0],
                    "cloud": [0.001, 0.999, 0.0]},
        "error": "row fit: no ground found",
    }  # fmt: skip
    print_compare(out)
    text = capsys.readouterr().out
    assert "87.0 % of 100 points" in text
    assert "soil    0.1 %  /   5.5 %" in text and "other" not in text  # empty bands left out
    assert text.rstrip().endswith("no observation: row fit: no ground found")
    assert "target" not in text


def test_nerfacto_probe_plane_is_the_same_ground_in_every_view(tmp_path):
    """``nerfacto_probe prepare --plane``: the control scene's depth is the plane's (a camera
    looking straight down from 1.5 m sees z-depth 1.5 everywhere), and its texture is a function
    of the ground point, so a point two cameras both see has one colour in both photos."""
    import json

    import numpy as np
    from PIL import Image

    from benchmarks.nerfacto_probe import main as probe
    from benchmarks.nerfacto_probe import plane_texture
    from cropcraft_core.geometry.camera import PinholeCamera
    from cropcraft_core.sfm import import_transforms_json
    from cropcraft_core.surfaces.nerfacto import write_transforms

    cams = [
        PinholeCamera.look_down((0.0, 0.0), 1.5, size=(64, 48), vfov_deg=50.0),
        PinholeCamera.look_down((0.2, 0.1), 1.2, (0.6, 0.8), size=(64, 48), vfov_deg=50.0),
    ]
    scene = tmp_path / "scene"
    blank = [np.zeros((48, 64, 3), np.uint8)] * 2
    write_transforms(scene, blank, cams)
    out = tmp_path / "plane"
    assert probe(["prepare", "--scene-dir", str(scene), "--out", str(out), "--plane"]) == 0
    names = [n for n, _ in import_transforms_json(out / "transforms.json")]
    depth = [np.load(out / "depth" / f"{n.rsplit('.', 1)[0]}.npy") for n in names]
    np.testing.assert_allclose(depth[0], 1.5, rtol=1e-6)
    np.testing.assert_allclose(depth[1], 1.2, rtol=1e-6)
    frames = json.loads((out / "data" / "transforms.json").read_text())["frames"]
    photos = [np.asarray(Image.open(out / "data" / f["file_path"])).astype(int) for f in frames]
    assert photos[0].std() > 20  # textured, not flat
    # every pixel is the texture at its centre ray's ground point, in either view
    for cam, d, photo in zip(cams, depth, photos, strict=True):
        ground = cam.unproject(d)
        np.testing.assert_allclose(ground[..., 2], 0.0, atol=1e-6)
        want = np.clip(plane_texture(ground[..., 0], ground[..., 1]), 0, 1) * 255
        assert np.abs(photo - want).max() <= 0.51


def test_run_summary_prints_each_rows_lai_and_their_spread(capsys):
    """``cropcraft run``'s summary of a scene fitted over three rows: each row's LAI and nodes,
    which answer the scene took, and the LAI's spread over the rows."""
    from flows.service_cli import _print_rows

    rows = {
        "n_rows": 3,
        "lai": {"1": 1.4, "-1": 1.1, "0": 1.2},
        "node_count": {"1": 9.0, "-1": 7.5, "0": 8.0},
        "lai_spread": {"mean": 1.2333, "sd": 0.1247, "min": 1.1, "max": 1.4},
        "answer": "mean",
    }
    _print_rows({"rows": rows})
    out = capsys.readouterr().out
    assert "-1: 1.1 (7.5 nodes)  +0: 1.2 (8 nodes)  +1: 1.4 (9 nodes)" in out
    assert "the answer is the mean of the rows' answers" in out
    assert "LAI over 3 rows: mean 1.23, sd 0.125, range 1.1 to 1.4" in out
    _print_rows({"rows": None})
    assert capsys.readouterr().out == ""


def test_run_and_demo_summaries_print_the_fits_warnings(capsys):
    """The rows against a camera-height hint and an answer pressing the box: the run summary
    (``cropcraft run``; the demo's prints them alike) gives each as a WARNING line."""
    from flows.service_cli import _print_summary

    out = {
        "scene": "s/soybean/2024-07-01",
        "store": "/x",
        "states": {"ingest": "Cached"},
        "metrics": {"lai": 1.2},
        "scale_warning": "the camera height given (1.4 m) and the rows disagree",
        "edge_warning": "the answer lies on the edge of the soybean parameter box",
        "report": "r",
        "bundle": "b",
    }
    _print_summary(out)
    printed = capsys.readouterr().out
    assert "WARNING  the camera height given (1.4 m) and the rows disagree" in printed
    assert "WARNING  the answer lies on the edge of the soybean parameter box" in printed
    # each number with its unit (a bare "lai 4.198" beside no m2/m2: session 91's CLI audit)
    assert "  lai                    1.2  m2/m2 (one-sided leaf area per ground area)" in printed


def test_run_summary_names_the_photos_sfm_left_out_and_the_copies(capsys):
    """SfM that registered 22 of 36 photos (the far side of the plot) said so only in the
    report's header, and dropped copies nowhere: the run's summary names both."""
    from flows.service_cli import _print_left_out

    _print_left_out(
        {
            "photos_left_out": {
                "unregistered": [f"view_{i:03d}.png" for i in range(18, 32)],
                "duplicates": ["view_002.jpg (= IMG_2000.jpg)"],
                "in_subfolders": ["101MEDIA/DJI_1000.JPG"],
            }
        }
    )
    said = capsys.readouterr().out.splitlines()
    assert said[0].startswith(
        "WARNING  14 photo(s) were not registered by structure from motion, left out: "
        "view_018.png, "
    ) and said[0].endswith("(+6 more)")
    assert said[1] == (
        "WARNING  1 photo(s) are copies of another photo, left out: view_002.jpg (= IMG_2000.jpg)"
    )
    assert said[2] == (  # a second card folder beside the photos (session 91's ingest audit)
        "WARNING  1 photo(s) are in subfolders, which are not read (move them into the folder), "
        "left out: 101MEDIA/DJI_1000.JPG"
    )


def test_run_progress_without_a_terminal_prints_each_10_percent_mark(capsys):
    """Without a terminal (a nightly job's log) a run's progress is one line at each 10 % of a
    long stage's step (the surfaces' stereo) and of each seed's evaluations, and once at the
    end, the seed's with its best loss so far."""
    from flows.service_cli import run_progress
    from tasks.common import report_progress, report_stage

    with run_progress(bar=True):  # pytest's stderr is no terminal: lines, not a bar
        for i in range(1, 51):  # 50 views
            report_stage("s/soybean/d", "surfaces: stereo", round(100 * i / 50), 100)
        report_stage("s/soybean/d", "surfaces: fusion", 100, 100)
        for done in range(1, 45):  # seed 0 stops early at 44 of 50 (a converged polish)
            report_progress("s/soybean/d", 0, done, 50, 1.0 / done)
        report_progress("s/soybean/d", 0, 50, 50, 0.0123)
        report_progress("s/soybean/d", 0, 50, 50, 0.0123)  # the task's closing tick again
        report_progress("s/soybean/d", "row_p1/2", 7, 7, None)
    report_progress("s/soybean/d", 0, 50, 50, 0.0)  # no sink after the block
    lines = capsys.readouterr().err.splitlines()
    seed0 = [line.split(" | ", 1)[1] for line in lines if "fit seed 0:" in line]
    assert seed0 == [
        *(f"fit seed 0: {d}/50 evaluations, best loss {1.0 / d:.4g}" for d in range(5, 45, 5)),
        "fit seed 0: 50/50 evaluations, best loss 0.0123",
    ]
    assert [line.split(" | ", 1)[1] for line in lines if "row_p1" in line] == [
        "fit seed row_p1/2: 7/7 evaluations"
    ]
    assert [line.split(" | ", 1)[1] for line in lines if "surfaces" in line] == [
        *(f"surfaces: stereo {p} %" for p in range(10, 101, 10)),
        "surfaces: fusion 100 %",
    ]


def test_run_progress_on_a_terminal_is_one_bar_from_stage_to_fit(monkeypatch):
    """On a terminal one bar follows the run: the surfaces' step in per cent, then all seeds'
    evaluations with the lowest loss any seed has reached."""
    import io
    import sys

    from flows.service_cli import run_progress
    from tasks.common import report_progress, report_stage

    class Terminal(io.StringIO):
        def isatty(self) -> bool:
            return True

    term = Terminal()
    monkeypatch.setattr(sys, "stderr", term)
    with run_progress(bar=True):
        report_stage("s/soybean/d", "surfaces: stereo", 40, 100)
        assert "surfaces: stereo" in term.getvalue().rsplit("\r", 1)[-1]
        report_progress("s/soybean/d", 0, 30, 50, 0.2)
        report_progress("s/soybean/d", 1, 20, 50, 0.1)
        last = term.getvalue().rsplit("\r", 1)[-1]
    assert "fit (BO evaluations)" in last and "50/100" in last and "best loss 0.1" in last


def test_a_log_line_on_a_terminal_prints_above_the_bar_not_over_it(monkeypatch):
    """A record the console prints while the bar is up (the flow's stage lines, warnings) gets
    its own line: the bar is cleared before it and redrawn under it, unless its step is
    finished, when the bar stays above as a line; after the run the console handler writes as
    before."""
    import io
    import logging
    import sys

    from flows.service_cli import run_progress
    from tasks.common import report_progress, report_stage

    class Terminal(io.StringIO):
        def isatty(self) -> bool:
            return True

    term = Terminal()
    monkeypatch.setattr(sys, "stderr", term)
    console = logging.StreamHandler(term)
    console.setFormatter(logging.Formatter("%(message)s"))
    log = logging.getLogger("cropcraft.test.console")
    monkeypatch.setattr(log, "propagate", False)
    monkeypatch.setattr(log, "level", logging.INFO)
    log.addHandler(console)
    logging.getLogger().addHandler(console)  # the root's handlers are the ones wrapped
    try:
        with run_progress(bar=True):
            log.info("ingest: Completed (0.6 s)")
            assert term.getvalue() == "ingest: Completed (0.6 s)\n"  # no bar before a tick
            report_stage("s/soybean/d", "surfaces: stereo", 40, 100)
            log.info("surfaces: Completed (437.1 s)")
            before, after = term.getvalue().split("surfaces: Completed (437.1 s)")
            # the bar's line was blanked and the cursor sent back before the message ...
            assert before.endswith("\r") and before.rsplit("\r", 2)[-2].strip() == ""
            # ... which ends its line; the bar is drawn again below it
            assert after.startswith("\n") and "40/100" in after
            # a finished step's bar stays above as a line of its own and is not drawn again
            report_stage("s/soybean/d", "surfaces: stereo", 100, 100)
            report_stage("s/soybean/d", "surfaces: stereo", 100, 100)  # its closing tick again
            log.info("surfaces: Completed (437.1 s)")
            done, msg = term.getvalue().rsplit("\n", 2)[-3:-1]
            assert "100/100" in done.rsplit("\r", 1)[-1] and msg == "surfaces: Completed (437.1 s)"
            assert term.getvalue().count("100/100") == 1
            # so does the fit's, once a line is printed under it
            report_progress("s/soybean/d", 0, 1, 2, 0.2)  # the next step: a new bar
            assert "1/2" in term.getvalue().rsplit("\r", 1)[-1]
            report_progress("s/soybean/d", 0, 2, 2, 0.1)
            log.info("aggregate: Completed (97.7 s)")
            done, msg = term.getvalue().rsplit("\n", 2)[-3:-1]
            assert "2/2" in done.rsplit("\r", 1)[-1] and msg == "aggregate: Completed (97.7 s)"
        assert "emit" not in vars(console)
        log.info("after the run")
        assert term.getvalue().endswith("after the run\n")
    finally:
        logging.getLogger().removeHandler(console)
        log.removeHandler(console)


def test_a_resumed_seeds_progress_starts_from_its_checkpoints_best(tmp_path):
    """A seed resumed from its checkpoint reports the best loss of every evaluation it holds,
    not only of those it makes after the resume."""
    import numpy as np

    from cropcraft_core.optimize import BOConfig, run_seed
    from tasks.fit_seed import _best_so_far

    ckpt = tmp_path / "seed.json"
    assert _best_so_far(ckpt) == float("inf")
    res = run_seed(
        lambda x, i: float(((x - 0.3) ** 2).sum()),
        [[0, 1], [0, 1]],
        BOConfig(n_evals=8, n_initial=4),
        seed=1,
        checkpoint=ckpt,
    )
    assert _best_so_far(ckpt) == float(np.min(res.y))
    ckpt.write_text("{not json")
    assert _best_so_far(ckpt) == float("inf")  # the optimiser names a bad checkpoint itself


def test_run_progress_keeps_prefects_task_run_records_off_the_console():
    """During a fit the console (Prefect's handler in this process, the threads runner's) drops
    task runs' INFO records, as the processes runner's workers do; warnings, the flow's stage
    lines and everything after the fit still print."""
    import logging

    from prefect import flow  # noqa: F401 - Prefect sets its console up on loading (alone: here)
    from prefect.logging.handlers import PrefectConsoleHandler

    from flows.service_cli import run_progress

    console = [h for h in logging.getLogger().handlers if isinstance(h, PrefectConsoleHandler)]
    assert console, "Prefect configured no console handler"

    def shown(name: str, level: int) -> bool:
        record = logging.LogRecord(name, level, __file__, 1, "msg", None, None)
        return all(h.filter(record) for h in console)

    with run_progress(bar=False):
        assert not shown("prefect.task_runs", logging.INFO)
        assert shown("prefect.task_runs", logging.WARNING)
        assert shown("prefect.flow_runs", logging.INFO)
    assert shown("prefect.task_runs", logging.INFO)


def test_ctrl_c_ends_the_command_and_its_child_processes(tmp_path):
    """A Ctrl-C the command cannot honour (here: its main thread swallows KeyboardInterrupt,
    as Prefect's crash handling does while it retries a temporary server the same Ctrl-C
    stopped) still ends it: after the grace period every child process is ended and the
    process exits 130; a second Ctrl-C does so at once."""
    import os
    import signal
    import subprocess
    import sys
    import time

    import psutil

    code = (
        "import signal, subprocess, sys, time\n"
        # as from a terminal: SIGINT not ignored even if the test runner's shell ignores it
        "signal.signal(signal.SIGINT, signal.default_int_handler)\n"
        "from flows.cli import interrupt_deadline\n"
        "with interrupt_deadline(grace_s=float(sys.argv[1])):\n"
        "    child = subprocess.Popen([sys.executable, '-c', 'import time; time.sleep(120)'])\n"
        "    while True:\n"
        "        try:\n"
        "            if child:\n"  # the pid once inside the try: no interrupt can escape it
        "                print(child.pid, flush=True)\n"
        "                child = None\n"
        "            time.sleep(120)\n"
        "        except KeyboardInterrupt:\n"
        "            pass\n"
    )
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    # SIGTERM (a scheduler's stop, `kill`, `timeout`) left Prefect's temporary server running,
    # orphaned (session 91's CLI audit): it ends the command as Ctrl-C does, 143
    cases = (
        (2.0, signal.SIGINT, 1, 2.0, 130, "interrupted"),
        (60.0, signal.SIGINT, 2, 0.0, 130, "interrupted"),
        (2.0, signal.SIGTERM, 1, 2.0, 143, "terminated"),
        (60.0, signal.SIGTERM, 2, 0.0, 143, "terminated"),
    )
    for grace, sig, presses, within, rc, said in cases:
        proc = subprocess.Popen(
            [sys.executable, "-c", code, str(grace)],
            cwd=root,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        child = int(proc.stdout.readline())
        t0 = time.monotonic()
        for _ in range(presses):
            proc.send_signal(sig)
            time.sleep(0.5)
        assert proc.wait(timeout=30) == rc
        elapsed = time.monotonic() - t0
        assert within <= elapsed < within + 15, elapsed
        assert f"{said}; ending its processes" in proc.stderr.read()
        assert not psutil.pid_exists(child) or psutil.Process(child).status() == "zombie"


def test_fit_with_a_small_budget_still_lets_the_optimiser_propose():
    """``cropcraft fit --evals 100`` clipped the 200 initial evaluations to 100: every one was
    random, a random search under the name bo. A smaller budget keeps the paper's 40 % initial
    share; an explicit --initial above --evals is refused, as the scene flow refuses it."""
    from cropcraft_core.errors import ConfigError
    from flows.cli import _fit_config, build_parser

    def cfg(*extra):
        argv = ["fit", "soybean", "--geometry", "g.ply", "--out", "o", *extra]
        return _fit_config(build_parser().parse_args(argv))

    assert (cfg().n_evals, cfg().n_initial) == (500, 200)
    assert cfg("--evals", "100").n_initial == 40
    assert cfg("--evals", "100", "--initial", "30").n_initial == 30
    with pytest.raises(ConfigError, match="n_initial"):
        cfg("--evals", "100", "--initial", "200")


@pytest.mark.parametrize(
    "extra,message",
    [
        (["--set", "fit.nope=1"], "unknown setting 'fit.nope'"),
        (["--runner", "bogus"], "bogus"),
    ],
)
def test_demo_names_bad_options_before_it_makes_its_scene(tmp_path, capsys, extra, message):
    """The demo made and stored its 50-photo scene (~50 s) before it read its options; a bad
    runner on a cached demo was never read at all."""
    store = tmp_path / "store"
    assert main(["demo", "--store", str(store), *extra]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("cropcraft: error:") and message in err
    assert not any(p.is_file() for p in store.rglob("*") if "images" in p.parts)


def test_run_names_a_prefect_server_that_does_not_answer(tmp_path, capsys):
    """README has users export PREFECT_API_URL; with that server stopped (or the URL
    mistyped) a run gave three tracebacks from inside the flow's start, not one line."""
    from PIL import Image
    from prefect.settings import PREFECT_API_URL, temporary_settings

    photos = tmp_path / "photos"
    photos.mkdir()
    for i in range(3):
        Image.new("RGB", (32, 24), (40 * i, 90, 30)).save(photos / f"p{i}.png")
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]  # closed again: nothing listens there
    argv = ["run", "plotA/soybean/2024-07-01", "--images", str(photos)]
    with temporary_settings({PREFECT_API_URL: f"http://127.0.0.1:{port}/api"}):
        assert main([*argv, "--store", str(tmp_path / "store")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("cropcraft: error: the Prefect server at PREFECT_API_URL=")
    assert "Traceback" not in err and "\n" not in err


def test_status_of_a_mistyped_store_or_scene_says_so_and_writes_nothing(tmp_path, capsys):
    """``status`` created a mistyped store's folder (and wrote a probe into it), and listed a
    scene never run as every stage "pending" with exit 0, as if it were waiting."""
    typo = tmp_path / "stor_typo"
    assert main(["status", "plotA/soybean/2024-07-01", "--store", str(typo)]) == 2
    assert "no store at" in capsys.readouterr().err and not typo.exists()
    (tmp_path / "store").mkdir()
    assert main(["status", "plotA/soybean/2024-07-01", "--store", str(tmp_path / "store")]) == 1
    assert "no run recorded for plotA/soybean/2024-07-01" in capsys.readouterr().err
    assert list((tmp_path / "store").iterdir()) == []


def test_a_refused_run_leaves_no_store_folder_it_made(tmp_path, capsys):
    """Too few photos (or a bad known.json) are refused before any work, but connecting had
    already made the new store's folders; an existing store keeps its folder as it was."""
    from PIL import Image

    photos = tmp_path / "photos"
    photos.mkdir()
    for i in range(2):
        Image.new("RGB", (32, 24), (i * 90, 120, 60)).save(photos / f"p{i}.jpg")
    new = tmp_path / "new" / "store"
    argv = ["run", "plotA/soybean/2024-07-01", "--images", str(photos), "--store", str(new)]
    assert main(argv) == 2
    assert "holds 2 JPEG/PNG photo(s); at least 3 are needed" in capsys.readouterr().err
    assert not (tmp_path / "new").exists()
    old = tmp_path / "old"
    old.mkdir()
    assert main([*argv[:-1], str(old)]) == 2
    assert old.is_dir() and list(old.iterdir()) == []


def test_status_says_the_cache_is_unknown_when_the_last_runs_photos_have_moved(tmp_path, capsys):
    """Every stage read "cached no" once the photos the last run read had moved, as if its
    results were lost; a rerun from their new place is served from the cache."""
    from cropcraft_core.store import SceneKey, SceneStore

    store = SceneStore(str(tmp_path / "store"))
    scene = SceneKey("plotA", "soybean", "2024-07-01")
    gone = str(tmp_path / "moved-away")
    store.init_manifest(scene, {"images/a.png": "1"}, {}, sources={"images": gone, "poses": None})
    assert main(["status", scene.prefix, "--store", str(tmp_path / "store")]) == 0
    out = capsys.readouterr().out
    assert "ingest       pending     ?" in out
    assert "cached ?: the photos or poses the last run read cannot be read now" in out


def test_status_writes_nothing_to_the_store(tmp_path, capsys):
    """``status`` probed the store with a write (connect's reachability check): on a full or
    read-only store, the very case that made a night fail, it said the photos had moved, and
    on any store it wrote and removed an object each call (session 94's disk audit)."""
    from cropcraft_core.store import SceneKey, SceneStore

    photos = tmp_path / "photos"
    photos.mkdir()
    for name in ("a.png", "b.png", "c.png"):
        (photos / name).write_bytes(b"a photo")
    store = SceneStore(str(tmp_path / "store"))
    scene = SceneKey("plotA", "soybean", "2024-07-01")
    store.init_manifest(scene, {}, {}, sources={"images": str(photos), "poses": None})
    store.update_stage(scene, "ingest", status="running")
    store.update_stage(scene, "ingest", status="done")
    root = tmp_path / "store"
    before = root.stat().st_mtime_ns
    time.sleep(0.01)
    assert main(["status", scene.prefix, "--store", str(root)]) == 0
    assert "cannot be read now" not in capsys.readouterr().out
    assert root.stat().st_mtime_ns == before  # no probe made and removed there


def test_a_full_disk_or_read_only_store_is_named_as_such():
    """A full disk's and a read-only file system's errors ended "check the store URI, endpoint,
    credentials and permissions", which sent users the wrong way (session 94's disk audit)."""
    import errno

    from cropcraft_core.store import SceneStore, StoreError, disk_hint

    store = SceneStore("memory://full")
    for code, said in ((errno.ENOSPC, "is full: free space"), (errno.EROFS, "read-only")):
        with pytest.raises(StoreError, match=said) as err:
            with store._io("write", "plotA/x.bin", reading=False):
                raise OSError(code, os.strerror(code))
        assert "credentials" not in str(err.value)
    wrapped = RuntimeError("flow failed")
    wrapped.__cause__ = OSError(errno.ENOSPC, "No space left on device")
    assert "is full" in disk_hint(wrapped)
    assert disk_hint(OSError(errno.EACCES, "Permission denied")) is None


def test_a_full_disk_under_prefects_database_is_one_line(tmp_path, monkeypatch, capsys):
    """On a worker whose disk is full, the temporary Prefect server's database cannot be
    written: the run ended in pages of the server's tracebacks and "500 Internal Server Error",
    exit 1, the disk never named (session 94's disk audit). It is refused before the run, and
    an error the full disk causes mid-run is one line. (Here the threshold is raised above the
    disk's free space: a real disk filled to the brim is the audit's.)"""
    import errno

    import httpx
    from prefect.exceptions import PrefectHTTPStatusError

    from flows import service_cli
    from flows.cli import disk_full_line

    monkeypatch.delenv("PREFECT_API_URL", raising=False)
    monkeypatch.setattr(service_cli, "PREFECT_HOME_MIN_FREE", 1 << 62)
    photos = tmp_path / "photos"
    photos.mkdir()
    for name in ("a.png", "b.png", "c.png"):
        (photos / name).write_bytes(b"not decoded before the run")
    code = main(["run", "plotA/soybean/2024-07-01", "--store", str(tmp_path / "s"),
                 "--images", str(photos)])  # fmt: skip
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1
    assert "the disk holding Prefect's database" in err and "PREFECT_HOME" in err
    request = httpx.Request("POST", "http://127.0.0.1:8986/api/flow_runs/")
    response = httpx.Response(500, request=request, json={"exception_message": "Internal"})
    failed = PrefectHTTPStatusError.from_httpx_error(
        httpx.HTTPStatusError("Server error '500 Internal Server Error'", request=request,
                              response=response)
    )  # fmt: skip
    assert "PREFECT_HOME" in disk_full_line(failed)
    wrapped = RuntimeError("a seed failed")
    wrapped.__context__ = OSError(errno.ENOSPC, "No space left on device")
    assert disk_full_line(wrapped).endswith("is full: free space there, then run again")
    assert disk_full_line(RuntimeError("something else")) is None


def test_run_prints_a_named_errors_record_without_prefects_traceback():
    """During a run the console prints a named error's record (a corrupt photo, a failed SfM)
    as its one line: Prefect's ~90 lines of its own frames came before the command's one-line
    error. A defect's record keeps its traceback, and so does every record after the run; the
    workers the run spawns are told to do the same."""
    import logging
    import os
    import sys

    from prefect import flow  # noqa: F401 - Prefect sets its console up on loading (alone: here)
    from prefect.logging.handlers import PrefectConsoleHandler

    from cropcraft_core.errors import InputError
    from flows.runners import ONE_LINE_ERRORS_ENV
    from flows.service_cli import run_progress

    console = [h for h in logging.getLogger().handlers if isinstance(h, PrefectConsoleHandler)]
    assert console, "Prefect configured no console handler"

    def printed(exc: Exception) -> list[str]:
        try:
            raise exc
        except Exception:
            info = sys.exc_info()
        record = logging.LogRecord(
            "prefect.task_runs", logging.ERROR, __file__, 1, "failed", (), info
        )
        record.task_run_name = "ingest-0"
        return [h.format(record) for h in console]

    assert ONE_LINE_ERRORS_ENV not in os.environ
    with run_progress(bar=False):
        assert os.environ[ONE_LINE_ERRORS_ENV] == "1"
        named = printed(InputError("image a.jpg cannot be decoded"))
        defect = printed(KeyError("a defect"))
    assert named and all("Traceback" not in text and text.endswith("failed") for text in named)
    assert all("Traceback" in text and "KeyError: 'a defect'" in text for text in defect)
    assert all("Traceback" in text for text in printed(InputError("after the run")))
    assert ONE_LINE_ERRORS_ENV not in os.environ


def test_run_of_a_busy_scene_or_a_corrupt_photo_ends_in_its_one_line_error(tmp_path):
    """`cropcraft run` in a fresh process: a scene another run holds is refused in one line
    before Prefect starts (it printed Prefect's start, a failed flow run and 31 lines of
    traceback); a truncated photo stops the ingest task, and the console names it without a
    traceback from the task's worker process or the flow."""
    import os
    import subprocess
    import sys

    import numpy as np
    from PIL import Image

    from cropcraft_core.lease import hold_scene
    from cropcraft_core.store import SceneKey, SceneStore

    photos = tmp_path / "photos"
    photos.mkdir()
    rng = np.random.default_rng(0)
    for i in range(4):
        pixels = rng.integers(0, 256, (48, 64, 3), dtype=np.uint8)
        Image.fromarray(pixels).save(photos / f"p{i}.jpg", quality=90)
    whole = (photos / "p2.jpg").read_bytes()
    (photos / "p2.jpg").write_bytes(whole[: len(whole) // 2])
    store = tmp_path / "store"
    env = {**os.environ, "PREFECT_LOGGING_LEVEL": "INFO"}
    env.pop("PREFECT_API_URL", None)  # a temporary server, as a user's first run has

    def run() -> subprocess.CompletedProcess:
        argv = ["run", "plotA/soybean/2024-07-01", "--images", str(photos), "--store", str(store)]
        code = f"import sys; from flows.cli import main; sys.exit(main({argv!r}))"
        return subprocess.run(
            [sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=600
        )

    with hold_scene(SceneStore(str(store)), SceneKey("plotA", "soybean", "2024-07-01"), "nightly"):
        busy = run()
    assert busy.returncode == 2
    assert len(busy.stderr.strip().splitlines()) == 1, busy.stderr  # no temporary server started
    assert busy.stderr.startswith(
        "cropcraft: error: scene plotA/soybean/2024-07-01 is being run by nightly"
    )

    corrupt = run()
    assert corrupt.returncode == 2, corrupt.stderr
    lines = corrupt.stderr.strip().splitlines()
    assert "Traceback" not in corrupt.stderr, corrupt.stderr
    assert any("Task run 'ingest" in line and "p2.jpg cannot be decoded" in line for line in lines)
    assert any(line.startswith("cropcraft: error: image p2.jpg cannot be") for line in lines)


def test_season_without_its_crop_asks_for_site_and_crop(tmp_path, capsys):
    """``cropcraft season plotA`` answered "unknown crop ''" (session 91's season audit)."""
    from flows.cli import main

    for bad in ("plotA", "plotA/", "plotA/soybean/2024-07-01"):
        assert main(["season", bad, "--store", str(tmp_path / "s")]) == 2
        err = capsys.readouterr().err
        assert f"season expects SITE/CROP (e.g. plotA/soybean), got '{bad}'" in err


def test_status_of_a_scene_whose_run_record_is_unreadable_says_so(tmp_path, capsys):
    """A finished scene whose manifest.json was damaged read as "no run recorded" (session
    91's crash audit), though its results are all there and the next run serves them."""
    from flows.cli import main

    folder = tmp_path / "store" / "plotA" / "soybean" / "2024-07-01"
    folder.mkdir(parents=True)
    (folder / "manifest.json").write_text("not json {")
    assert main(["status", "plotA/soybean/2024-07-01", "--store", str(tmp_path / "store")]) == 1
    err = capsys.readouterr().err
    assert "manifest.json is not a valid manifest" in err and "no run recorded" not in err
    assert "the next run sets the record aside and serves what is cached" in err


def test_a_param_over_the_field_notes_is_said():
    """``--param leaf_length=1`` replaced known.json's measured 0.9 with no word anywhere
    (session 91's maize season audit): the run and the season say so."""
    from flows.scene import notes_overridden

    known = {"num_nodes": 9, "leaf_length": 0.9}
    assert notes_overridden(known, {"fit.box.leaf_length": 1.0}) == [
        "--param leaf_length=1 goes over known.json's 0.9"
    ]
    assert notes_overridden(known, {"fit": {"box": {"num_nodes": [8.0, 11.0]}}}) == [
        "--param num_nodes=8:11 goes over known.json's 9"
    ]
    assert notes_overridden(known, {"fit.box.num_nodes": 9.0, "fit.n_evals": 20}) == []
