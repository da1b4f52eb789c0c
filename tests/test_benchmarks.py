"""The benchmarks' command lines: bad values stop a run before any work, results are strict
JSON, and comparisons run every arm on the same objective."""

from __future__ import annotations

import json
import math
import sys

import numpy as np
import pytest

from benchmarks.options import at_least, output_file, positive, seeds_by_evals, write_json
from flows.cli import main


def test_option_types_name_the_bad_value(tmp_path):
    import argparse

    assert at_least(1)("3") == 3
    assert seeds_by_evals("10X500") == "10x500"
    assert positive("0.25") == 0.25
    assert output_file(str(tmp_path / "x.json")) == str(tmp_path / "x.json")
    for parse, text, match in (
        (at_least(1), "0", "0 is below 1"),
        (at_least(0), "abc", "not a whole number"),
        (positive, "0", "not a finite number > 0"),
        (positive, "nan", "not a finite number > 0"),
        (seeds_by_evals, "10", "not SEEDSxEVALS"),
        (seeds_by_evals, "0x500", "at least 1 seed of 5 evaluations"),
        (output_file, str(tmp_path / "missing" / "x.json"), "does not exist"),
        (output_file, str(tmp_path), "is a folder"),
    ):
        with pytest.raises(argparse.ArgumentTypeError, match=match):
            parse(text)


def test_json_results_are_strict_json(tmp_path):
    """NaN (a per-iteration time a short run has not reached, an empty view's score) is
    written as null: Python's json.dump would write NaN, which strict parsers refuse."""
    p = write_json(tmp_path / "r.json", {"a": math.nan, "b": [np.float64(1.5), np.inf], "c": 2})

    def refuse(c):
        raise ValueError(c)

    assert json.loads(p.read_text(), parse_constant=refuse) == {"a": None, "b": [1.5, None], "c": 2}
    assert [q.name for q in tmp_path.iterdir()] == ["r.json"]


@pytest.mark.parametrize(
    "argv, message",
    [
        (["accuracy", "--crop", "soybean", "--scenes", "0"], "argument --scenes: 0 is below 1"),
        (["accuracy", "--crop", "soybean", "--image-scale", "0"], "argument --image-scale"),
        (["accuracy", "--crop", "soybean", "--json", "/nonexistent/x.json"], "does not exist"),
        (["accuracy", "--crop", "soybean", "--seeds", "0"], "argument --seeds: 0 is below 1"),
        (["rows", "--crop", "soybean", "--budget", "10"], "not SEEDSxEVALS"),
        (["rows", "--crop", "soybean", "--scenes", "-1"], "argument --scenes"),
        (["optimizer", "--methods", "random,foo"], "unknown method(s) foo"),
        (["optimizer", "--n", "10", "--n-initial", "20"], "--n-initial 20 exceeds --n 10"),
        (["pipeline", "--fit", "10"], "not SEEDSxEVALS"),
        (["accuracy", "--crop", "soybean", "--methods", "random,bogus"], "unknown method(s) bogus"),
        (["accuracy", "--crop", "soybean", "--methods", ","], "no method"),
        (["accuracy", "--crop", "soybean", "--runner", "threads", "--methods", "mlp"], "mlp"),
        (["pipeline", "--surfaces", "bogus=1"], "unexpected keyword argument 'bogus'"),
        (["pipeline", "--sfm", "bogus=1"], "--sfm bogus: not a setting of run_sfm"),
        (["pipeline", "--bbox", "[1, 2]"], "surfaces bbox must be"),
        (["pipeline", "--prediction-blur", "-1"], "prediction blur must be"),
        (["fit-speed", "--initial", "30", "--evals", "20"], "--initial 30 exceeds --evals 20"),
        (["fit-speed", "--arms", "ours,nope"], "unknown arm(s) ['nope']"),
        (["fit-speed", "--arms", "ours+local"], "--arms ours+local needs --local-share"),
        (["fit-speed", "--local-share", "1.5"], "--local-share must be between 0 and 1"),
        # session 93's bench audit: tracebacks, work done first, a wrong exit status
        (["optimizer", "--load", "/nonexistent/o.json"], "/nonexistent/o.json: no such file"),
        (["optimizer", "--load", sys.executable], "not a JSON file"),
        (["optimizer", "--noise-sd", "-1"], "-1 is not a finite number >= 0"),
        (["optimizer", "--methods", "skopt", "--skopt-seeds", "0"], "no method to run"),
        (["draws", "a/soybean/2024-07-01", "--truth", sys.executable], "not a JSON file"),
        (["accuracy", "--crop", "soybean", "--checkpoint-dir", sys.executable], "is a file"),
        (["rows", "--crop", "soybean", "--checkpoint-dir", sys.executable], "is a file"),
        (["accuracy", "--crop", "soybean", "--known", "foo"], "--known foo: not a soybean"),
        (["accuracy", "--crop", "soybean", "--preset", "foo=1"], "preset setting 'foo'"),
        (["nerfacto", "train", "--scene-dir", "/nonexistent", "--out", "x"], "no such folder"),
        (["nerfacto", "compare", "--scene-dir", sys.prefix, "--kept", "x"], "holds no scene.json"),
        (["fit-speed", "--skip-full", "--skopt-seeds", "0"], "leaves nothing to run"),
    ],
)
def test_bad_benchmark_options_stop_before_any_work(argv, message, capsys):
    with pytest.raises(SystemExit) as e:
        main(["bench", *argv])
    assert e.value.code == 2
    assert message in capsys.readouterr().err


def test_accuracy_with_a_runner_refuses_the_options_it_cannot_honour(capsys):
    for extra in (["--checkpoint-dir", "x"], ["--crn-ablation"], ["--draw", "1"]):
        with pytest.raises(SystemExit) as e:
            main(["bench", "accuracy", "--crop", "soybean", "--runner", "threads", *extra])
        assert e.value.code == 2
        assert "not available with --runner" in capsys.readouterr().err


def test_fit_speed_compares_skopt_on_the_objective_fit_seed_optimises(monkeypatch):
    """(b)'s scikit-optimize arm gets fit_seed's own objective (soybean: two canopies an
    evaluation, the same box), so the best losses compare like for like."""
    import benchmarks.bench_fit_speed as fs
    import cropcraft_core.optimize.skopt_reference as ref
    from cropcraft_core.fit import FitConfig
    from cropcraft_core.fit.fitting import seed_objective

    got = {}
    keep = ref.run_skopt

    def spy(objective, bounds, **kw):
        got["r"], got["bounds"] = keep(objective, bounds, **kw), np.asarray(bounds)
        return got["r"]

    monkeypatch.setattr(ref, "run_skopt", spy)
    method, row = fs._compare_one(("skopt", 1, 7, 6, None))
    assert method == "skopt" and math.isfinite(row["best"])
    obj, box, _ = seed_objective(fs._observation(), 1, FitConfig(n_evals=7, n_initial=6))
    np.testing.assert_array_equal(got["bounds"], box.bounds)
    assert [obj(x, i) for i, x in enumerate(got["r"].X)] == got["r"].y.tolist()


def test_fit_speed_runs_the_seeds_asked_for(tmp_path, capsys):
    """``--skopt-first`` numbers (b)'s seeds from K, so the five ~40-minute scikit-optimize
    seeds can be run over several sittings and joined seed by seed."""
    out = tmp_path / "fs.json"
    argv = ["--skip-full", "--skopt-first", "3", "--skopt-seeds", "1", "--evals", "7"]
    main(["bench", "fit-speed", *argv, "--initial", "6", "--workers", "1", "--json", str(out)])
    got = json.loads(out.read_text())
    rows = got["compare"]
    assert {k: [r["seed"] for r in v] for k, v in rows.items()} == {"ours": [3], "skopt": [3]}
    printed = capsys.readouterr().out
    assert "mean of 1 (seeds 3–3)" in printed
    # both halves of the target judged (it printed the time's alone, the loss's never)
    low = rows["ours"][0]["best"] <= rows["skopt"][0]["best"]
    verdict = got["verdict"]["ours"]
    assert verdict["loss_vs_skopt"] == pytest.approx(
        rows["ours"][0]["best"] / rows["skopt"][0]["best"] - 1.0
    )
    assert verdict["met"] == (low and verdict["time_ratio"] >= 10.0)
    assert f"(target ≤: {'yes' if low else 'NO'})" in printed
    with pytest.raises(SystemExit) as err:  # nothing to run: it exited 0 having done nothing
        main(["bench", "fit-speed", "--skip-full", "--skopt-seeds", "0"])
    assert err.value.code == 2
    assert "leaves nothing to run" in capsys.readouterr().err


def test_fit_speed_local_share_adds_an_arm_and_arms_choose_which_run(tmp_path, capsys, monkeypatch):
    """``--local-share`` adds ``ours+local`` (our optimiser with its closing local search), and
    ``--arms`` leaves out an arm measured in an earlier sitting (scikit-optimize's, the long
    one), so the run prints no time ratio it has no scikit-optimize arm for."""
    import benchmarks.bench_fit_speed as bench_fit_speed

    out = tmp_path / "fs.json"
    argv = ["--skip-full", "--skopt-seeds", "1", "--evals", "10", "--initial", "6"]
    argv += ["--workers", "1", "--local-share", "0.4", "--arms", "ours,ours+local"]
    written = []
    keep = bench_fit_speed.write_json

    def spy(path, data):  # every write of the JSON file, as its reader would find it
        written.append(json.loads(json.dumps(data, default=float)))
        return keep(path, data)

    monkeypatch.setattr(bench_fit_speed, "write_json", spy)
    main(["bench", "fit-speed", *argv, "--json", str(out)])
    # a row at a time (a stopped run keeps the rows it finished), complete only at the end
    assert [(len(w["compare"]["ours"]), len(w["compare"]["ours+local"])) for w in written] == [
        (1, 0),
        (1, 1),
        (1, 1),
    ]
    assert [w["complete"] for w in written] == [False, False, True]
    got = json.loads(out.read_text())
    assert {k: [r["seed"] for r in v] for k, v in got["compare"].items()} == {
        "ours": [0],
        "ours+local": [0],
    }
    assert got["local_share"] == 0.4
    assert [got["compare"][k][0]["local_evals"] for k in ("ours", "ours+local")] == [0, 4]
    printed = capsys.readouterr().out
    assert "ours+local" in printed and "ratio" not in printed


def test_a_reused_scene_is_scored_on_its_own_layout_and_needs_its_true_traits_to_fit(
    tmp_path, capsys
):
    """``bench pipeline``/``nerfacto train`` took the crop's default layout for a reused scene
    made with another (``cropcraft synth --row-spacing``): the row fit's known spacing, the
    true rows and the fitted canopy were of rows the scene does not have. And ``--fit`` on a
    scene without ``truth/metrics.json`` (``bench surfaces`` makes them so) failed after the
    whole fit."""
    import dataclasses

    from benchmarks.bench_pipeline import scene_layout
    from cropcraft_core.config import default_layout

    narrow = dataclasses.replace(default_layout("soybean"), row_spacing=0.38)
    (tmp_path / "scene.json").write_text(
        json.dumps({"crop": "soybean", "layout": narrow.to_dict()})
    )
    assert scene_layout(tmp_path, "soybean") == narrow
    assert scene_layout(tmp_path / "none", "maize") == default_layout("maize")
    with pytest.raises(SystemExit, match=r"truth/metrics\.json is missing"):
        main(["bench", "pipeline", "--scene-dir", str(tmp_path), "--fit", "1x5"])


def test_bench_surfaces_checks_its_settings_first_and_keeps_no_scene(tmp_path, monkeypatch, capsys):
    """``bench surfaces --set foo=1`` rendered its 50-view scene (41 s) and then ended in a
    traceback; every run left its scene (74 MB) in the temporary folder (session 93's bench
    audit). A bad setting is refused in one line first, and a run's own scene goes with it;
    the run prints its verdict against the L1 target."""
    import tempfile

    monkeypatch.setenv("TMPDIR", str(tmp_path))
    monkeypatch.setattr(tempfile, "tempdir", None)  # re-read TMPDIR
    for bad, said in (
        ("foo=1", "--set foo: not a setting of the surfaces"),
        ("backend=bogus", "unknown surfaces backend 'bogus'"),
        ("voxel_size=-1", "voxel_size must be a positive number"),
    ):
        with pytest.raises(SystemExit) as err:
            main(["bench", "surfaces", "--set", bad])
        assert err.value.code == 2 and said in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []
    assert (
        main(
            ["bench", "surfaces", "--views", "6", "--resolution", "160x120", "--set", "n_depths=8"]
        )
        == 0
    )
    printed = capsys.readouterr().out
    assert "depth-histogram L1 against the truth" in printed and "(target <= 0.15)" in printed
    assert list(tmp_path.iterdir()) == []


def test_bench_surfaces_compares_the_stereo_at_the_default_scale():
    """``stereo_vs_truth`` compared only integer down-scales, so at the default mvs_scale 0.75
    its record was always ``{}``. Depth maps at 0.75 of a flat field seen from 1 m read
    complete and within 2 cm of the truth (the stereo's maps as a fitted backend holds them)."""
    from types import SimpleNamespace

    from benchmarks.bench_surfaces import stereo_vs_truth
    from cropcraft_core.geometry import PinholeCamera

    cam = PinholeCamera.look_down(height_m=1.0, size=(160, 120))
    small = cam.scaled(0.75)
    truth = np.ones((cam.height, cam.width))
    maps = [np.ones((small.height, small.width), np.float32)]
    fitted = SimpleNamespace(
        config=SimpleNamespace(mvs_scale=0.75), raw_depth_maps=maps, depth_maps=maps
    )
    got = stereo_vs_truth(fitted, [cam], [truth])
    assert got["raw"]["ground"] == {"complete": 1.0, "dz_lt_2cm": 1.0}
    assert got["filtered"]["ground"] == {"complete": 1.0, "dz_lt_2cm": 1.0}


def test_accuracy_table_judges_bo_against_the_papers_row(capsys):
    """The accuracy table printed the paper's row beside ours and left the reader to judge
    the target (session 93's bench audit): it now says, column by column, whether BO beats
    the paper's row and holds median LAIPE to 0.10."""
    from benchmarks.bench_accuracy import COLUMNS, print_table

    def res(laie: float) -> dict:
        errors = dict.fromkeys(COLUMNS, 0.01) | {"LAIE": laie, "LAIPE_median": 0.03}
        bo = {"errors": errors, "seconds_per_scene": 1.0}
        return {"crop": "maize", "scenes": 2, "quick": True, "methods": {"bo": bo}}

    print_table(res(0.288))
    printed = capsys.readouterr().out
    assert "LAIE 0.288 NOT < 0.13; NDPE 0.010 < 0.05; NCPE 0.010 < 0.08" in printed
    assert "median LAIPE 0.030 <= 0.10: NOT met" in printed
    print_table(res(0.12))
    printed = capsys.readouterr().out
    assert "LAIE 0.120 < 0.13" in printed and "median LAIPE 0.030 <= 0.10: met" in printed


def test_a_smaller_evaluation_budget_takes_the_fits_share_of_random_points():
    """``bench accuracy --evals N`` reads N as ``fit --evals N`` does: 40 % random (the
    paper's 200 of 500), not a fixed 200 (or --quick's 25) that refused every N below it."""
    from benchmarks.bench_accuracy import budget

    assert budget(False, 1, "bo", overrides={"n_evals": 100}).fit.n_initial == 40
    assert budget(True, 1, "bo", overrides={"n_evals": 20}).fit.n_initial == 8
    assert budget(True, 1, "bo").fit.n_initial == 25  # --quick's own budget as it was
    assert budget(False, 1, "bo").fit.n_initial == 200
    given = {"n_evals": 100, "n_initial": 10}
    assert budget(False, 1, "bo", overrides=given).fit.n_initial == 10
