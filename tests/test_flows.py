"""The scene flow under Prefect's test harness, on a small synthetic scene, with real
components: the cache (a rerun executes nothing), a late config change, a fault in one mapped
seed and its resume, the store and results on a real S3-compatible server (moto), the Dask
runner on a 2-worker local cluster and the processes runner, and named errors for bad input
before any work starts.

The harness (a temporary Prefect server and database, ~20 s) starts once per session with a
temporary PREFECT_HOME and local result storage. The scene is computed once (module fixture
``base_run``); the other tests reuse its upstream stages through the cache, which is the point.
"""

from __future__ import annotations

import io
import json
import math
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("prefect")
pytest.importorskip("cropcraft_core.synth")
pytest.importorskip("cropcraft_core.surfaces")

from cropcraft_core.errors import ConfigError, CropCraftError, InputError  # noqa: E402
from cropcraft_core.observe import Observation, coverage_warning  # noqa: E402
from cropcraft_core.store import (  # noqa: E402
    TMP_PREFIX,
    SceneKey,
    SceneStore,
    StoreError,
    config_hash,
)
from tests.conftest_s3 import s3_server  # noqa: E402, F401

CROP = "soybean"
DATE = "2024-07-01"
N_SEEDS = 3
OVERRIDES = {
    "surfaces.bbox": [[-1.2, -1.2, -0.1], [1.2, 1.2, 1.0]],
    # fewer plane hypotheses on smaller photos than soybean's preset (96 at full size since
    # session 83): the stereo is most of every flow that reconstructs, and these tests check
    # the flow, not the preset
    "surfaces.n_depths": 64,
    "surfaces.mvs_scale": 0.75,
    "observe.image_scale": 0.25,
    "fit.n_seeds": N_SEEDS,
    "fit.n_evals": 12,
    "fit.n_initial": 6,
    # the answer rule's re-scoring and polishes at a test's size (soybean's guarded median)
    "fit.reevaluate_canopies": 2,
    "fit.polish_evals": 4,
    "metrics.gap_fraction": False,
}
N_TASKS = 11 + N_SEEDS  # eleven single stages + the mapped seeds
LATE_STAGES = ("aggregate", "generate", "metrics", "export", "report")


@pytest.fixture(scope="session")
def prefect_harness(tmp_path_factory):
    """One Prefect test server for the session, temporary PREFECT_HOME and result storage."""
    from prefect.settings import PREFECT_HOME, PREFECT_LOCAL_STORAGE_PATH, temporary_settings
    from prefect.testing.utilities import prefect_test_harness

    home = tmp_path_factory.mktemp("prefect-home")
    with temporary_settings(
        {PREFECT_HOME: str(home), PREFECT_LOCAL_STORAGE_PATH: str(home / "storage")}
    ):
        with prefect_test_harness(server_startup_timeout=90):
            yield


@pytest.fixture(scope="session")
def scene_dir(tmp_path_factory) -> Path:
    """A small synthetic soybean scene: photos, transforms.json, truth."""
    from cropcraft_core.synth import make_scene

    out = tmp_path_factory.mktemp("scene")
    make_scene(CROP, out, seed=0, views=16, resolution=(400, 300), metrics=False)
    return out


def _run(site, store, scene_dir, overrides=OVERRIDES, runner="threads", refresh=False):
    from flows.scene import run_scene

    return run_scene(
        site,
        CROP,
        DATE,
        images=str(scene_dir / "images"),
        poses=str(scene_dir / "transforms.json"),
        overrides=overrides,
        store=str(store),
        runner=runner,
        refresh=refresh,
    )


def _task_run_states(flow_run_id: str, expect: int, timeout_s: float = 60.0) -> list[str]:
    """Final state names of the task runs of one flow run, read back from the Prefect API.

    Prefect 3 reports task run states to the server through events, asynchronously: poll until
    ``expect`` task runs are there and all are final.
    """
    from prefect.client.orchestration import get_client
    from prefect.client.schemas.filters import FlowRunFilter, FlowRunFilterId
    from prefect.client.schemas.sorting import TaskRunSort

    deadline = time.monotonic() + timeout_s
    with get_client(sync_client=True) as client:
        while True:
            runs = client.read_task_runs(
                flow_run_filter=FlowRunFilter(id=FlowRunFilterId(any_=[flow_run_id])),
                sort=TaskRunSort.EXPECTED_START_TIME_DESC,
                limit=200,
            )
            states = [r.state.name if r.state else "None" for r in runs]
            final = all(r.state is not None and r.state.is_final() for r in runs)
            if (len(runs) >= expect and final) or time.monotonic() > deadline:
                return states
            time.sleep(0.5)


def _same_result(a: dict, b: dict) -> None:
    """Same fitted parameters and metrics, up to floating-point reduction order (BLAS threads
    differ between a thread pool and Dask worker processes): relative 1e-6."""
    assert a["params"] == pytest.approx(b["params"], rel=1e-6)
    for k, v in b["metrics"].items():
        assert a["metrics"][k] == (pytest.approx(v, rel=1e-6) if isinstance(v, float) else v), k


def _executed(states: dict[str, str]) -> list[str]:
    return sorted(k for k, v in states.items() if v != "Cached")


@pytest.fixture(scope="module")
def base_run(prefect_harness, scene_dir, tmp_path_factory):
    """The scene computed once from scratch, then rerun with the same inputs."""
    store = tmp_path_factory.mktemp("store-local")
    t = time.perf_counter()
    first = _run("plotA", store, scene_dir)
    t_first = time.perf_counter() - t
    t = time.perf_counter()
    second = _run("plotA", store, scene_dir)
    t_second = time.perf_counter() - t
    return {"store": store, "first": first, "second": second, "t": (t_first, t_second)}


def test_scene_flow_produces_everything(base_run):
    from cropcraft_core.config import CanopyLayout
    from cropcraft_core.metrics import canopy_metrics
    from cropcraft_core.procedural import generate_canopy

    out = base_run["first"]
    assert len(out["states"]) == N_TASKS
    assert _executed(out["states"]) == sorted(out["states"])  # all computed the first time
    m = out["metrics"]
    assert m["lai"] > 0 and math.isfinite(m["lai"])
    assert 0 < m["leaf_angle_mean_deg"] < 90
    store = SceneStore(str(base_run["store"]))
    scene = f"plotA/{CROP}/{DATE}"
    html = store.get_bytes(f"{scene}/report/report.html").decode()
    for needle in ("data:image/png;base64,", "observed", "predicted", "Stage timings", "m2"):
        assert needle in html
    # the row spacing fitted with, and that it was the crop's default (session 96)
    assert out["row_spacing"] == {"m": 0.76, "given": False}
    assert f"0.76 (the {CROP} default)" in html
    # the share of the row view without a fully supported surface, kept with the observation;
    # a fill (tsdf's one-view surface) can only have closed some of it in the rendered depth
    obs = Observation.load(io.BytesIO(store.get_bytes(f"{scene}/observe/observation.npz")))
    seen = out["observation"]["no_surface_fraction"]
    assert seen == obs.meta["no_surface_fraction"]
    assert seen > float(np.mean(~np.isfinite(obs.depth)))
    assert out["observation"]["warning"] == coverage_warning(seen)
    assert f"{100 * seen:.1f} %" in html and "row view without surface" in html
    # the paper's sharp predictions unless asked (observe.prediction_blur)
    assert obs.preset.prediction_blur_m == 0 and obs.prediction_blur_px == 0
    # the surfaces against the photos at the photos' cameras: stored with every view's shares,
    # summarised (shares of the photos' plant), in the report
    cons = store.get_json(f"{scene}/consistency/consistency.json")
    c = out["consistency"]
    assert 10 <= c["views"] == len(cons["views"]) == len(cons["per_view"]) <= 12
    assert 0 < c["photo_plant"] < 1 and 0 <= c["unreconstructed"] <= 1 and c["extra"] >= 0
    assert c["net"] == pytest.approx(c["extra"] - c["unreconstructed"]) == cons["net"]
    assert (c["warning"] is not None) == (abs(c["net"]) >= 0.15)
    assert f"surfaces against {c['views']} photos" in html and f"{100 * c['net']:+.1f} %" in html
    for name in ("canopy.ply", "canopy.glb", "canopy.helios.xml", "preview.png", "metrics.json"):
        assert store.isfile(f"{scene}/export/bundle/{name}")
    # every seed's answer measured on the answer's plants, beside the answer
    metrics = store.get_json(f"{scene}/metrics/metrics.json")
    fit = store.get_json(f"{scene}/fit/fit.json")
    recipe = store.get_json(f"{scene}/generate/canopy.json")
    seeds = metrics["seeds"]
    assert seeds["n_seeds"] == N_SEEDS == len(fit["seed_params"])
    lai = seeds["traits"]["lai"]["values"]
    assert len(lai) == N_SEEDS and all(v > 0 for v in lai)
    assert m["lai_seeds_min"] == metrics["lai_seeds_min"] == min(lai)
    assert m["lai_seeds_max"] == metrics["lai_seeds_max"] == max(lai)
    last = generate_canopy(
        CROP, fit["seed_params"][-1], CanopyLayout(**recipe["layout"]), seed=recipe["seed"]
    )
    assert lai[-1] == canopy_metrics(last, gap_fraction=False)["lai"]
    assert "Traits over the 3 seeds' answers" in html
    assert "seeds" in store.get_json(f"{scene}/export/bundle/metrics.json")
    manifest = store.load_manifest(SceneKey.parse(scene))
    assert all(manifest.stages[s].status == "done" for s in ("ingest", "report", "fit_seed"))
    # every stage says which numeric libraries computed it; the report names the fit's
    for rec in manifest.stages.values():
        assert rec.environment["numpy"] == np.__version__
    assert f"numpy {np.__version__}" in html and "libraries (fit)" in html
    # no arrays in any record that went through Prefect
    assert len(repr(out)) < 20_000


def _artifacts(key: str) -> list:
    """The Prefect artifacts under ``key``, newest first, read back from the API."""
    from prefect.client.orchestration import get_client
    from prefect.client.schemas.filters import ArtifactFilter, ArtifactFilterKey
    from prefect.client.schemas.sorting import ArtifactSort

    with get_client(sync_client=True) as client:
        return client.read_artifacts(
            artifact_filter=ArtifactFilter(key=ArtifactFilterKey(any_=[key])),
            sort=ArtifactSort.CREATED_DESC,
        )


def test_a_scene_run_shows_its_results_in_the_prefect_ui(base_run):
    """The UI showed a finished scene run's state and logs only (its result is not
    persisted): the run now publishes a markdown artifact under its plot's key, linked to its
    flow run, with the traits and their units, the report's warnings and where the files are."""
    from flows.artifacts import artifact_key

    out = base_run["first"]
    key = artifact_key("plotA", CROP, "scene")
    assert key.startswith("plota-") and key.endswith(f"-{CROP}-scene")
    found = [a for a in _artifacts(key) if str(a.flow_run_id) == out["flow_run_id"]]
    assert len(found) == 1, found
    md = found[0].data
    assert md.startswith(f"# plotA/{CROP}/{DATE}\n")
    assert f"| lai | {out['metrics']['lai']:.4g} | m2/m2" in md
    assert f"| num_nodes | {out['params']['num_nodes']:.4g} |" in md
    assert f"{N_SEEDS} fit seeds" in md and out["report"] in md and out["bundle"] in md
    store = SceneStore(str(base_run["store"]))
    for warning in store.get_json(f"plotA/{CROP}/{DATE}/report/warnings.json"):
        assert warning.replace("|", "\\|") in md


def test_artifact_keys_keep_prefects_alphabet_and_plots_apart():
    from flows.artifacts import MAX_KEY, artifact_key, season_table

    assert artifact_key("plota", "soybean", "scene") == "plota-soybean-scene"
    sites = ("PlotA", "plota", "plot_a", "plot.a", "plot-a")
    keys = {artifact_key(s, "maize", "season") for s in sites}
    assert len(keys) == 5
    long = artifact_key("x" * 200, "soybean", "season")
    assert len(long) <= MAX_KEY and long != artifact_key("x" * 199, "soybean", "season")
    for k in keys | {long}:
        assert all(c.isdigit() or c == "-" or "a" <= c <= "z" for c in k), k
    # the season's table: NaN (JSON has none) as an empty cell
    assert season_table([{"date": "2024-07-01", "lai_m2_m2": math.nan, "note": ""}]) == [
        {"date": "2024-07-01", "lai_m2_m2": None, "note": ""}
    ]


def test_a_run_sweeps_its_scenes_temporaries_whatever_their_age(base_run, scene_dir):
    """A run killed mid-write left a temporary object; a rerun within the hour kept it (only
    those an hour old were swept), and once that rerun finished the scene nothing ran its flow
    again: kept for good, a whole artefact's size (session 94's store audit). A run holding
    the scene now sweeps them all before its first write."""
    store = SceneStore(str(base_run["store"]))
    young = f"plotA/{CROP}/{DATE}/surfaces/{TMP_PREFIX}killed-surface.ply"
    store.fs.pipe_file(store._full(young), b"a whole surface")
    out = _run("plotA", base_run["store"], scene_dir, {**OVERRIDES, "metrics.seed_traits": False})
    assert "metrics" in _executed(out["states"])
    assert not store.fs.exists(store._full(young))
    _run("plotA", base_run["store"], scene_dir)  # back to the default for the tests after


def test_the_seeds_traits_can_be_left_out(base_run, scene_dir):
    """``metrics.seed_traits=false``: metrics.json without the seeds' traits, only the
    metrics stage and what follows it recomputed; a setting that is no boolean is named."""
    out = _run("plotA", base_run["store"], scene_dir, {**OVERRIDES, "metrics.seed_traits": False})
    assert _executed(out["states"]) == ["export", "metrics", "report"]
    store = SceneStore(str(base_run["store"]))
    assert "seeds" not in store.get_json(f"plotA/{CROP}/{DATE}/metrics/metrics.json")
    assert "lai_seeds_min" not in out["metrics"]
    assert out["metrics"]["lai"] == base_run["first"]["metrics"]["lai"]
    with pytest.raises(ConfigError, match="metrics.seed_traits must be true or false"):
        _cached(base_run["store"], scene_dir, {**OVERRIDES, "metrics.seed_traits": "no"})
    _run("plotA", base_run["store"], scene_dir)  # back to the default for the tests after


def test_season_summary_carries_each_dates_row_view_coverage(base_run):
    """The season summary lists the scene, run from photos outside the store (no inbox), with
    its share of the row view without a reconstructed surface beside its traits."""
    from flows.season import write_summary

    store = SceneStore(str(base_run["store"]))
    season = write_summary(store, "plotA", CROP)
    (row,) = season["rows"]
    out = base_run["first"]
    assert row["date"] == DATE
    assert row["row_view_no_surface_fraction"] == pytest.approx(
        out["observation"]["no_surface_fraction"]
    )
    assert row["lai_m2_m2"] == pytest.approx(out["metrics"]["lai"])
    assert row["parameters_given"] == ""  # the whole box was searched
    assert row["scale_source"] == out["scale_source"] == "metric_poses"  # session 96
    import csv

    text = store.get_bytes(f"plotA/{CROP}/season/summary.csv").decode()
    head, line = csv.reader(text.splitlines())
    assert row["photo_net_cover_fraction"] == pytest.approx(out["consistency"]["net"])
    assert head[-9:] == [
        "row_view_no_surface_fraction",
        "photo_net_cover_fraction",
        "rows_fitted",
        "lai_rows_min_m2_m2",
        "lai_rows_max_m2_m2",
        "lai_seeds_min_m2_m2",
        "lai_seeds_max_m2_m2",
        "status",
        "note",
    ]
    assert line[0] == DATE
    assert line[-7:-4] == ["", "", ""]  # fitted over its best row alone
    assert row["lai_seeds_min_m2_m2"] == out["metrics"]["lai_seeds_min"]
    assert row["lai_seeds_max_m2_m2"] == out["metrics"]["lai_seeds_max"]
    assert float(line[-3]) == pytest.approx(out["metrics"]["lai_seeds_max"], rel=1e-5)
    # its status, and the warnings its report listed (its small reconstruction's coverage)
    listed = store.get_json(f"plotA/{CROP}/{DATE}/report/warnings.json")
    assert line[-2] == "done" and line[-1] == "; ".join(listed) == row["note"]
    assert "of the row camera's view has no fully supported reconstructed surface" in line[-1]


def test_season_flow_runs_pending_dates_and_survives_a_bad_one(
    prefect_harness, scene_dir, tmp_path
):
    """The nightly deployment's flow: every date with photos in the store's inbox and no
    report is run; a date that fails (two photos: too few) does not stop the others; the
    summary holds the finished date; the next night only the failed date is pending."""
    from flows.season import pending_dates, run_season

    store = SceneStore(str(tmp_path / "store"))
    good, bad = "2024-07-08", "2024-07-15"
    photos = sorted((scene_dir / "images").iterdir())
    for p in photos:
        store.put_bytes(f"plotS/{CROP}/{good}/images/{p.name}", p.read_bytes())
    store.put_bytes(
        f"plotS/{CROP}/{good}/images/transforms.json", (scene_dir / "transforms.json").read_bytes()
    )
    for p in photos[:2]:
        store.put_bytes(f"plotS/{CROP}/{bad}/images/{p.name}", p.read_bytes())
    # a folder whose name is not a date is named, not silently skipped
    store.put_bytes(f"plotS/{CROP}/2024-7-22/images/{photos[0].name}", photos[0].read_bytes())
    # ... and so is a date whose photos were dropped beside its images/ folder, not in it
    store.put_bytes(f"plotS/{CROP}/2024-07-29/{photos[0].name}", photos[0].read_bytes())
    assert pending_dates(store, "plotS", CROP) == [good, bad]

    out = run_season("plotS", CROP, str(tmp_path / "store"), OVERRIDES)
    assert out["failed"] == [bad] and out["scenes"][good] == "Completed", out["scenes"]
    assert out["state"] == "Failed"  # the run reads Failed in the UI: its alerts fire
    # ... and its message, which they and the UI's run list show, says why (it named the date
    # only, and the result holding the reasons is not persisted: session 92's deploy audit)
    assert out["message"].startswith(f"1 of 2 date(s) failed: {bad} (invalid: ")
    assert "at least 3 are needed" in out["message"]
    # the runs are named by their scene in the UI, not by Prefect's random words
    from prefect.client.orchestration import get_client

    with get_client(sync_client=True) as client:
        names = {r.name for r in client.read_flow_runs(limit=200)}
    assert {f"plotS/{CROP}/{good}", f"plotS/{CROP} season"} <= names, names
    # ... and the season's summary is a table in the UI under the plot's key, a row a date
    from flows.artifacts import artifact_key

    table = json.loads(_artifacts(artifact_key("plotS", CROP, "season"))[0].data)
    assert [r["date"] for r in table] == [good, bad]
    assert table[0]["status"] == "done" and table[0]["lai_m2_m2"] > 0
    assert table[1]["status"] == "failed" and "at least 3 are needed" in table[1]["note"]
    assert out["misnamed"] == ["2024-7-22"] and out["astray"] == ["2024-07-29"]
    # the reason, named before the date's flow starts: its inbox holds two photos
    assert (
        out["scenes"][bad].startswith("invalid: ") and "at least 3 are needed" in out["scenes"][bad]
    )
    csv = store.get_bytes(f"plotS/{CROP}/season/summary.csv").decode().splitlines()
    assert len(csv) == 3 and csv[1].startswith(good)
    # the refused date is listed, failed, with why (it had no row: session 91's audits)
    assert csv[2].startswith(f"{bad},") and ",failed,not run: " in csv[2]
    assert "at least 3 are needed" in csv[2]
    # the finished date's warnings beside its "Completed", as its report lists them
    listed = store.get_json(f"plotS/{CROP}/{good}/report/warnings.json")
    assert out["notes"].get(good, []) == listed
    assert store.isfile(f"plotS/{CROP}/season/summary.png")
    assert store.isfile(f"plotS/{CROP}/{good}/export/bundle/canopy.helios.xml")
    assert pending_dates(store, "plotS", CROP) == [bad]
    assert out["unchanged"] == []  # nothing had finished before the night
    # field notes added after the night (known.json): the date is refitted with them
    notes = f"plotS/{CROP}/{good}/images/known.json"
    store.put_bytes(notes, b'{"num_nodes": 9}')
    assert pending_dates(store, "plotS", CROP) == [good, bad]
    store.delete(notes)
    assert pending_dates(store, "plotS", CROP) == [bad]
    # a photo uploaded after the night that finished the date: the date is pending again
    late = photos[0].with_name("late_" + photos[0].name)
    store.put_bytes(f"plotS/{CROP}/{good}/images/{late.name}", photos[0].read_bytes())
    assert pending_dates(store, "plotS", CROP) == [good, bad]


def test_a_season_on_a_store_without_the_site_says_which_store_it_read(prefect_harness, tmp_path):
    """A worker without CROPCRAFT_STORE reads its own empty folder: the run completes with
    nothing to do every night, so it warns (its log, its result), naming the store it read."""
    from flows.season import run_season

    # a store folder not there at all is a mistyped --store: refused, nothing made (it made
    # itself and a header-only summary, exit 0: session 91's CLI audit)
    with pytest.raises(InputError, match=f"no store at file://{tmp_path}/empty: check --store"):
        run_season("plotZ", CROP, str(tmp_path / "empty"), OVERRIDES)
    assert not (tmp_path / "empty").exists()
    (tmp_path / "empty").mkdir()  # there, but not the one the photos go to
    out = run_season("plotZ", CROP, str(tmp_path / "empty"), OVERRIDES)
    assert out["state"] == "Completed" and out["scenes"] == {}
    [warning] = out["warnings"]
    assert f"no dated scene in the store file://{tmp_path}/empty" in warning
    # ... and writes nothing there: it made the site's folder and an empty summary
    assert out["csv"] is None and list((tmp_path / "empty").iterdir()) == []
    # a site typed in another case (plotz for PlotZ) is named (session 94's folders audit)
    photos = SceneStore(str(tmp_path / "empty"))
    photos.put_bytes(f"PlotZ/{CROP}/{DATE}/images/a.jpg", b"a photo")
    [warning] = run_season("plotz", CROP, str(tmp_path / "empty"), OVERRIDES)["warnings"]
    assert "the store holds PlotZ, spelled otherwise" in warning
    assert sorted(p.name for p in (tmp_path / "empty").iterdir()) == ["PlotZ"]
    photos.delete("PlotZ", recursive=True)
    # a scene run ad hoc from photos kept elsewhere is a dated scene of the site: no warning
    # (it said "no dated scene" beside a summary that listed the date)
    photos.init_manifest(SceneKey("plotZ", CROP, DATE), {"images/a.png": "1"}, {})
    assert run_season("plotZ", CROP, str(tmp_path / "empty"), OVERRIDES)["warnings"] == []


def test_season_names_finished_dates_that_other_settings_answered(base_run, scene_dir):
    """The season runs only new or changed photos: a finished date run under other settings
    (the deployment's changed) keeps its answer in the summary, unmarked. The run names it,
    and says nothing where this release and these settings serve the stored results."""
    from flows.season import run_season, stale_dates

    store = SceneStore(str(base_run["store"]))
    _run("plotA", base_run["store"], scene_dir)  # whatever earlier tests left: the default
    assert stale_dates(store, "plotA", CROP, OVERRIDES) == []
    other = {**OVERRIDES, "generate.seed": 99}
    assert stale_dates(store, "plotA", CROP, other) == [DATE]
    assert stale_dates(store, "plotA", CROP, other, skip=[DATE]) == []  # run tonight anyway
    out = run_season("plotA", CROP, str(base_run["store"]), other)
    assert out["scenes"] == {}  # its photos are unchanged: not run again
    assert out["unchanged"] == [DATE]  # and the closing lines say so
    assert any("hold results that these settings" in w and DATE in w for w in out["warnings"])


def test_rerun_is_cached_everywhere(base_run):
    second = base_run["second"]
    assert set(second["states"].values()) == {"Cached"}
    api = _task_run_states(second["flow_run_id"], N_TASKS)
    assert len(api) == N_TASKS
    assert [s for s in api if s != "Cached"] == [], f"executed on rerun: {api}"
    assert second["params"] == base_run["first"]["params"]


def test_a_scene_being_run_is_not_run_again_at_the_same_time(base_run, scene_dir):
    """A second run of a scene while one holds it (the nightly season and an ad hoc run of
    the same date) is refused before it writes anything, naming the run that holds it -- here
    with other settings, which would otherwise reset the holder's stage records; once the
    first is done the same request runs."""
    from cropcraft_core.lease import hold_scene

    store = SceneStore(str(base_run["store"]))
    scene = SceneKey("plotA", CROP, DATE)
    before = store.get_bytes(f"{scene.prefix}/manifest.json")
    late = {**OVERRIDES, "fit.polish_evals": 5}
    with hold_scene(store, scene, owner="flow run nightly-plotA"):
        with pytest.raises(StoreError, match="being run by flow run nightly-plotA") as err:
            _run("plotA", base_run["store"], scene_dir, overrides=late)
        assert type(err.value).__name__ == "SceneBusyError"
        assert store.get_bytes(f"{scene.prefix}/manifest.json") == before
    again = _run("plotA", base_run["store"], scene_dir)
    assert set(again["states"].values()) == {"Cached"}


def test_bench_draws_reanswers_a_stored_fit_in_sets_of_its_seeds(base_run, tmp_path, capsys):
    """``cropcraft bench draws``: the stored seeds split into sets, each answered by each rule
    as the aggregate would: the set holding all the flow's seeds under the crop's rule is the
    flow's own answer; the store is left as it was."""
    from benchmarks import bench_draws
    from flows.cli import main as cli_main

    store = SceneStore(str(base_run["store"]))
    scene = f"plotA/{CROP}/{DATE}"
    before = {k: store.sha256(k) for k in store.list(scene)}
    truth = str(tmp_path / "metrics.json")  # a truth to compare with (the scene skips its own)
    Path(truth).write_text(json.dumps({"lai": 1.5, "node_count": 9.0}))
    whole = bench_draws.run(str(base_run["store"]), scene, N_SEEDS, ["guarded"], truth)
    [answer] = whole["answers"]["guarded"]
    assert answer["params"] == pytest.approx(base_run["first"]["params"], rel=1e-9)
    true_lai = json.loads(Path(truth).read_text())["lai"]
    assert answer["lai_error"] == pytest.approx(answer["lai"] / true_lai - 1.0)

    assert cli_main(["bench", "draws", scene, "--store", str(base_run["store"]),
                     "--set-size", "1", "--truth", truth]) == 0  # fmt: skip
    out = capsys.readouterr().out
    assert f"{N_SEEDS} stored seeds in sets of 1; true LAI {true_lai:.3f}" in out
    for rule in ("guarded", "median", "mean"):
        assert any(line.startswith(rule) for line in out.splitlines()), out
    assert "seeds 0-0" in out and f"seeds {N_SEEDS - 1}-{N_SEEDS - 1}" in out
    one = bench_draws.run(str(base_run["store"]), scene, 1, ["median", "mean"], truth)
    # one seed per set: every rule answers with that seed's own point
    for a, b in zip(one["answers"]["median"], one["answers"]["mean"], strict=True):
        assert a["params"] == pytest.approx(b["params"])
    with pytest.raises(InputError, match="3 stored seeds make no set of 4"):
        bench_draws.run(str(base_run["store"]), scene, 4, ["mean"], truth)
    assert {k: store.sha256(k) for k in store.list(scene)} == before


def test_force_recomputes_every_stage_and_keeps_the_answer(base_run, scene_dir):
    """``cropcraft run --force`` (``refresh``): no stage is served from the cache, each one's
    cached result is replaced, the answer is the same, and the next plain rerun is cached."""
    forced = _run("plotA", base_run["store"], scene_dir, refresh=True)
    assert set(forced["states"].values()) == {"Completed"}, forced["states"]
    assert forced["params"] == base_run["first"]["params"]
    assert _executed(_run("plotA", base_run["store"], scene_dir)["states"]) == []


def _cached(store, scene_dir, overrides=OVERRIDES):
    """``flows.scene.cached_result`` for these settings: the summary or None (no flow run)."""
    from flows.scene import cached_result, prepare

    images, poses = str(scene_dir / "images"), str(scene_dir / "transforms.json")
    return cached_result(prepare("plotA", CROP, DATE, images, poses, overrides, str(store)))


def test_unchanged_scene_answered_without_prefect(base_run, scene_dir):
    """``cropcraft run`` answers an unchanged scene from the stage records without a flow run,
    and only then: settings never run are a miss (None), not another run's answer."""
    from prefect.client.orchestration import get_client

    with get_client(sync_client=True) as client:
        runs_before = client.count_flow_runs()
        hit = _cached(base_run["store"], scene_dir)
        assert hit is not None and hit["params"] == base_run["first"]["params"]
        assert client.count_flow_runs() == runs_before  # no flow run: the records answered
    assert _cached(base_run["store"], scene_dir, {**OVERRIDES, "generate.seed": 99}) is None


def test_a_cached_answer_records_where_its_inputs_were_read(base_run, scene_dir, tmp_path):
    """A run answered wholly from the cache updates the manifest's sources as a flow run does
    (the season judges a date's inbox by them), keeping its stage records."""
    from flows.scene import note_sources, prepare

    store = tmp_path / "store"
    shutil.copytree(base_run["store"], store)
    images, poses = str(scene_dir / "images"), str(scene_dir / "transforms.json")
    req = prepare("plotA", CROP, DATE, images, poses, OVERRIDES, str(store))
    st = SceneStore(str(store))
    before = st.load_manifest(req.scene)
    st.init_manifest(req.scene, before.inputs, req.config, sources={"images": "/elsewhere"})
    note_sources(req, images, poses)
    after = st.load_manifest(req.scene)
    assert after.sources == {"images": os.path.abspath(images), "poses": os.path.abspath(poses)}
    assert after.stages == before.stages and after.stages


def test_the_same_files_read_again_rerun_only_their_reading(base_run, scene_dir, tmp_path):
    """Photos and poses copied to another folder with new modification times (an inbox synced
    again) are read again, but they are the same files: the stages after them key on what the
    images and poses are, not on where they were read, so stereo and the fit stay cached."""
    store = tmp_path / "store"
    shutil.copytree(base_run["store"], store)
    copy = tmp_path / "scene"
    shutil.copytree(scene_dir, copy, copy_function=shutil.copyfile)
    later = time.time() + 3600
    for path in copy.rglob("*"):
        os.utime(path, (later, later))
    out = _run("plotA", store, copy)
    assert _executed(out["states"]) == ["ingest", "poses"]
    assert out["params"] == base_run["first"]["params"]
    manifest = SceneStore(str(store)).get_json(f"plotA/{CROP}/{DATE}/ingest/images/manifest.json")
    assert manifest["source"] == str(copy / "images")  # the provenance is the new read's


def test_late_config_change_recomputes_from_that_stage_on(base_run, scene_dir):
    out = _run("plotA", base_run["store"], scene_dir, {**OVERRIDES, "generate.seed": 1})
    assert _executed(out["states"]) == ["export", "generate", "metrics", "report"]
    api = _task_run_states(out["flow_run_id"], N_TASKS)
    assert sorted(api).count("Completed") == 4 and api.count("Cached") == N_TASKS - 4


def test_changing_the_answer_rule_reuses_the_seeds(base_run, scene_dir):
    """``fit.combine`` only changes how the seeds become one answer: the seeds stay cached, the
    aggregate re-scores their candidates against the stored observation and records them."""
    overrides = {**OVERRIDES, "fit.combine": "reevaluate", "fit.reevaluate_canopies": 2}
    out = _run("plotA", base_run["store"], scene_dir, overrides)
    executed = set(_executed(out["states"]))
    assert {"aggregate", "report"} <= executed
    assert not any(k.startswith("fit_seed") for k in executed)
    store = SceneStore(str(base_run["store"]))
    fit = store.get_json(f"plotA/{CROP}/{DATE}/fit/fit.json")
    sel = fit["extra"]["selection"]
    rescored = {*(f"seed-{s}" for s in range(N_SEEDS)), "mean", "averaged"}
    loss = {k: c["loss"] for k, c in sel["candidates"].items()}
    best = min(rescored, key=loss.get)
    assert set(sel["candidates"]) == rescored | {f"polished-{best}"}  # the winner, refined
    assert loss[sel["chosen"]] == min(loss.values()) <= loss[best]
    assert fit["params"] == sel["candidates"][sel["chosen"]]["params"] == out["params"]
    assert fit["config"]["combine"] == "reevaluate"


def test_a_new_default_answer_rule_reaggregates_cached_seeds(base_run, scene_dir, monkeypatch):
    """The aggregate's cache key names the rule a default config resolves to: the crop's rule
    written out is the same run (all cached), and a release that changes the crop's default
    re-aggregates the cached seeds instead of serving the old rule's stored answer."""
    from cropcraft_core.fit import fitting

    rule = fitting.DEFAULT_COMBINE[CROP]
    _run("plotA", base_run["store"], scene_dir)  # whatever earlier tests left: the default
    out = _run("plotA", base_run["store"], scene_dir, {**OVERRIDES, "fit.combine": rule})
    assert _executed(out["states"]) == []
    other = "mean" if rule != "mean" else "median"
    monkeypatch.setitem(fitting.DEFAULT_COMBINE, CROP, other)
    out = _run("plotA", base_run["store"], scene_dir)
    executed = set(_executed(out["states"]))
    assert "aggregate" in executed
    assert not any(k.startswith("fit_seed") for k in executed)
    fit = SceneStore(str(base_run["store"])).get_json(f"plotA/{CROP}/{DATE}/fit/fit.json")
    assert fit["config"]["combine"] == other


def test_blurred_predictions_reobserve_and_refit_only(base_run, scene_dir):
    """``observe.prediction_blur=auto``: the observation's preset carries the fused surfaces'
    own softening (tsdf: 0.8 voxel, in metres by the row fit's scale), in the observe record's
    summary too; the observe stage and every seed run again, nothing upstream does."""
    from cropcraft_core.surfaces import SurfacesConfig
    from cropcraft_core.surfaces.tsdf import EDGE_BLUR_VOXELS

    _run("plotA", base_run["store"], scene_dir)  # whatever earlier tests left: the default
    out = _run(
        "plotA", base_run["store"], scene_dir, {**OVERRIDES, "observe.prediction_blur": "auto"}
    )
    executed = set(_executed(out["states"]))
    assert "observe" in executed and sum(k.startswith("fit_seed") for k in executed) == N_SEEDS
    assert not executed & {"ingest", "poses", "surfaces", "rowfit", "consistency"}
    store = SceneStore(str(base_run["store"]))
    scene = f"plotA/{CROP}/{DATE}"
    obs = Observation.load(io.BytesIO(store.get_bytes(f"{scene}/observe/observation.npz")))
    scale = store.get_json(f"{scene}/rowfit/rowfit.json")["scale"]
    blur = EDGE_BLUR_VOXELS * SurfacesConfig().voxel_size * scale
    assert obs.preset.prediction_blur_m == pytest.approx(blur) and blur > 0
    z = float(np.median(obs.depth[obs.mask]))
    assert obs.prediction_blur_px == pytest.approx(blur * obs.camera.fy / z)
    _run("plotA", base_run["store"], scene_dir)  # back to the default for the tests after


def test_a_new_default_canopy_count_refits_the_seeds(base_run, scene_dir, monkeypatch):
    """The seeds' cache key names the canopies per evaluation a default config resolves to
    (``DEFAULT_CANOPIES``): written out it is the same run, and a release changing the crop's
    default refits the seeds (their losses average a different number of canopies)."""
    from cropcraft_core.fit import fitting

    k = fitting.DEFAULT_CANOPIES[CROP]
    _run("plotA", base_run["store"], scene_dir)  # whatever earlier tests left: the default
    out = _run("plotA", base_run["store"], scene_dir, {**OVERRIDES, "fit.canopies_per_eval": k})
    assert _executed(out["states"]) == []
    monkeypatch.setitem(fitting.DEFAULT_CANOPIES, CROP, k + 1)
    out = _run("plotA", base_run["store"], scene_dir)
    executed = set(_executed(out["states"]))
    assert sum(name.startswith("fit_seed") for name in executed) == N_SEEDS
    # the stages after aggregate rerun only where the new seeds change the answer (at this
    # tiny budget the lowest points may be the same initial draws, and then they are cached)
    assert "aggregate" in executed
    assert not executed & {"ingest", "poses", "surfaces", "rowfit", "observe"}


def test_the_floors_rule_polishes_in_the_seed_tasks_and_ranks_in_the_aggregate(
    base_run, scene_dir, tmp_path
):
    """``fit.combine=floors`` through the flow: the seeds rerun (their records carry their
    floors), each stored seed holds its floor, and the aggregate ranks them without polishing
    any seed's again."""
    from cropcraft_core.fit.select import reevaluation_seeds
    from cropcraft_core.optimize import SeedResult, aggregate

    _run("plotA", base_run["store"], scene_dir)  # whatever earlier tests left: the default
    out = _run("plotA", base_run["store"], scene_dir, {**OVERRIDES, "fit.combine": "floors"})
    executed = set(_executed(out["states"]))
    assert {f"fit_seed-{s}" for s in range(N_SEEDS)} | {"aggregate"} <= executed
    assert not executed & {"ingest", "poses", "surfaces", "rowfit", "observe"}
    store = SceneStore(str(base_run["store"]))
    prefix = f"plotA/{CROP}/{DATE}"
    for s in range(N_SEEDS):
        seed = SeedResult.load(store.get_file(f"{prefix}/fit/seed-{s}.npz", tmp_path / f"{s}.npz"))
        assert seed.floor["polish_evals"] == OVERRIDES["fit.polish_evals"]
        assert seed.floor["canopy_seeds"] == reevaluation_seeds(
            OVERRIDES["fit.reevaluate_canopies"]
        )
    fit = store.get_json(f"{prefix}/fit/fit.json")
    floors = fit["extra"]["floors"]
    assert floors["from_seeds"] == [f"seed-{s}" for s in range(N_SEEDS)]
    assert fit["config"]["combine"] == "floors" and out["params"] == fit["params"]
    if floors["chosen"] == "median":  # the seeds' median, stored seeds' best points
        best = [
            SeedResult.load(store.get_file(f"{prefix}/fit/seed-{s}.npz", tmp_path / f"{s}.npz"))
            for s in range(N_SEEDS)
        ]
        median = np.median(aggregate(best).per_seed, axis=0)
        assert np.allclose(list(fit["params"].values()), median)
    else:
        assert fit["params"] == floors["floors"][floors["chosen"]]["params"]


def test_the_papers_optimiser_keeps_the_seed_keys_it_had_before_the_local_search(monkeypatch):
    """BO's closing local search and log output are hashed only when they change the fit: the
    defaults (and their values written out) give the seeds' config of earlier releases, so
    stored seeds stay served; another value, or a release changing the crop's default, is
    another key."""
    from cropcraft_core.fit import fitting
    from flows.scene import resolve_config, stage_configs

    def seed_config(overrides):
        return stage_configs(resolve_config(CROP, overrides), CROP)["fit_seed"]

    default = seed_config({})
    assert "local_share" not in default and "gp_output" not in default
    assert seed_config({"fit.local_share": 0.0, "fit.gp_output": "none"}) == default
    assert seed_config({"fit.local_share": 0.2})["local_share"] == 0.2
    assert seed_config({"fit.gp_output": "log"})["gp_output"] == "log"
    monkeypatch.setitem(fitting.DEFAULT_LOCAL_SHARE, CROP, 0.2)
    assert seed_config({})["local_share"] == 0.2
    monkeypatch.setitem(fitting.DEFAULT_LOCAL_SHARE, CROP, 0.0)
    monkeypatch.setitem(fitting.DEFAULT_GP_OUTPUT, CROP, "log")
    assert seed_config({})["gp_output"] == "log"
    assert seed_config({"fit.gp_output": "none"}) == default


def test_only_the_floors_rule_keys_the_seeds_by_their_polish():
    """The answer rule and its polish are the aggregate's settings, so changing them re-combines
    the stored seeds; under ``floors`` each seed polishes its own point in its task, so there
    they are the seeds' settings too (and a seed polished 60 times is not one polished 30)."""
    from flows.scene import resolve_config, stage_configs

    def configs(overrides):
        return stage_configs(resolve_config(CROP, overrides), CROP)

    default = configs({})["fit_seed"]
    assert not {"combine", "polish_evals", "reevaluate_canopies", "loss_estimator"} & set(default)
    unbiased = configs({"fit.loss_estimator": "unbiased"})
    assert unbiased["fit_seed"] == {**default, "loss_estimator": "unbiased"}
    assert unbiased["aggregate"]["loss_estimator"] == "unbiased"
    for o in ({"fit.combine": "reevaluate"}, {"fit.polish_evals": 30}):
        assert configs(o)["fit_seed"] == default
    floors = configs({"fit.combine": "floors"})
    assert floors["fit_seed"] == {
        **default,
        "combine": "floors",
        "polish_evals": 60,
        "reevaluate_canopies": 16,
    }
    assert floors["aggregate"]["combine"] == "floors"
    assert (
        configs({"fit.combine": "floors", "fit.polish_evals": 30})["fit_seed"] != floors["fit_seed"]
    )


def test_settings_that_change_no_result_keep_the_stages_cached():
    """A layout setting written out at the crop's default is the same layout (it refitted every
    canopy stage); a fit's seed count does not change seed k (10 -> 12 seeds fitted all twelve
    again), while the aggregate, which combines them, is keyed by it."""
    from flows.scene import resolve_config, stage_configs
    from tasks.common import stage_key

    def configs(overrides):
        return stage_configs(resolve_config(CROP, overrides), CROP)

    default = configs({})
    assert configs({"layout.row_spacing": 0.76}) == default
    assert configs({"layout.row_spacing": 0.5})["fit_seed"] != default["fit_seed"]
    scene = f"plotA/{CROP}/{DATE}"
    up = {"observe": {"hashes": {"a": "1"}}}

    def key(stage, overrides, **extra):
        return stage_key(stage, scene, configs(overrides)[stage], up, extra)

    assert key("fit_seed", {"fit.n_seeds": 12}, seed=3) == key("fit_seed", {}, seed=3)
    assert key("fit_seed", {"fit.n_evals": 400}, seed=3) != key("fit_seed", {}, seed=3)
    assert key("aggregate", {"fit.n_seeds": 12}) != key("aggregate", {})
    # a setting added later keys, at its default, as the stage did before it existed
    assert "exif_focal" not in default["poses"]
    off = configs({"poses.exif_focal": False})["poses"]
    assert off == {**default["poses"], "exif_focal": False}
    assert key("poses", {"poses.exif_focal": False}) != key("poses", {})


def test_the_row_fit_and_the_report_are_keyed_by_the_summaries_they_read(scene_dir, tmp_path):
    """The row fit reads the poses' frame (metric? the scale's source, the camera height) from
    their record's summary, and the report prints the stages' summaries: a camera height equal
    to the prior levels the poses to the same bytes, and consistency.warn changes only the
    consistency summary, so both were served from the earlier run."""
    from flows.scene import _wire, prepare
    from tasks.common import upstream_hashes

    class Recorder:
        """Every stage's upstream, with records whose summaries a test sets."""

        def __init__(self, summaries):
            self.up, self.summaries = {}, summaries

        def _rec(self, stage):
            return {"hashes": {stage: "h"}, "summary": self.summaries.get(stage, {})}

        def run(self, stage, upstream, row=None, **_):
            self.up[stage] = upstream
            return self._rec(stage)

        def run_rows(self, stage, jobs):
            return {row: self.run(stage, up, row) for row, up in jobs.items()}

        def map_seeds(self, jobs, seeds):
            return {row: {f"seed-{s}": self._rec("fit_seed") for s in seeds} for row in jobs}

    req = prepare("plotA", CROP, DATE, str(scene_dir / "images"), None, OVERRIDES, str(tmp_path))
    hinted = {"metric": True, "frame": {"scale_source": "camera_height", "camera_height_m": 1.4}}
    prior = {"metric": False, "frame": {"scale_source": "prior", "camera_height_m": 1.4}}
    a, b = Recorder({"poses": prior}), Recorder({"poses": hinted})
    _wire(a, req), _wire(b, req)

    def keyed(rec, stage):  # what of its upstream a stage's cache key holds
        return upstream_hashes(rec.up[stage])

    assert keyed(a, "rowfit") != keyed(b, "rowfit")
    assert keyed(a, "surfaces") == keyed(b, "surfaces")  # the same poses.json: the same surfaces
    c = Recorder({"poses": prior, "consistency": {"warning": "no surface under 39 %"}})
    _wire(c, req)
    assert keyed(c, "rowfit") == keyed(a, "rowfit") and keyed(c, "report") != keyed(a, "report")


def test_imported_poses_read_by_the_auto_rule_are_keyed_by_it(scene_dir, tmp_path):
    """Poses read as metric or not by ``imported_metric="auto"`` carry the rule's version in
    their key (so poses read by an earlier rule, e.g. an ns-process-data SfM transforms.json
    once read as metric, are read again), and only they: SfM scenes and an explicit reading
    keep their keys."""
    from flows.scene import AUTO_METRIC_RULE, METRIC_LEVELLING_RULE, SWEEP_RULE, _wire, prepare

    class Recorder:
        def __init__(self):
            self.up = {}

        def run(self, stage, upstream, row=None, **_):
            self.up[stage] = upstream
            return {"hashes": {stage: "h"}, "summary": {}}

        def run_rows(self, stage, jobs):
            return {row: self.run(stage, up, row) for row, up in jobs.items()}

        def map_seeds(self, jobs, seeds):
            return {row: {f"seed-{s}": self.run("fit_seed", {}) for s in seeds} for row in jobs}

    def poses_upstream(poses, overrides):
        rec = Recorder()
        req = prepare(
            "plotA", CROP, DATE, str(scene_dir / "images"), poses, {**OVERRIDES, **overrides},
            str(tmp_path),
        )  # fmt: skip
        _wire(rec, req)
        return rec.up["poses"]

    transforms = str(scene_dir / "transforms.json")
    assert poses_upstream(transforms, {})["rule"] == AUTO_METRIC_RULE
    # read as metric by an explicit true: keyed by the levelling rule (a walk along one side
    # of the plot was levelled 41° off), not by the auto rule
    explicit = poses_upstream(transforms, {"poses.imported_metric": True})
    assert explicit["rule"] == METRIC_LEVELLING_RULE
    assert "rule" not in poses_upstream(transforms, {"poses.imported_metric": False})
    assert "rule" not in poses_upstream(None, {})

    def surfaces_upstream(overrides):
        rec = Recorder()
        _wire(rec, prepare("plotA", CROP, DATE, str(scene_dir / "images"), transforms,
                           {**OVERRIDES, **overrides}, str(tmp_path)))  # fmt: skip
        return rec.up["surfaces"]

    # the sweep's rule changed for depth_range and min_ncc = -1: only such scenes are rekeyed
    assert "rule" not in surfaces_upstream({})
    assert "rule" not in surfaces_upstream({"surfaces.min_ncc": 0.3})
    assert surfaces_upstream({"surfaces.min_ncc": -1})["rule"] == SWEEP_RULE
    assert surfaces_upstream({"surfaces.depth_range": [0.3, 2.0]})["rule"] == SWEEP_RULE


def test_the_flows_embedded_defaults_are_the_core_configs_own():
    """The flow's config table writes its defaults out (a user reads them, ``--set`` names
    them, and the flow imports no core module to build it); each is the core default it
    stands for, so a changed core default cannot leave the flow computing the old one."""
    import dataclasses
    import inspect

    from cropcraft_core.fit import FitConfig
    from cropcraft_core.observe.observation import NO_SURFACE_WARN
    from cropcraft_core.sfm.ingest import ingest_images
    from cropcraft_core.surfaces import consistency
    from flows.scene import DEFAULTS

    core_fit = {
        f.name: f.default if f.default is not dataclasses.MISSING else f.default_factory()
        for f in dataclasses.fields(FitConfig)
    }
    assert DEFAULTS["fit"] == core_fit
    assert DEFAULTS["rows"]["max_no_surface"] == NO_SURFACE_WARN
    assert DEFAULTS["consistency"]["max_views"] == consistency.MAX_VIEWS
    assert DEFAULTS["consistency"]["min_height"] == consistency.MIN_HEIGHT_M
    min_images = inspect.signature(ingest_images).parameters["min_images"].default
    assert DEFAULTS["ingest"]["min_images"] == min_images


def test_the_surfaces_backend_parameter_sits_beneath_the_overrides():
    """A deployment names its backend in ``surfaces_backend`` (Prefect would drop it from a
    deployment's ``overrides`` once a run brings its own); a run's own ``surfaces.backend``,
    dotted or nested, still wins; the flow's choices are the backends but the benchmarks'
    truth; an unknown one is refused before any work."""
    import typing

    from cropcraft_core.surfaces import BACKENDS
    from flows.scene import SurfacesBackend, resolve_config, with_backend

    assert set(typing.get_args(SurfacesBackend)) == set(BACKENDS) - {"truth"}

    def backend(overrides, choice):
        return resolve_config("maize", with_backend(overrides, choice))["surfaces"]["backend"]

    assert backend(None, None) == "points"  # maize's own default
    assert backend({"fit.n_seeds": 2}, "tsdf") == "tsdf"
    assert backend({"surfaces.backend": "points"}, "tsdf") == "points"
    assert backend({"surfaces": {"backend": "points"}}, "tsdf") == "points"
    with pytest.raises(ConfigError, match="unknown surfaces backend 'nerf'"):
        resolve_config("maize", with_backend(None, "nerf"))


def test_a_whole_number_written_as_a_float_is_stored_as_a_whole_number():
    """``--set fit.n_seeds=1e1`` is JSON's 10.0: the config holds 10, hashed as the 10 a user
    writes out (the same cache key)."""
    from flows.scene import resolve_config

    a = resolve_config(CROP, {"fit.n_seeds": 1e1})
    assert a["fit"]["n_seeds"] == 10 and isinstance(a["fit"]["n_seeds"], int)
    assert config_hash(a) == config_hash(resolve_config(CROP, {"fit.n_seeds": 10}))


def test_an_observation_pooled_over_rows_is_keyed_with_their_spacing():
    """Pooling the observation over neighbouring rows needs the planting row spacing, so the
    observe stage then hashes the layout; otherwise its key is what it was before pooling
    existed (the stored observations are served), and pooling along the row alone keys by
    the preset."""
    from flows.scene import resolve_config, stage_configs

    def observe(overrides):
        return stage_configs(resolve_config(CROP, overrides), CROP)["observe"]

    default = observe({})
    assert default == {"image_scale": 1.0, "preset": {}}
    along = observe({"observe.preset.views_along": 3})
    assert along["preset"] == {"views_along": 3} and "layout" not in along
    rows = observe({"observe.preset.views_across": 1, "layout.row_spacing": 0.5})
    assert rows["layout"] == {"row_spacing": 0.5}
    # unblurred predictions (the default) keep the key; a blur is a key of its own
    assert observe({"observe.prediction_blur": 0}) == default
    assert observe({"observe.prediction_blur": "auto"})["prediction_blur"] == "auto"


def test_each_crop_gets_its_measured_surfaces_under_the_users_settings():
    """Maize (drone photos) splats points capped at their spacing; soybean keeps the fused
    surface; a user's setting wins over the crop's, and the crops' surfaces stages hash apart."""
    from flows.scene import resolve_config, stage_configs

    maize = resolve_config("maize")["surfaces"]
    assert maize["backend"] == "points" and maize["splat_density"] == 1.0
    assert maize["visibility_ratio"] == 0.1
    soy = resolve_config("soybean")["surfaces"]
    assert soy["backend"] == "tsdf" and "splat_density" not in soy
    assert resolve_config("maize", {"surfaces.backend": "tsdf"})["surfaces"]["backend"] == "tsdf"
    assert (
        resolve_config("maize", {"surfaces.splat_density": None})["surfaces"]["splat_density"]
        is None
    )
    with pytest.raises(ConfigError, match="splat_density must be a positive number"):
        resolve_config("maize", {"surfaces.splat_density": -1})
    assert (
        stage_configs(resolve_config("maize"))["surfaces"]
        != stage_configs(resolve_config("soybean"))["surfaces"]
    )


def test_the_surfaces_stage_hashes_the_crops_scene_box_it_resolves(monkeypatch):
    """``bbox: auto`` is keyed as the crop's box itself, so a release that changes the box
    (maize's reached 3.5 m down in November) recomputes the surfaces instead of serving ones
    whose box cut the soil out; an explicit box is keyed as given."""
    from cropcraft_core.surfaces import base
    from flows.scene import resolve_config, stage_configs

    cfg = resolve_config("maize")
    assert cfg["surfaces"]["bbox"] == "auto"
    keyed = stage_configs(cfg, "maize")["surfaces"]["bbox"]
    assert keyed == [list(c) for c in base.SCENE_BOX["maize"]]
    monkeypatch.setitem(base.SCENE_BOX, "maize", ((-3.0, -3.0, -0.3), (3.0, 3.0, 3.5)))
    assert stage_configs(cfg, "maize")["surfaces"]["bbox"] != keyed
    mine = resolve_config("maize", {"surfaces.bbox": [[-1, -1, -1], [1, 1, 1]]})
    assert stage_configs(mine, "maize")["surfaces"]["bbox"] == [[-1, -1, -1], [1, 1, 1]]


def test_nerfacto_surfaces_are_keyed_by_their_far_plane_margin():
    """nerfacto's default far plane moved to the scene (session 30): a nerfacto surfaces stage
    is keyed with the margin written out, so surfaces trained with nerfstudio's far plane
    (stored under the old key) are trained again; the CPU backends' keys do not change."""
    from cropcraft_core.surfaces import SurfacesConfig
    from flows.scene import resolve_config, stage_configs

    nerf = stage_configs(resolve_config(CROP, {"surfaces.backend": "nerfacto"}), CROP)
    assert nerf["surfaces"]["nerf_far_margin"] == SurfacesConfig.nerf_far_margin == 1.5
    off = resolve_config(CROP, {"surfaces.backend": "nerfacto", "surfaces.nerf_far_margin": None})
    assert stage_configs(off, CROP)["surfaces"]["nerf_far_margin"] is None
    assert "nerf_far_margin" not in stage_configs(resolve_config(CROP), CROP)["surfaces"]


def test_nerfacto_in_the_flow_takes_the_papers_settings_per_crop():
    """The ``scene-nerfacto`` deployment promises the paper's NeRF: for maize its near/far
    planes, MLP width and orientation (``NERF_PAPER``), under the user's own settings; soybean
    keeps nerfstudio's; the CPU backends get none of them."""
    from cropcraft_core.surfaces import NERF_PAPER, SurfacesConfig
    from flows.scene import resolve_config

    maize = resolve_config("maize", {"surfaces.backend": "nerfacto"})["surfaces"]
    assert {k: maize[k] for k in NERF_PAPER["maize"]} == NERF_PAPER["maize"]
    cfg = SurfacesConfig.from_dict(
        {k: v for k, v in maize.items() if k not in ("bbox", "n_points")}
    )
    assert (cfg.near_plane, cfg.far_plane, cfg.hidden_dim, cfg.orientation) == (
        0.05, 6.0, 128, "vertical",
    )  # fmt: skip
    mine = resolve_config("maize", {"surfaces.backend": "nerfacto", "surfaces.far_plane": 8.0})
    assert mine["surfaces"]["far_plane"] == 8.0 and mine["surfaces"]["hidden_dim"] == 128
    soy = resolve_config("soybean", {"surfaces.backend": "nerfacto"})["surfaces"]
    assert "far_plane" not in soy and "hidden_dim" not in soy
    assert "far_plane" not in resolve_config("maize")["surfaces"]


def test_guided_matching_is_off_by_default_and_in_the_poses_stage_hash():
    """Epipolar re-matching is slower and less accurate on canopies (run_sfm's docstring): off
    unless asked for, and asking for it re-runs SfM (its stage hashes apart)."""
    from flows.scene import resolve_config, stage_configs

    assert resolve_config(CROP)["poses"]["guided_matching"] is False
    on = resolve_config(CROP, {"poses.guided_matching": True})
    assert on["poses"]["guided_matching"] is True
    assert stage_configs(on)["poses"] != stage_configs(resolve_config(CROP))["poses"]


def _timeless(record):
    """``record`` without its wall-clock fields (``seconds``, ``rescore_seconds``)."""
    if isinstance(record, dict):
        return {k: _timeless(v) for k, v in record.items() if not k.endswith("seconds")}
    if isinstance(record, list):
        return [_timeless(v) for v in record]
    return record


def test_a_cached_run_whose_artefacts_were_overwritten_is_recomputed(base_run, scene_dir):
    """Artefacts live at one key per scene and stage: a run with other settings writes over
    them. Rerunning the first settings must not serve their cached records over the other
    run's files: the stages whose artefacts changed recompute (the seeds do not), the store
    holds the first settings' answer again, and the next rerun is all cached."""
    store = SceneStore(str(base_run["store"]))
    fit_key = f"plotA/{CROP}/{DATE}/fit/fit.json"
    _run("plotA", base_run["store"], scene_dir)  # whatever earlier tests left: the default
    default = store.get_json(fit_key)
    other = "mean" if default["config"]["combine"] != "mean" else "median"
    _run("plotA", base_run["store"], scene_dir, {**OVERRIDES, "fit.combine": other})
    assert store.get_json(fit_key)["config"]["combine"] == other
    # the first settings' records are still there, but their files are not: no cached answer
    assert _cached(base_run["store"], scene_dir) is None
    out = _run("plotA", base_run["store"], scene_dir)
    executed = set(_executed(out["states"]))
    assert {"aggregate", "generate", "export", "report"} <= executed
    assert not any(k.startswith("fit_seed") for k in executed)
    # the same answer; the re-scoring's wall-clock seconds (soybean's guarded median) differ
    assert _timeless(store.get_json(fit_key)) == _timeless(default)
    assert _executed(_run("plotA", base_run["store"], scene_dir)["states"]) == []
    assert _cached(base_run["store"], scene_dir)["params"] == default["params"]


def test_a_cached_run_whose_artefact_was_deleted_is_recomputed(base_run, scene_dir):
    """Someone deletes an artefact (clearing space, or by hand): the record that names it must
    not be served, or every rerun fails on the missing object; the stage that wrote it runs
    again, and the next rerun is all cached."""
    store = SceneStore(str(base_run["store"]))
    fit_key = f"plotA/{CROP}/{DATE}/fit/fit.json"
    _run("plotA", base_run["store"], scene_dir)  # whatever earlier tests left: the default
    default = store.get_json(fit_key)
    store.delete(fit_key)
    assert _cached(base_run["store"], scene_dir) is None
    # and a writer killed mid-write long ago left a temporary object: the run sweeps it
    dead = Path(base_run["store"]) / f"plotA/{CROP}/{DATE}/fit/{TMP_PREFIX}dead-fit.json"
    dead.write_bytes(b"half")
    os.utime(dead, (time.time() - 7200, time.time() - 7200))
    executed = set(_executed(_run("plotA", base_run["store"], scene_dir)["states"]))
    assert not dead.exists()
    assert "aggregate" in executed
    assert not any(k.startswith("fit_seed") for k in executed)
    assert _timeless(store.get_json(fit_key)) == _timeless(default)
    assert _executed(_run("plotA", base_run["store"], scene_dir)["states"]) == []


def test_a_cached_run_whose_artefacts_were_damaged_in_place_is_recomputed(base_run, scene_dir):
    """Files cut short or edited by hand in a finished scene (a bundle's canopy.ply, a seed's
    npz, metrics.json) were served from the cache: `cropcraft run` exited 0 pointing at the cut
    bundle, `status` said cached, and a damaged upstream file failed every rerun the same way
    (session 91's crash audit). A local store's artefacts are checked against the sha256 their
    stage recorded: the stages that wrote them run again, and their files are whole again."""
    from flows.service_cli import scene_status

    store = SceneStore(str(base_run["store"]))
    scene = f"plotA/{CROP}/{DATE}"
    _run("plotA", base_run["store"], scene_dir)  # whatever earlier tests left: the default
    keys = (f"{scene}/export/bundle/canopy.ply", f"{scene}/fit/seed-0.npz")
    whole = {k: store.get_bytes(k) for k in (*keys, f"{scene}/metrics/metrics.json")}
    root = Path(base_run["store"])
    for k in keys:
        with open(root / k, "r+b") as f:
            f.truncate(50)
    (root / f"{scene}/metrics/metrics.json").write_text('{"lai": "nonsense"')
    assert _cached(base_run["store"], scene_dir) is None
    listing = {r["stage"]: r for r in scene_status(str(base_run["store"]), scene)}
    assert listing["metrics"]["cached"] != "yes" and listing["export"]["cached"] != "yes"
    executed = set(_executed(_run("plotA", base_run["store"], scene_dir)["states"]))
    assert {"fit_seed-0", "metrics", "export"} <= executed and "fit_seed-1" not in executed
    assert "ingest" not in executed and "surfaces" not in executed
    ply, seed, metrics = whole
    assert store.get_bytes(ply) == whole[ply]  # the same canopy, whole again
    assert _timeless(store.get_json(metrics)) == _timeless(json.loads(whole[metrics]))
    again = store.get_npz(seed)
    with np.load(io.BytesIO(whole[seed])) as before:
        assert set(again) == set(before.files) and len(again) > 1
    assert _executed(_run("plotA", base_run["store"], scene_dir)["states"]) == []


def test_a_stage_that_fails_part_way_does_not_leave_a_cached_record_served(
    base_run, scene_dir, monkeypatch
):
    """A stage that fails after writing some of its artefacts (here generate, with another
    canopy seed: its recipe written, then the mesh export fails) leaves the store holding other
    bytes than the cached record of the earlier settings names: the rerun of those settings
    must recompute the stage, not serve the record."""
    import cropcraft_core.export as export_module

    store = SceneStore(str(base_run["store"]))
    scene = SceneKey("plotA", CROP, DATE)
    recipe_key = f"{scene.prefix}/generate/canopy.json"
    _run("plotA", base_run["store"], scene_dir)  # whatever earlier tests left: the default
    default = store.get_bytes(recipe_key)

    def broken(*args, **kwargs):
        raise OSError("disk full (injected)")

    with monkeypatch.context() as m:
        m.setattr(export_module, "write_ply", broken)
        with pytest.raises(OSError, match="injected"):
            _run("plotA", base_run["store"], scene_dir, {**OVERRIDES, "generate.seed": 1})
    assert store.get_bytes(recipe_key) != default  # the failed attempt's recipe is there
    # ... but not Prefect's record of its exception at the store's root, outside every scene
    stray = [p.name for p in Path(base_run["store"]).iterdir() if p.is_file()]
    assert not [n for n in stray if len(n) == 32 and all(c in "0123456789abcdef" for c in n)]
    failed = store.load_manifest(scene).stages["generate"]
    assert failed.status == "failed" and recipe_key in failed.artefacts
    out = _run("plotA", base_run["store"], scene_dir)
    assert "generate" in _executed(out["states"])
    assert store.get_bytes(recipe_key) == default
    done = store.load_manifest(scene).stages["generate"]  # not the failed attempt's error
    assert done.status == "done" and done.error is None
    assert _executed(_run("plotA", base_run["store"], scene_dir)["states"]) == []


def test_a_run_that_dies_before_recording_its_writes_leaves_no_cached_record_served(
    base_run, scene_dir, monkeypatch
):
    """A run with other settings writes generate's files and dies before the manifest hears
    of them (killed, out of memory, or here its record refused): the next run of the first
    settings must not serve their cached record over those files. The attempt's note in the
    manifest (``writing``) outlives the run; the next run hashes its folder first, and the
    cache walk (``cropcraft run``'s answer without a flow, ``cropcraft status``) misses."""
    from flows.scene import _PrefectRun

    store = SceneStore(str(base_run["store"]))
    scene = SceneKey("plotA", CROP, DATE)
    recipe_key = f"{scene.prefix}/generate/canopy.json"
    _run("plotA", base_run["store"], scene_dir)  # whatever earlier tests left: the default
    default = store.get_bytes(recipe_key)
    real = _PrefectRun._record

    def dies(self, stage, upstream, rec, error=None, row=None):
        if stage == "generate":
            raise StoreError("the manifest write failed (injected): the run ends here")
        return real(self, stage, upstream, rec, error, row)

    with monkeypatch.context() as m:
        m.setattr(_PrefectRun, "_record", dies)
        with pytest.raises(StoreError, match="injected"):
            _run("plotA", base_run["store"], scene_dir, {**OVERRIDES, "generate.seed": 1})
    assert store.get_bytes(recipe_key) != default  # the other settings' files are there
    assert "generate" in store.load_manifest(scene).writing
    assert _cached(base_run["store"], scene_dir) is None
    from flows.service_cli import scene_status  # no run holds the scene: not "running"

    listing = {r["stage"]: r["status"] for r in scene_status(str(base_run["store"]), scene.prefix)}
    assert listing["generate"] == "interrupted"
    out = _run("plotA", base_run["store"], scene_dir)
    assert "generate" in _executed(out["states"])
    assert store.get_bytes(recipe_key) == default
    assert store.load_manifest(scene).writing == {}
    assert _executed(_run("plotA", base_run["store"], scene_dir)["states"]) == []
    # an aggregate killed the same way shares its folder (fit/) with the seeds: their files
    # are whole, and status said "not cached" for seeds the next run served (crash audit 91)
    with monkeypatch.context() as m:
        m.setattr(_PrefectRun, "_record", dies_at("aggregate", real))
        with pytest.raises(StoreError, match="injected"):
            _run("plotA", base_run["store"], scene_dir, {**OVERRIDES, "fit.combine": "mean"})
    assert "aggregate" in store.load_manifest(scene).writing
    listing = {r["stage"]: r for r in scene_status(str(base_run["store"]), scene.prefix)}
    assert listing["fit_seed"]["cached"] == f"{N_SEEDS} seeds"
    assert (
        listing["aggregate"]["cached"] == "no" and listing["aggregate"]["status"] == "interrupted"
    )
    out = _run("plotA", base_run["store"], scene_dir)
    assert "aggregate" in _executed(out["states"])
    assert not any(k.startswith("fit_seed") for k in _executed(out["states"]))


def dies_at(stage_name, real):
    """``_PrefectRun._record`` refusing ``stage_name``'s record, as a run killed after the
    stage wrote its files and before the manifest heard of them."""

    def dies(self, stage, upstream, rec, error=None, row=None):
        if stage == stage_name:
            raise StoreError("the manifest write failed (injected): the run ends here")
        return real(self, stage, upstream, rec, error, row)

    return dies


def test_an_answer_after_a_failed_run_of_other_settings_is_recorded(
    base_run, scene_dir, monkeypatch
):
    """A run of other settings failed before it wrote anything; the earlier settings, all
    cached still, were answered without a flow, and the manifest kept the failure: status and
    the season said "failed" beside the answer (session 91's S3 audit). The flow answers
    them, serving every stage from the cache and recording it."""
    import tasks.fit_seed as fit_seed_module
    from flows.scene import cache_walk, prepare

    _run("plotA", base_run["store"], scene_dir)  # whatever earlier tests left: the default

    def broken(*args, **kwargs):
        raise RuntimeError("injected fault before any seed is written")

    monkeypatch.setattr(fit_seed_module, "fit_seed", broken)
    with pytest.raises(CropCraftError, match="fit seeds failed"):
        _run("plotA", base_run["store"], scene_dir, {**OVERRIDES, "fit.n_evals": 15})
    store = SceneStore(str(base_run["store"]))
    scene = SceneKey("plotA", CROP, DATE)
    assert store.load_manifest(scene).stages["fit_seed"].status == "failed"
    images, poses = str(scene_dir / "images"), str(scene_dir / "transforms.json")
    default = prepare("plotA", CROP, DATE, images, poses, OVERRIDES, str(base_run["store"]))
    assert cache_walk(default)[1] is None and _cached(base_run["store"], scene_dir) is None
    assert _executed(_run("plotA", base_run["store"], scene_dir)["states"]) == []
    assert store.load_manifest(scene).stages["fit_seed"].status == "done"
    assert _cached(base_run["store"], scene_dir) is not None


def test_fault_in_one_seed_then_resume_only_missing_work(base_run, scene_dir, monkeypatch):
    import tasks.fit_seed as fit_seed_module
    from cropcraft_core.fit import FitConfig, fit_observation
    from cropcraft_core.observe import Observation

    overrides = {**OVERRIDES, "fit.n_evals": 14}  # a new fit: seeds and what follows recompute
    real = fit_seed_module.fit_seed
    calls: list[int] = []

    def faulty(observation, seed, *args, **kwargs):
        calls.append(int(seed))
        if int(seed) == 1:
            raise RuntimeError("injected fault in seed 1")
        return real(observation, seed, *args, **kwargs)

    monkeypatch.setattr(fit_seed_module, "fit_seed", faulty)
    with pytest.raises(CropCraftError, match="1 of 3 fit seeds failed"):
        _run("plotA", base_run["store"], scene_dir, overrides)
    assert sorted(calls) == [0, 1, 2]
    store = SceneStore(str(base_run["store"]))
    scene = SceneKey("plotA", CROP, DATE)
    assert store.load_manifest(scene).stages["fit_seed"].status == "failed"

    def counting(observation, seed, *args, **kwargs):
        calls.append(int(seed))
        return real(observation, seed, *args, **kwargs)

    monkeypatch.setattr(fit_seed_module, "fit_seed", counting)
    calls.clear()
    out = _run("plotA", base_run["store"], scene_dir, overrides)
    assert calls == [1], "only the missing seed may run again"
    executed = set(_executed(out["states"]))
    assert {"fit_seed-1", "aggregate", "generate", "report"} <= executed
    assert not {"fit_seed-0", "fit_seed-2"} & executed
    # the metrics and what follows them recompute even where the answer is an earlier run's:
    # they also measure each seed's answer (metrics.json's seeds), and these seeds are new
    assert {"metrics", "export"} <= executed

    # equals a clean run: all seeds of the same fit computed in one go, no fault
    obs = Observation.load(io.BytesIO(store.get_bytes(f"{scene.prefix}/observe/observation.npz")))
    cfg = FitConfig(
        method="bo",
        n_seeds=N_SEEDS,
        n_evals=14,
        n_initial=6,
        reevaluate_canopies=OVERRIDES["fit.reevaluate_canopies"],
        polish_evals=OVERRIDES["fit.polish_evals"],
    )
    from cropcraft_core.config import default_layout

    clean = fit_observation(obs, cfg, default_layout(CROP))
    for k, v in clean.params.items():
        assert out["params"][k] == pytest.approx(v, rel=1e-6), k


def test_a_seed_whose_run_no_longer_holds_the_scene_writes_nothing(
    base_run, scene_dir, monkeypatch
):
    """On a Dask cluster a seed runs on after its run has failed or lost its client, and one
    wrote its seed file over the scene 9 s after its run had ended (session 92's Dask audit).
    Each seed carries its run's lease token and checks the scene's lease before it starts,
    every 10 % and before it writes: seeds handed a token that no longer holds the scene stop,
    and the stored seeds are left as they were."""
    from cropcraft_core.lease import SceneLease

    _run("plotA", base_run["store"], scene_dir)  # whatever earlier tests left: the default
    store = SceneStore(str(base_run["store"]))
    scene = SceneKey("plotA", CROP, DATE)
    seeds = {k: store.get_bytes(k) for k in store.list(f"{scene.prefix}/fit") if "seed-" in k}
    assert len(seeds) >= N_SEEDS
    monkeypatch.setattr(SceneLease, "token", property(lambda self: "a run that ended"))
    with pytest.raises(CropCraftError, match="no longer holds the scene") as err:
        _run("plotA", base_run["store"], scene_dir, {**OVERRIDES, "fit.n_evals": 16})
    assert f"{N_SEEDS} of {N_SEEDS} fit seeds failed" in str(err.value)
    assert {k: store.get_bytes(k) for k in seeds} == seeds


def test_a_seeds_unreadable_checkpoint_is_set_aside_and_the_seed_starts_afresh(
    base_run, scene_dir, monkeypatch
):
    """A seed checkpoint cut short (disk damage, a hand edit) failed its seed on every rerun
    with "rerun the same command" (session 91's crash audit): it is only a cache, so it is kept
    aside under another name and the seed is fitted from the start."""
    import tasks.fit_seed as fit_seed_module

    real = fit_seed_module.fit_seed
    damaged: list[Path] = []

    def cut_short(observation, seed, cfg, layout, checkpoint, *args, **kwargs):
        if int(seed) == 0 and not damaged:  # as a kill then a disk fault would leave it
            Path(checkpoint).write_text('{"X": [[0.5, 0.5')
            damaged.append(Path(checkpoint))
        return real(observation, seed, cfg, layout, checkpoint, *args, **kwargs)

    monkeypatch.setattr(fit_seed_module, "fit_seed", cut_short)
    out = _run("plotA", base_run["store"], scene_dir, {**OVERRIDES, "fit.n_evals": 13})
    assert {"fit_seed-0", "fit_seed-1"} <= set(_executed(out["states"]))
    (ckpt,) = damaged
    assert not ckpt.exists()  # removed on success, as any finished seed's
    # the newest set aside (the checkpoint folder is the user's, kept between test runs)
    aside = max(ckpt.parent.glob(f"{ckpt.stem}.unreadable-*.json"), key=lambda p: p.name)
    assert aside.read_text() == '{"X": [[0.5, 0.5'
    assert time.time() - aside.stat().st_mtime < 600


def _copy_without_late_results(src: Path, dst: Path) -> None:
    """A copy of a local store minus the cached results from fit_seed on (so they recompute)."""
    shutil.copytree(src, dst)
    for cache in dst.glob("*/*/*/.prefect"):
        for stage in ("fit_seed", *LATE_STAGES):
            shutil.rmtree(cache / stage, ignore_errors=True)


@pytest.mark.parametrize("runner", ["dask", "processes"])
def test_process_runners_give_the_same_result_as_threads(
    base_run, scene_dir, tmp_path, runner, capsys
):
    from flows.service_cli import run_progress

    if runner == "dask":
        pytest.importorskip("prefect_dask")
    store = tmp_path / f"store-{runner}"
    _copy_without_late_results(base_run["store"], store)
    with run_progress(bar=False):  # the CLI's console progress without a terminal
        out = _run("plotA", store, scene_dir, runner=runner)
    assert _executed(out["states"]) == sorted(
        [*(f"fit_seed-{s}" for s in range(N_SEEDS)), *LATE_STAGES]
    )
    _same_result(out, base_run["first"])
    # the workers' task runs reach the server the flow reports to (flows.runners hands them its
    # address; before, each worker process started an ephemeral server of its own)
    api = _task_run_states(out["flow_run_id"], N_TASKS)
    assert len(api) == N_TASKS and sorted(api).count("Completed") == N_SEEDS + len(LATE_STAGES)
    # the fit's progress reaches this process (the CLI's console); from Dask's workers through
    # the scheduler's events (session 92's Dask audit: the dask runner printed none)
    err = capsys.readouterr().err
    for seed in range(N_SEEDS):
        n = OVERRIDES["fit.n_evals"]
        assert err.count(f"fit seed {seed}: {n}/{n} evaluations, best loss ") == 1, err


def test_store_and_results_on_s3(base_run, scene_dir, s3_server, monkeypatch):  # noqa: F811
    import fsspec

    monkeypatch.setenv("AWS_ACCESS_KEY_ID", s3_server.key)
    monkeypatch.setenv("AWS_SECRET_ACCESS_KEY", s3_server.secret)
    monkeypatch.setenv("AWS_DEFAULT_REGION", s3_server.region)
    monkeypatch.setenv("AWS_ENDPOINT_URL", s3_server.endpoint)
    root = f"s3://{s3_server.bucket}/flows"
    local = Path(str(base_run["store"])) / "s3-copy"
    _copy_without_late_results(base_run["store"], local)
    fs = fsspec.filesystem("s3", endpoint_url=s3_server.endpoint, skip_instance_cache=True)
    fs.put(str(local) + "/", f"{s3_server.bucket}/flows/", recursive=True)
    shutil.rmtree(local)

    # upstream stages are read back from the results on S3, the fit and later stages are
    # computed against S3 and their results written there
    first = _run("plotA", root, scene_dir)
    assert _executed(first["states"]) == sorted(
        [*(f"fit_seed-{s}" for s in range(N_SEEDS)), *LATE_STAGES]
    )
    _same_result(first, base_run["first"])
    second = _run("plotA", root, scene_dir)
    assert set(second["states"].values()) == {"Cached"}
    results = fs.find(f"{s3_server.bucket}/flows/plotA/{CROP}/{DATE}/.prefect")
    assert any("/report/" in p for p in results) and any("/fit_seed/" in p for p in results)
    assert first["report"].startswith("s3://")
    # a metrics.json edited on the bucket (LAI 99) was served and published by the season
    # (session 91's S3 audit): its stage runs again and writes the answer back
    key = f"{s3_server.bucket}/flows/plotA/{CROP}/{DATE}/metrics/metrics.json"
    fs.pipe(key, b'{"lai": 99}')
    third = _run("plotA", root, scene_dir)
    assert "metrics" in _executed(third["states"])
    assert json.loads(fs.cat(key))["lai"] == pytest.approx(first["metrics"]["lai"])


def test_imported_poses_of_other_photos_are_named(prefect_harness, scene_dir, tmp_path):
    """A COLMAP model imported through the flow whose images are not the ingested photos
    (renamed on the way: other names, other stems) fails in the poses stage, naming the
    mismatch, and nothing downstream runs."""
    from flows.scene import run_scene

    photos = tmp_path / "renamed"
    photos.mkdir()
    for i, p in enumerate(sorted((scene_dir / "images").iterdir())):
        (photos / f"plot_{i:03d}{p.suffix}").write_bytes(p.read_bytes())
    store = tmp_path / "store"
    with pytest.raises(InputError, match=r"name 16 images but only 0 of them were ingested"):
        run_scene(
            "plotC",
            CROP,
            DATE,
            images=str(photos),
            poses=str(scene_dir / "colmap" / "sparse" / "0"),
            overrides=OVERRIDES,
            store=str(store),
        )
    manifest = SceneStore(str(store)).load_manifest(SceneKey("plotC", CROP, DATE))
    assert manifest.stages["ingest"].status == "done"
    assert manifest.stages["poses"].status == "failed"
    assert "were ingested" in manifest.stages["poses"].error
    assert "surfaces" not in manifest.stages or manifest.stages["surfaces"].status != "done"


def _dead_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_field_notes_give_a_dates_camera_height_and_row_spacing(scene_dir, tmp_path):
    """Nadir soybean photos at a hand-held scale now stop and ask for the cameras' height
    (session 97), and ``season --camera-height`` gives every date the same one: a season's one
    drone date among walks gives its own in its ``known.json`` (``camera_height``, and
    ``row_spacing`` likewise), under the run's own flags, which are said to go over it."""
    from flows.scene import notes_overridden, prepare

    photos = tmp_path / "images"
    shutil.copytree(scene_dir / "images", photos)
    notes = {"camera_height": 13, "row_spacing": 0.38, "num_nodes": 6}
    (photos / "known.json").write_text(json.dumps(notes))
    store = str(tmp_path / "store")
    req = prepare("plotA", CROP, DATE, str(photos), None, None, store)
    assert req.config["poses"]["camera_height"] == 13
    assert req.config["layout"]["row_spacing"] == 0.38
    assert req.config["fit"]["box"] == {"num_nodes": 6}
    mine = prepare("plotA", CROP, DATE, str(photos), None, {"poses.camera_height": 12.5}, store)
    assert mine.config["poses"]["camera_height"] == 12.5
    assert notes_overridden(notes, {"poses.camera_height": 12.5, "layout.row_spacing": 0.38}) == [
        "--camera-height 12.5 goes over known.json's 13"
    ]
    # a run given a distance between two photos: its scale goes over the notes' height (the
    # two together were refused as "not both")
    two = sorted(p.name for p in photos.glob("*.jpg"))[:2]
    measured = {"poses.camera_distance": [*two, 1.5]}
    req = prepare("plotA", CROP, DATE, str(photos), None, measured, store)
    assert req.config["poses"]["camera_height"] is None
    assert req.config["poses"]["camera_distance"] == [*two, 1.5]
    assert notes_overridden(notes, measured) == [
        "--camera-distance goes over known.json's camera_height 13"
    ]
    for text, error, message in (
        ('{"camera_height": -1}', InputError, "known.json: camera_height must be a positive"),
        ('{"row_spacing": "30in"}', InputError, "known.json: row_spacing must be a positive"),
        ('{"camera_height": 140}', ConfigError, r"centimetres.*with the field notes in .*known"),
    ):
        (photos / "known.json").write_text(text)
        with pytest.raises(error, match=message):
            prepare("plotA", CROP, DATE, str(photos), None, None, store)


def test_bad_input_fails_before_any_work(scene_dir, tmp_path, monkeypatch):
    from flows.scene import prepare, run_scene

    store = str(tmp_path / "store")
    with pytest.raises(ConfigError, match="invalid site"):
        run_scene("plot A/../x", CROP, DATE, images=str(scene_dir / "images"), store=store)
    with pytest.raises(InputError, match="no images found"):
        run_scene("plotA", CROP, DATE, images=str(tmp_path / "missing"), store=store)
    card = tmp_path / "card"  # a camera's card copied whole: the photos two levels down
    shutil.copytree(scene_dir / "images", card / "DCIM" / "100MEDIA")
    with pytest.raises(InputError, match="the photos are in 'DCIM/100MEDIA' below it"):
        prepare("plotA", CROP, DATE, str(card), None, None, store)
    shutil.copytree(scene_dir / "images", card / "DCIM" / "101MEDIA")  # past 999 photos
    with pytest.raises(InputError, match=r"in 2 folders below it \('DCIM/100MEDIA', 'DCIM/101"):
        prepare("plotA", CROP, DATE, str(card), None, None, store)
    # a photo instead of their folder, and fewer photos than ingest takes: named here, not
    # after Prefect has started and the scene's lease and manifest are written
    one = sorted((scene_dir / "images").glob("*.jpg"))[0]
    with pytest.raises(InputError, match="is a file, not a folder of photos"):
        prepare("plotA", CROP, DATE, str(one), None, None, store)
    two = tmp_path / "two"
    two.mkdir()
    for p in sorted((scene_dir / "images").glob("*.jpg"))[:2]:
        shutil.copy(p, two / p.name)
    with pytest.raises(InputError, match="holds 2 JPEG/PNG photo.s.; at least 3 are needed"):
        prepare("plotA", CROP, DATE, str(two), None, None, store)
    heic = tmp_path / "heic"  # a phone's own format: named, not "0 JPEG/PNG photos"
    heic.mkdir()
    for i in range(4):
        (heic / f"IMG_{i}.HEIC").write_bytes(b"\0\0\0\x18ftypheic" + bytes(16))
    with pytest.raises(InputError, match="holds 0 JPEG/PNG photo.s. .its HEIC files CropCraft"):
        prepare("plotA", CROP, DATE, str(heic), None, None, store)
    for pair in (["IMG_9999.jpg", one.name], [one.name, one.name]):  # not after SfM
        hint = {"poses.camera_distance": [*pair, 2.5]}
        with pytest.raises(InputError, match="poses.camera_distance names"):
            prepare("plotA", CROP, DATE, str(scene_dir / "images"), None, hint, store)
    with pytest.raises(ConfigError, match="unknown setting"):
        prepare("plotA", CROP, DATE, str(scene_dir / "images"), None, {"fit.n_eval": 3}, store)
    with pytest.raises(ConfigError, match="fit.method=mlp: the scene flow maps optimiser seeds"):
        prepare("plotA", CROP, DATE, str(scene_dir / "images"), None, {"fit.method": "mlp"}, store)
    for bad, match in (
        ({"consistency.max_views": 0}, "consistency.max_views"),
        ({"consistency.warn": 1.5}, "consistency.warn"),
        ({"observe.prediction_blur": -0.01}, "observe.prediction_blur must be"),
        ({"observe.prediction_blur": "voxel"}, "observe.prediction_blur must be"),
        ({"observe.preset.prediction_blur_m": 0.01}, "set observe.prediction_blur"),
        # not finite: SfM would run for minutes before the poses stage refused it
        ({"poses.camera_height": math.nan}, "poses.camera_height must be a positive"),
        ({"poses.camera_height": math.inf}, "poses.camera_height must be a positive"),
        ({"poses.prior_camera_height": math.nan}, "poses.prior_camera_height must be"),
        ({"poses.camera_distance": ["a.png", "b.png", math.inf]}, "camera_distance must be"),
        # the kind of every setting: --set keeps a value that is not JSON as text
        ({"fit.n_seeds": "abc"}, "fit.n_seeds must be a whole number, got 'abc'"),
        ({"fit.n_seeds": 10.5}, "fit.n_seeds must be a whole number"),
        ({"fit.n_evals": math.nan}, "fit.n_evals must be a whole number"),
        ({"layout.row_spaceing": 0.5}, "unknown setting layout.row_spaceing: the layout's are"),
        ({"fit.n_seeds": True}, "fit.n_seeds must be a whole number"),
        ({"poses.guided_matching": "False"}, "poses.guided_matching must be true or false"),
        ({"fit.common_random_numbers": "no"}, "fit.common_random_numbers must be true or"),
        ({"observe.image_scale": "abc"}, "observe.image_scale must be a number"),
        ({"observe.image_scale": None}, "observe.image_scale must be a number"),
        ({"poses.matcher": "foo"}, "poses.matcher must be auto, exhaustive or sequential"),
        ({"poses.num_threads": 0}, "poses.num_threads must be at least 1"),
        ({"ingest.max_size": 8}, "ingest.max_size must be at least 16 or null"),
        ({"rowfit.scale": 0}, "rowfit.scale must be a positive number or null"),
        ({"report.n_thumbnails": "six"}, "report.n_thumbnails must be a whole number"),
        ({"fit.canopies_per_eval": "two"}, "canopies_per_eval must be a whole number"),
        ({"fit.local_share": "half"}, "local_share must be a number in"),
        ({"poses.imported_metric": "yes"}, "poses.imported_metric must be true, false or auto"),
        ({"generate.seed": 2**32}, "generate.seed must be below 2\\*\\*32"),
        # the optimiser's, the point cloud's and the presets' (a traceback before)
        ({"fit.refit_every": 0}, "refit_every=0"),
        ({"surfaces.n_points": "abc"}, "surfaces.n_points must be a whole number"),
        ({"surfaces.n_points": -5}, "surfaces.n_points must be a whole number"),
        ({"observe.preset": 5}, "observe.preset' must be a mapping"),
        ({"rowfit.preset": []}, "rowfit.preset' must be a mapping"),
    ):
        with pytest.raises(ConfigError, match=match):
            prepare("plotA", CROP, DATE, str(scene_dir / "images"), None, bad, store)
    monkeypatch.setenv("AWS_ACCESS_KEY_ID", "x")
    monkeypatch.setenv("AWS_SECRET_ACCESS_KEY", "y")
    monkeypatch.setenv("AWS_ENDPOINT_URL", f"http://127.0.0.1:{_dead_port()}")
    t = time.perf_counter()
    with pytest.raises(StoreError, match="not reachable"):
        run_scene("plotA", CROP, DATE, images=str(scene_dir / "images"), store="s3://nope/x")
    assert time.perf_counter() - t < 30
    # photos in a bucket whose endpoint is down: one named error, not botocore's traceback
    import s3fs

    s3fs.S3FileSystem.clear_instance_cache()  # not another test's client, on its endpoint
    t = time.perf_counter()
    with pytest.raises(
        InputError, match="cannot list images at 's3://nope/photos': EndpointConnectionError"
    ):
        prepare("plotA", CROP, DATE, "s3://nope/photos", None, None, store)
    assert time.perf_counter() - t < 60
    assert not (tmp_path / "store").exists() or not any((tmp_path / "store").rglob("*.npz"))


def test_a_measured_distance_between_two_photos_sets_the_scale(base_run, scene_dir):
    """Imported poses read as non-metric are levelled; the measured distance between two
    photos' cameras (``--camera-distance``) sets their scale exactly, and the row fit keeps
    it (and says so) instead of measuring it from the rows."""
    frames = json.loads((scene_dir / "transforms.json").read_text())["frames"]
    a, b = (np.array(frames[i]["transform_matrix"])[:3, 3] for i in (2, 9))
    names = [Path(frames[i]["file_path"]).name for i in (2, 9)]
    hint = {
        "poses.imported_metric": False,
        "poses.camera_distance": [*names, float(np.linalg.norm(a - b))],
    }
    out = _run("plotD", base_run["store"], scene_dir, {**OVERRIDES, **hint})
    assert set(out["states"].values()) == {"Completed"}
    rowfit = SceneStore(str(base_run["store"])).get_json(f"plotD/{CROP}/{DATE}/rowfit/rowfit.json")
    assert rowfit["scale_source"] == "camera_distance" and rowfit["scale"] == 1.0
    with pytest.raises(ConfigError, match="camera_distance must be"):
        _run("plotD", base_run["store"], scene_dir, {"poses.camera_distance": ["a", 2.0]})
    with pytest.raises(ConfigError, match="not both"):
        _run("plotD", base_run["store"], scene_dir, {**hint, "poses.camera_height": 1.4})
    # synth's transforms.json reads as a metric AR capture: a hint cannot scale it
    with pytest.raises(InputError, match="read as metric, so a camera height or distance"):
        _run("plotM", base_run["store"], scene_dir, {**OVERRIDES, "poses.camera_height": 1.4})


def test_ar_poses_in_their_own_frame_read_the_scene_as_levelled_ones(base_run, scene_dir, tmp_path):
    """The scene's poses as Record3D's ns-process-data writes a phone's ARKit poses (metres, y
    up, the origin where tracking started): the poses stage turns them onto their y axis
    exactly and moves them onto the plot, and the row fit finds the base run's ground and row
    camera there (before, they were used as given and the scene box held no plot)."""
    doc = json.loads((scene_dir / "transforms.json").read_text())
    first = np.array(doc["frames"][0]["transform_matrix"])[:3, 3]
    arkit = np.eye(4)
    arkit[:3, :3] = [[1, 0, 0], [0, 0, 1], [0, -1, 0]]  # z up -> y up
    arkit[:3, 3] = -(arkit[:3, :3] @ first)
    for f in doc["frames"]:
        f["transform_matrix"] = (arkit @ np.array(f["transform_matrix"])).tolist()
    poses_file = tmp_path / "transforms.json"
    poses_file.write_text(json.dumps(doc))
    from flows.scene import run_scene

    out = run_scene(
        "plotR",
        CROP,
        DATE,
        images=str(scene_dir / "images"),
        poses=str(poses_file),
        overrides={**OVERRIDES, "surfaces.bbox": "auto"},
        store=str(base_run["store"]),
        runner="threads",
    )
    assert set(out["states"].values()) == {"Completed"}
    s = SceneStore(str(base_run["store"]))
    poses = s.get_json(f"plotR/{CROP}/{DATE}/poses/poses.json")
    levelled = {Path(v["name"]).stem: np.array(v["camera"]["cam_to_world"]) for v in poses["views"]}
    truth = {Path(f["file_path"]).stem: np.array(f["transform_matrix"]) for f in json.loads(
        (scene_dir / "transforms.json").read_text())["frames"]}  # fmt: skip
    shift = [levelled[n][:3, 3] - truth[n][:3, 3] for n in truth]
    np.testing.assert_allclose(shift, np.repeat(shift[:1], len(shift), 0), atol=1e-9)
    for n in truth:  # the same rotation: gravity exactly, no tilt from the cameras' estimate
        np.testing.assert_allclose(
            levelled[n][:3, :3], truth[n][:3, :3] @ np.diag([1, -1, -1]), atol=1e-9
        )
    assert np.hypot(*shift[0][:2]) < 0.25 and abs(shift[0][2]) < 0.25
    here = s.get_json(f"plotR/{CROP}/{DATE}/rowfit/rowfit.json")
    base = s.get_json(f"plotA/{CROP}/{DATE}/rowfit/rowfit.json")
    assert np.degrees(np.arccos(min(1.0, here["ground_normal"][2]))) < 1.0
    cam = np.array(here["camera_in_scene"]["cam_to_world"])
    ref = np.array(base["camera_in_scene"]["cam_to_world"])
    assert abs(float(cam[:3, 0] @ ref[:3, 0])) > np.cos(np.radians(2.0))  # along the same row
    assert abs(cam[2, 3] - shift[0][2] - ref[2, 3]) < 0.05  # the same height over the soil


def test_a_measured_camera_height_sets_the_scale_above_the_fitted_ground(base_run, scene_dir):
    """Imported poses read as non-metric, levelled with the user's camera height: levelling
    puts the ground where the optical axes meet (on the canopy top here, not the soil), so its
    scale is a quarter off; the row fit measures the cameras' height above its fitted ground
    plane again and its scale is the true one."""
    transforms = json.loads((scene_dir / "transforms.json").read_text())
    centres = np.array([f["transform_matrix"] for f in transforms["frames"]])[:, :3, 3]
    height = float(np.median(centres[:, 2]))  # truth frame: ground z = 0
    hint = {"poses.imported_metric": False, "poses.camera_height": height}
    out = _run("plotH", base_run["store"], scene_dir, {**OVERRIDES, **hint})
    assert set(out["states"].values()) == {"Completed"}
    s = SceneStore(str(base_run["store"]))
    poses = s.get_json(f"plotH/{CROP}/{DATE}/poses/poses.json")
    levelled = np.median([v["camera"]["cam_to_world"][2][3] for v in poses["views"]])
    assert levelled == pytest.approx(height, rel=1e-6)  # the hint, above levelling's ground
    rowfit = s.get_json(f"plotH/{CROP}/{DATE}/rowfit/rowfit.json")
    assert rowfit["scale_source"] == "camera_height"
    true_scale = 1.0 / _levelled_scale(poses, centres)  # metres per levelled unit
    assert abs(true_scale - 1.0) > 0.1  # levelling's own scale (1) is well off ...
    assert rowfit["scale"] == pytest.approx(true_scale, rel=0.01)  # ... the row fit's is not


def _levelled_scale(poses: dict, true_centres: np.ndarray) -> float:
    """Scene units per metre of the levelled poses: their cameras' spread over the true ones'."""
    a = np.array([v["camera"]["cam_to_world"] for v in poses["views"]])[:, :3, 3]
    b = true_centres
    spread = lambda x: np.sqrt(((x - x.mean(0)) ** 2).sum(1).mean())  # noqa: E731
    return float(spread(a) / spread(b))


def test_a_failed_rerun_keeps_the_dates_last_answer_in_the_season_flagged(tmp_path):
    """The one date's photos replaced (a stray empty upload) and its rerun failed: the date's
    good answer went from the summary and the plot with it (session 91's season audit). It
    stays, marked failed with where and why; a date that never finished is listed as failed
    with no values, and a season of no values has no plot of an older night."""
    from flows.season import write_summary

    store = SceneStore(str(tmp_path / "store"))
    scene = SceneKey("plotA", CROP, DATE)
    store.put_bytes(f"{scene.prefix}/images/a.png", b"x")
    store.init_manifest(scene, {"images/a.png": "1"}, {})
    store.put_json(f"{scene.prefix}/metrics/metrics.json", {"lai": 1.2, "node_count": 7.0})
    store.update_stage(scene, "metrics", status="running")
    store.update_stage(scene, "metrics", status="done")
    first = write_summary(store, "plotA", CROP)
    png = f"plotA/{CROP}/season/summary.png"
    assert len(first["rows"]) == 1 and store.isfile(png)
    # refused tonight before any work (its known.json broken since): failed, values kept
    (row,) = write_summary(store, "plotA", CROP, {DATE: "known.json: not valid JSON"})["rows"]
    assert (row["status"], row["lai_m2_m2"]) == ("failed", 1.2)
    assert row["note"] == "not run: known.json: not valid JSON; the values are its run's before"
    store.init_manifest(scene, {"images/a.png": "2"}, {})  # new photos: its stages reset
    store.update_stage(scene, "fit_seed", status="running")
    store.update_stage(scene, "fit_seed", status="failed", error="no rows found")
    second = write_summary(store, "plotA", CROP)
    (row,) = second["rows"]
    assert row["lai_m2_m2"] == 1.2 and row["status"] == "failed"
    assert row["note"] == (
        "the last run failed at fit_seed: no rows found; the values are its run's before"
    )
    assert store.isfile(png)
    store.delete(f"{scene.prefix}/metrics/metrics.json")  # a date that never finished
    third = write_summary(store, "plotA", CROP)
    (row,) = third["rows"]
    assert row["lai_m2_m2"] is None and row["status"] == "failed" and third["png"] is None
    assert not store.isfile(png)
    assert row["note"] == "the last run failed at fit_seed: no rows found"


def test_report_opens_with_the_runs_warnings():
    """The console printed the run's warnings (an answer on the box's edge, the row view's
    coverage) and the report, read the next morning, had none of them."""
    from cropcraft_core.report import scene_report_html

    page = scene_report_html(
        "s/soybean/2024-07-01",
        warnings=["the answer lies on the edge of the soybean parameter box <b>", "26 % of"],
        info={"crop": "soybean"},
    )
    assert page.index("<h2>Warnings</h2>") < page.index("<th>crop</th>")
    assert "<li>the answer lies on the edge of the soybean parameter box &lt;b&gt;</li>" in page


def test_report_says_which_rows_answer_the_scene():
    """Fitted over its neighbour rows with ``rows.answer=mean``, the scene's answer is the
    rows' mean, but the rows table said row 0 was "the scene's answer above"."""
    from cropcraft_core.config import CanopyLayout
    from cropcraft_core.config.params import param_space
    from cropcraft_core.metrics.rows import compare_rows
    from cropcraft_core.report import scene_report_html

    base = {s.name: s.middle for s in param_space("soybean")}
    rows = [
        {"index": 0, "offset_m": 0.0, "params": base},
        {"index": 1, "offset_m": 0.76, "params": {**base, "leaf_length": 1.3}},
    ]
    table = compare_rows("soybean", rows, CanopyLayout(plot_length=1.0, plot_width=1.0), 0)
    for how, says in (
        ("best", "Row 0 is the row fit's best row, the scene's answer above;"),
        ("mean", "Row 0 is the row fit's best row, and the scene's answer above is the mean of"),
    ):
        page = scene_report_html("s/soybean/2024-07-01", rows={**table, "answer": how})
        assert says in page


def test_report_times_every_rows_seeds_and_answers():
    """Under neighbour rows the page timed only the best row's seeds, and under
    ``rows.answer=mean`` it timed the rows stage twice, once as the aggregate's."""
    from tasks.report import _timings

    rec = {"hashes": {}, "summary": {}}
    up = {"ingest": {**rec, "seconds": 1.0}, "aggregate": {**rec, "seconds": 5.0}}
    up |= {f"seed-{s}": {**rec, "seconds": 10.0} for s in range(2)}
    assert _timings(up) == {"ingest": 1.0, "fit_seed (x2)": 20.0, "aggregate": 5.0}
    up |= {f"seed-{s}@row_p1": {**rec, "seconds": 20.0} for s in range(2)}
    up |= {"aggregate@row_p1": {**rec, "seconds": 6.0}, "rows": {**rec, "seconds": 2.0}}
    up |= {"answer": up["rows"]}  # rows.answer=mean: the rows stage is the answer
    assert _timings(up) == {
        "ingest": 1.0,
        "fit_seed (x4 over 2 rows)": 60.0,
        "aggregate (x2 over 2 rows)": 11.0,
        "rows": 2.0,
    }


def test_report_builder_is_self_contained():
    from cropcraft_core.report import scene_report_html, season_csv, season_rows

    depth = np.full((8, 10), 0.8)
    depth[0, 0] = np.nan
    page = scene_report_html(
        "s/soybean/2024-07-01",
        thumbnails=[np.zeros((4, 6, 3), np.uint8)],
        observed_depth=depth,
        predicted_depth=depth + 0.1,
        metrics={
            "lai": 2.0,
            "definitions": {"lai": {"unit": "m2 m-2", "method": "x"}},
            # as the store gives it back: keys sorted
            "seeds": {
                "n_seeds": 2,
                "traits": {
                    "lai": {"values": [1.5, 2.5], "median": 2.0, "min": 1.5, "max": 2.5},
                    "node_count": {"values": [6.0, 8.0], "median": 7.0, "min": 6.0, "max": 8.0},
                },
            },
        },
        fit={
            "params": {"a": 1.0, "b": 9.0, "c": 0.9},
            "params_std": {"a": 0.1, "b": 0.0, "c": 0.01},
            "seed_params": [{"a": 1.0, "b": 9.0, "c": 0.9}],
            "config": {"box": {"b": 9, "c": [0.8, 1.0]}},
        },
        timings={"ingest": 1.0},
    )
    # a thumbnail, the observed and predicted depths and their colour key
    assert page.count("data:image/png;base64,") == 4 and "m2 m-2" in page
    assert "Warnings" not in page  # none given
    # the two spreads' definitions differ (params_std: ddof 1; the seeds' traits: ddof 0)
    assert "SD over seeds (÷n−1)" in page and "<th>SD (÷n)</th>" in page
    assert "b (given, not fitted)" in page and "c (searched 0.8 to 1)" in page
    # the narrowed parameter keeps its spread over the seeds beside its label
    assert "c (searched 0.8 to 1)</td><td class='num'>0.9</td><td class='num'>0.01<" in page
    assert "src='http" not in page
    # the seeds' traits in the traits' own order, the answer beside their median and range
    seeds = page[page.index("Traits over the 2 seeds' answers") :]
    assert seeds.index(">lai<") < seeds.index(">node_count<")
    assert "<td>lai</td><td class='num'>2</td><td class='num'>2</td><td class='num'>1.5" in seeds
    csv = season_csv(season_rows({"2024-07-01": {"lai": 2.0}, "2024-06-01": {"lai": 1.0}}))
    assert csv.splitlines()[1].startswith("2024-06-01,1")
    # an unknown value is an empty cell, NaN and inf (read from a metrics.json) too
    csv = season_csv(season_rows({"2024-06-01": {"lai": float("nan"), "plant_height_m": 1e999}}))
    assert csv.splitlines()[1] == "2024-06-01" + "," * (csv.splitlines()[0].count(","))


@pytest.mark.slow
def test_scene_flow_from_photos_alone(prefect_harness, tmp_path_factory):
    """The user path without poses: real pycolmap SfM on the default 50 walk-around photos
    (30 photos of this synthetic canopy are too few: 13 of 30 register), levelled poses, the
    crop's scene box, the metric scale measured from the rows (~10 min on 2 cores)."""
    from cropcraft_core.synth import make_scene
    from flows.scene import run_scene

    scene_dir = tmp_path_factory.mktemp("sfm-scene")
    make_scene(CROP, scene_dir, seed=0, views=50, resolution=(640, 480), metrics=False)
    store = tmp_path_factory.mktemp("store-sfm")
    overrides = {k: v for k, v in OVERRIDES.items() if not k.startswith("surfaces")}
    out = run_scene("plotS", CROP, DATE, images=str(scene_dir / "images"), overrides=overrides,
                    store=str(store))  # fmt: skip
    assert set(out["states"].values()) == {"Completed"}
    s = SceneStore(str(store))
    rowfit = s.get_json(f"plotS/{CROP}/{DATE}/rowfit/rowfit.json")
    assert rowfit["scale_source"] == "row_spacing"
    # the levelled frame is metric within a few per cent already; the rows refine it
    assert abs(rowfit["scale"] - 1) < 0.1
    assert abs(rowfit["ground_normal"][2]) > math.cos(math.radians(3))
    assert 0 < out["metrics"]["lai"] < 5


# --------------------------------------------------------------------------- benchmark flow


def test_benchmark_flow_maps_seeds_and_matches_the_in_process_benchmark(prefect_harness, tmp_path):
    """The accuracy benchmark as a flow (one task per method × scene × seed): the same table as
    ``bench_accuracy.run`` in this process, stored as JSON in the scene store."""
    from benchmarks.bench_accuracy import run
    from flows.benchmark import run_benchmark

    # the re-scoring rules' canopies and polish at a test's size
    budget = {
        "n_seeds": 2,
        "n_evals": 14,
        "n_initial": 8,
        "reevaluate_canopies": 4,
        "polish_evals": 6,
    }
    got = run_benchmark(
        "threads",
        crop="maize",
        methods=["bo", "random"],
        quick=True,
        scenes=2,
        store=str(tmp_path / "store"),
        overrides=budget,
    )
    ref = run("maize", ["bo", "random"], True, 2, log=lambda *_: None, overrides=budget)
    # maize's bo: candidates re-scored and the best polished (its default); bo-unpolished:
    # without the polish; bo-mean: the paper's mean of the seeds; bo-guarded: the median unless
    # the polished winner's basin is significantly deeper
    rows = {"bo", "bo-mean", "bo-median", "bo-guarded", "bo-unpolished", "random"}
    for m in rows:
        assert got["predictions"][m] == [p["params"] for p in ref["methods"][m]["predictions"]]
        assert got["errors"][m] == ref["methods"][m]["errors"]
    stored = SceneStore.connect(str(tmp_path / "store")).get_json(got["key"])
    assert set(stored["methods"]) == rows
    # the seeds' own answers around the truth, the same both ways
    spread = ref["methods"]["bo"]["seed_spread"]
    assert stored["methods"]["bo"]["seed_spread"] == spread
    assert got["seed_spread"]["bo"] == spread  # returned too: the CLI prints its line
    assert [s["scene"] for s in spread["scenes"]] == [0, 1]
    inside = [s["lai_min"] <= s["true_lai"] <= s["lai_max"] for s in spread["scenes"]]
    assert spread["truth_in_lai_range"] == np.mean(inside)
    assert [s["true_lai"] for s in spread["scenes"]] == [t["lai"] for t in ref["truths"]]
    assert stored["methods"]["bo-unpolished"]["budget"]["polish_evals"] == 0
    assert stored["methods"]["bo-mean"]["budget"]["combine"] == "mean"
    assert len(stored["truths"]) == 2 and stored["methods"]["bo"]["budget"]["n_evals"] == 14


def test_benchmark_flow_names_a_method_it_cannot_map(prefect_harness, tmp_path):
    from flows.benchmark import benchmark, run_benchmark
    from flows.runners import LocalProcessPool

    with pytest.raises(ConfigError, match="mlp"):
        run_benchmark("threads", crop="maize", methods=["bo", "mlp"], store=str(tmp_path))
    with pytest.raises(ConfigError, match="scenes must be a whole number >= 1, got 0"):
        run_benchmark("threads", crop="maize", methods=["bo"], scenes=0, store=str(tmp_path))
    # a deployment's run (no run_benchmark) maps its seeds over a bounded pool of processes,
    # not Prefect's default thread pool that starts every seed at once
    assert isinstance(benchmark.task_runner, LocalProcessPool)


def test_pooled_row_cameras_outside_the_reconstruction_are_left_out(base_run, scene_dir):
    """``observe.preset.views_*`` pools the observation over row cameras; on the test scene's
    small reconstruction, views that show more without a surface than the row camera's own
    view (and than 18 %) are left out: the observe record, the scene's summary, the stored
    observation and the report say which, and every kept view's share is within the limit."""
    store = SceneStore(str(base_run["store"]))
    scene = f"plotA/{CROP}/{DATE}"
    limit = max(0.18, base_run["first"]["observation"]["no_surface_fraction"])
    overrides = {**OVERRIDES, "observe.preset.views_along": 3, "observe.preset.views_across": 1}
    out = _run("plotA", base_run["store"], scene_dir, overrides)
    seen = out["observation"]
    left = seen["views_left_out"]
    assert seen["views_pooled"] + len(left) == 9 and left and seen["views_pooled"] > 1
    assert all(share > limit for *_, share in left)
    obs = Observation.load(io.BytesIO(store.get_bytes(f"{scene}/observe/observation.npz")))
    assert obs.meta["views_left_out"] == left and len(obs.meta["views"]) == seen["views_pooled"]
    assert all(share <= limit for share in obs.meta["views_outside"])
    assert {tuple(o) for o in obs.meta["views"]}.isdisjoint((dx, dy) for dx, dy, _ in left)
    html = store.get_bytes(f"{scene}/report/report.html").decode()
    assert f"{seen['views_pooled']} of 9 (left out, outside the reconstruction" in html
    # the single camera's observation is served again from its own key
    back = _run("plotA", base_run["store"], scene_dir)
    assert "views_pooled" not in back["observation"]
    assert back["params"] == base_run["first"]["params"]


def test_neighbour_rows_are_fitted_beside_the_best_row_whose_answer_stays_cached(
    base_run, scene_dir
):
    """``rows.neighbours`` observes the rows beside the best one and fits each alone: the best
    row's observation, seeds and answer stay cached; every kept neighbour gets its own
    observation, seeds and answer under ``row_p1/`` keys; the rows stage lays the answers side
    by side; a neighbour whose view lies outside the reconstruction is listed and left out.
    ``rows.answer=best`` keeps the best row's answer as the scene's (row 0's traits are the
    scene's metrics), ``mean`` answers with the rows' mean, refitting nothing."""
    from flows.season import write_summary
    from flows.service_cli import scene_status

    store = SceneStore(str(base_run["store"]))
    scene = f"plotA/{CROP}/{DATE}"
    # the test scene's reconstruction is small and its best row lies off its centre: its own
    # view lacks surface over 42 %, so the limit is that (over the default 18 %), which keeps
    # a row on one side and leaves the others out
    limit = max(0.18, base_run["first"]["observation"]["no_surface_fraction"])
    overrides = {**OVERRIDES, "rows.neighbours": 2, "rows.answer": "best"}
    _run("plotA", base_run["store"], scene_dir)  # whatever earlier tests left: the default
    out = _run("plotA", base_run["store"], scene_dir, overrides)
    executed = set(_executed(out["states"]))
    listed = {e["index"]: e for e in store.get_json(f"{scene}/rows/rows.json")["rows"]}
    kept = sorted(k for k in listed if k != 0)
    tried = {e["index"]: e for e in store.get_json(f"{scene}/rows/rows.json")["tried"]}
    assert sorted(tried) == [-2, -1, 1, 2]
    assert kept and {int(k) for k in out["rows"]["left_out"]} == set(tried) - set(kept)
    assert all(tried[k]["no_surface_fraction"] <= limit for k in kept)
    assert all(v > limit for v in out["rows"]["left_out"].values())
    labels = {k: ("row_p" if k > 0 else "row_m") + str(abs(k)) for k in kept}
    assert executed == {
        "observe_rows",
        "rows",
        "report",
        *(f"fit_seed-{s}@{labels[k]}" for k in kept for s in range(N_SEEDS)),
        *(f"aggregate@{labels[k]}" for k in kept),
    }
    assert out["params"] == base_run["first"]["params"]
    rows = out["rows"]
    assert rows["n_rows"] == len(kept) + 1 and set(rows["lai"]) == {"0", *map(str, kept)}
    assert rows["lai"]["0"] == pytest.approx(out["metrics"]["lai"], rel=1e-9)
    # each neighbour: its own observation (the camera moved across the rows), seeds, answer
    best = Observation.load(io.BytesIO(store.get_bytes(f"{scene}/observe/observation.npz")))
    for k in kept:
        obs = Observation.load(
            io.BytesIO(store.get_bytes(f"{scene}/observe/{labels[k]}/observation.npz"))
        )
        shift = obs.camera.cam_to_world[:3, 3] - best.camera.cam_to_world[:3, 3]
        assert shift @ best.camera.cam_to_world[:3, 1] == pytest.approx(listed[k]["offset_m"])
        # k row spacings from the best row (rows.snap: null), not on a fitted RANSAC line
        assert listed[k]["offset_m"] == pytest.approx(0.76 * k, abs=1e-9)
        assert tried[k]["snapped"] is False
        assert obs.meta["row"]["index"] == k
        fit = store.get_json(f"{scene}/fit/{labels[k]}/fit.json")
        assert fit["params"] == listed[k]["params"]
        for s in range(N_SEEDS):
            assert store.isfile(f"{scene}/fit/{labels[k]}/seed-{s}.npz")
    html = store.get_bytes(f"{scene}/report/report.html").decode()
    assert f"The answer over {len(kept) + 1} rows" in html
    (season,) = write_summary(store, "plotA", CROP)["rows"]
    assert season["rows_fitted"] == len(kept) + 1
    assert season["lai_rows_min_m2_m2"] == min(v for v in rows["lai"].values())
    assert season["lai_rows_max_m2_m2"] == max(v for v in rows["lai"].values())
    listing = {r["stage"]: r for r in scene_status(str(base_run["store"]), scene)}
    status = {stage: r["status"] for stage, r in listing.items()}
    assert status["observe_rows"] == status["rows"] == status["aggregate"] == "done"
    # the photos came from a folder, not the inbox: the manifest says where, so status walks
    # the cache for them; the best row's seeds, then the neighbour rows'
    assert store.load_manifest(SceneKey.parse(scene)).sources["images"] == str(scene_dir / "images")
    assert listing["observe_rows"]["cached"] == listing["rows"]["cached"] == "yes"
    assert listing["fit_seed"]["cached"] == f"{N_SEEDS}+{N_SEEDS * len(kept)} seeds"
    # unchanged: answered from the records, rows included
    hit = _cached(base_run["store"], scene_dir, overrides)
    assert hit is not None and hit["rows"] == rows
    with pytest.raises(ConfigError, match="rows.neighbours"):
        _cached(base_run["store"], scene_dir, {**OVERRIDES, "rows.neighbours": -1})
    with pytest.raises(ConfigError, match="rows.answer"):
        _cached(base_run["store"], scene_dir, {**overrides, "rows.answer": "median"})
    for bad in (0.5, 0, "near", True):
        with pytest.raises(ConfigError, match="rows.snap"):
            _cached(base_run["store"], scene_dir, {**overrides, "rows.snap": bad})

    # the scene's answer from every row's: the rows' answers are reused, only what follows the
    # answer is recomputed; the best row's own answer stays where it was
    out = _run("plotA", base_run["store"], scene_dir, {**overrides, "rows.answer": "mean"})
    # the metrics too, even where the rows' mean is the best row's answer (at this test's
    # budget two rows can end on the same design point): the answer is no longer one fit's
    # seeds, so their traits leave metrics.json (rows.json has the rows' spread)
    expected = ["export", "generate", "metrics", "report", "rows"]
    assert _executed(out["states"]) == sorted(expected)
    assert "seeds" not in store.get_json(f"{scene}/metrics/metrics.json")
    assert "lai_seeds_min" not in out["metrics"]
    answers = [listed[k]["params"] for k in sorted(listed)]
    for name, value in out["params"].items():
        assert value == pytest.approx(np.mean([a[name] for a in answers]), rel=1e-12)
        assert out["params_std"][name] == pytest.approx(np.std([a[name] for a in answers]))
    assert store.get_json(f"{scene}/fit/fit.json")["params"] == base_run["first"]["params"]
    assert store.get_json(f"{scene}/generate/canopy.json")["params"] == out["params"]
    html = store.get_bytes(f"{scene}/report/report.html").decode()
    assert f"mean of {len(kept) + 1} rows" in html and "SD over rows" in html
    n = len(kept) + 1  # every row's seeds and answer timed, the rows stage once
    assert f"fit_seed (x{N_SEEDS * n} over {n} rows)" in html
    assert f"aggregate (x{n} over {n} rows)" in html and html.count("<td>rows</td>") == 1
    (season,) = write_summary(store, "plotA", CROP)["rows"]
    assert season["rows_fitted"] == len(kept) + 1
    assert season["lai_m2_m2"] == pytest.approx(out["metrics"]["lai"])
    # the best row alone again: its answer, and the season no longer claims the rows
    out = _run("plotA", base_run["store"], scene_dir)
    assert out["params"] == base_run["first"]["params"] and out["rows"] is None
    (season,) = write_summary(store, "plotA", CROP)["rows"]
    # the season tells a rows run's canopy from the best row's by what the generate stage
    # built it from (flows.season._rows), also where the rows' mean is exactly the best row's
    # answer and the parameters cannot tell them apart
    assert season["rows_fitted"] is None


def test_field_notes_beside_the_photos_are_the_fits_known_parameters(base_run, scene_dir, tmp_path):
    """``known.json`` beside a date's photos (the nodes counted in the field that day) fixes
    those parameters for that date's fit: the seeds are refitted with it, the answer carries
    it, the stages before the fit stay cached; a run's own ``--param`` goes over the notes;
    a bad notes file is named before any work. (Last in the module: it writes plotA's fit.)"""
    from flows.scene import prepare, run_scene
    from flows.season import write_summary

    photos = tmp_path / "images"
    shutil.copytree(scene_dir / "images", photos)  # the same files and times: the same inputs
    (photos / "known.json").write_text(json.dumps({"num_nodes": 6}))
    store = base_run["store"]
    out = run_scene(
        "plotA",
        CROP,
        DATE,
        images=str(photos),
        poses=str(scene_dir / "transforms.json"),
        overrides=OVERRIDES,
        store=str(store),
    )
    executed = _executed(out["states"])
    assert any(k.startswith("fit_seed") for k in executed) and "ingest" not in executed
    fit = SceneStore(str(store)).get_json(f"plotA/{CROP}/{DATE}/fit/fit.json")
    assert fit["params"]["num_nodes"] == 6.0 == out["params"]["num_nodes"]
    assert fit["config"]["box"] == {"num_nodes": 6} and fit["params_std"]["num_nodes"] == 0.0
    season = write_summary(SceneStore(str(store)), "plotA", CROP)
    assert season["rows"][0]["parameters_given"] == "num_nodes=6"
    mine = prepare("plotA", CROP, DATE, str(photos), None, {"fit.box.num_nodes": 7}, str(store))
    assert mine.config["fit"]["box"] == {"num_nodes": 7}
    # notes and settings that fix every parameter: the notes are named beside the settings
    rest = {f"fit.box.{p}": 1.0 for p in ("petiole_angle", "petiole_length", "leaf_length")}
    rest["fit.box.internode_length"] = 1.0
    with pytest.raises(ConfigError, match=r"nothing is left to fit \(with the field notes in "):
        prepare("plotA", CROP, DATE, str(photos), None, rest, str(store))
    for text, message in (
        ("[6]", "known.json: must be a JSON object of soybean parameters"),
        ('{"nodes": 6}', "known.json: unknown soybean parameter 'nodes'"),
        ('{"num_nodes": 6', "known.json: not valid JSON"),
    ):
        (photos / "known.json").write_text(text)
        with pytest.raises(InputError, match=message):
            prepare("plotA", CROP, DATE, str(photos), None, OVERRIDES, str(store))


def test_the_scene_dask_deployments_flow_runs_the_scene_on_its_runner(base_run, scene_dir):
    """``process_scene`` (the ``scene-dask`` deployment) runs ``reconstruct_scene`` as a
    subflow on the runner it is given: here threads, on the computed scene, all cached and the
    same answer; a bad runner is named before any work."""
    from flows.scene import process_scene

    _run("plotA", base_run["store"], scene_dir)  # whatever earlier tests left: the default
    images, poses = str(scene_dir / "images"), str(scene_dir / "transforms.json")
    out = process_scene(
        "plotA", CROP, DATE, images, poses, OVERRIDES, str(base_run["store"]), runner="threads"
    )
    assert _executed(out["states"]) == []
    assert out["params"] == base_run["first"]["params"]
    with pytest.raises(ConfigError, match="runner"):
        process_scene(
            "plotA", CROP, DATE, images, poses, OVERRIDES, str(base_run["store"]), runner="bogus"
        )


def test_a_remote_cluster_with_local_paths_is_warned_of(scene_dir, tmp_path):
    """Stages on another machine's Dask workers read and write their own disks: local store
    and photo paths are warned of (a mount every worker shares is valid), local runners and a
    cluster on this machine are not."""
    import warnings

    from flows.scene import prepare, warn_local_paths_on_a_remote_cluster

    req = prepare("plotA", CROP, DATE, str(scene_dir / "images"), None, None, str(tmp_path))
    with pytest.warns(UserWarning, match="10.0.0.5 runs the stages.*store and photos"):
        warn_local_paths_on_a_remote_cluster("dask://10.0.0.5:8786", req)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for runner in ("processes", "threads", "dask", "dask://127.0.0.1:8786"):
            warn_local_paths_on_a_remote_cluster(runner, req)


def test_a_smaller_fit_budget_keeps_the_papers_share_of_random_points():
    """``--set fit.n_evals=200`` (the help's own example) kept 200 random points: no GP step,
    a random search named bo; a budget under 200 was refused, naming n_initial without its
    section. The initial design is now 40 % of the budget unless given, as `cropcraft fit`'s."""
    from flows.scene import resolve_config

    def initial(**sets):
        return resolve_config(CROP, {f"fit.{k}": v for k, v in sets.items()})["fit"]["n_initial"]

    assert (initial(), initial(n_evals=200), initial(n_evals=100)) == (200, 80, 40)
    assert initial(n_evals=100, n_initial=30) == 30
    assert resolve_config(CROP, {"fit": {"n_evals": 50, "n_initial": 10}})["fit"]["n_initial"] == 10
    with pytest.raises(ConfigError, match=r"fit settings \(fit\.\*\): need 2 <= n_initial"):
        resolve_config(CROP, {"fit.n_evals": 50, "fit.n_initial": 60})


def test_a_camera_height_in_other_units_is_refused_before_any_work():
    """`--camera-height 140` (centimetres) for a soybean walk passed, and the run failed in
    the stereo naming the poses and the box; a height no capture has (over the 120 m drones
    may fly, under 0.3 m) is refused with the likely slip. Drone heights for either crop pass:
    a 30 m soybean flight and a phone 0.6 m over maize were refused as other units when the
    limit was 20x the crop's usual capture height (session 96's capture audit)."""
    from flows.scene import resolve_config

    with pytest.raises(ConfigError, match=r"camera_height 140 m is outside .*usual capture height "
                       r"is 1.4 m\): is it in centim"):  # fmt: skip
        resolve_config("soybean", {"poses.camera_height": 140})
    with pytest.raises(ConfigError, match=r"camera_height 120.0001 m is outside"):
        resolve_config("soybean", {"poses.camera_height": 120.0001})
    with pytest.raises(ConfigError, match=r"camera_height 0.05 m .* in another unit"):
        resolve_config("maize", {"poses.camera_height": 0.05})
    for crop, height in (("soybean", 1.2), ("soybean", 4.0), ("soybean", 30.0), ("maize", 0.6),
                         ("maize", 13.0), ("maize", 120.0)):  # fmt: skip
        assert resolve_config(crop, {"poses.camera_height": height})["poses"]["camera_height"]


def test_a_date_of_an_older_release_keeps_its_coverage_warning_in_the_season(tmp_path):
    """A date run before reports listed their warnings (report/warnings.json) read with an
    empty note in the season's summary though 79 % of its row view had no surface: the
    cleanest-looking date of the season (session 92's upgrade audit). Its observation keeps
    the coverage, which is warned of; a listed report's warnings are read as they are."""
    import io

    from cropcraft_core.config import default_layout
    from cropcraft_core.export import write_ply
    from cropcraft_core.fit.geometry import observe_geometry
    from cropcraft_core.procedural import generate_canopy, plot_region
    from flows.season import date_warnings

    lay = default_layout("soybean", plot_length=2.0, plot_width=2.4)
    c = generate_canopy("soybean", {"num_nodes": 5}, lay, seed=1, region=plot_region(lay, 0.3))
    write_ply(tmp_path / "c.ply", c.mesh)
    obs, _ = observe_geometry(str(tmp_path / "c.ply"), "soybean")
    obs.meta["no_surface_fraction"] = 0.79
    buf = io.BytesIO()
    obs.save(buf)
    store = SceneStore(str(tmp_path / "store"))
    scene = SceneKey("plotA", "soybean", "2024-07-01")
    store.put_bytes(f"{scene.prefix}/observe/observation.npz", buf.getvalue())
    said = date_warnings(store, scene)
    assert len(said) == 1 and said[0].startswith("79.0 % of the row camera's view has no")
    store.put_json(f"{scene.prefix}/report/warnings.json", ["listed"])
    assert date_warnings(store, scene) == ["listed"]


def test_a_run_whose_dask_cluster_lost_every_worker_fails_naming_it(
    prefect_harness, tmp_path, monkeypatch
):
    """A worker that cannot import the project ends its whole ``dask worker`` command at its
    first task, and the run waited on that task silently for good (session 93's Dask audit: a
    nightly season would hang). With no worker for ``NO_WORKER_S`` the run's tasks are
    cancelled, naming the cause."""
    from prefect import flow

    import flows.dask_runner as dask_runner
    from flows.runners import local_cluster, make_task_runner
    from tests.dask_stages import long_stage

    monkeypatch.setattr(dask_runner.DaskTaskRunnerWithProgress, "no_worker_s", 3.0)
    started = tmp_path / "started"

    # the runner's own cluster: a plain LocalCluster's nanny writes Dask's malloc pin into this
    # process's environment for good (os.environ.update), and later clusters' workers inherit it
    with local_cluster(
        n_workers=1, threads_per_worker=1, processes=True, dashboard_address=None
    ) as cluster:

        @flow(task_runner=make_task_runner(f"dask://{cluster.scheduler_address[6:]}"))
        def one_long_stage() -> int:
            return long_stage.submit(str(started)).result()

        def end_the_workers() -> None:  # as the audit's worker did, at its first task
            deadline = time.monotonic() + 120
            while not started.exists() and time.monotonic() < deadline:
                time.sleep(0.2)
            cluster.scale(0)

        threading.Thread(target=end_the_workers, daemon=True).start()
        t0 = time.monotonic()
        with pytest.raises(Exception, match="has had no worker for 3 s") as err:
            one_long_stage()
        assert time.monotonic() - t0 < 100  # not the stage's 120 s, nor for good
        assert "deploy/README.md" in str(err.value)


def test_season_plot_marks_failed_dates_and_spans_days_around_one():
    """The season plot left a failed date off and drew a failed rerun's old values as a fresh
    answer (the PNG byte-identical before and after both failures); a first night's one date
    spanned 4 years, its own date unlabelled, the legend over its points (session 93's report
    audit)."""
    import datetime

    import matplotlib.pyplot as plt

    from cropcraft_core.report import season_figure, season_plot_png

    def day(date, status="done", lai=None):
        values = {} if lai is None else {"lai_m2_m2": lai, "plant_height_m": 0.5}
        return {"date": date, "status": status, **values, "leaf_angle_mean_deg": lai and 40.0}

    first = [day("2024-07-01", lai=1.1)]
    fig = season_figure(first, "plotA soybean")
    lo, hi = fig.axes[2].get_xlim()
    assert hi - lo <= 2 * 7 + 1  # days, not years
    fig.canvas.draw()
    labels = [t.get_text() for t in fig.axes[2].get_xticklabels()]
    assert "2024-07-01" in labels, labels
    legend = fig.axes[0].get_legend().get_window_extent()
    assert legend.x0 >= fig.axes[0].get_window_extent().x1  # beside the panel, not over it
    plt.close(fig)
    plain = season_plot_png([*first, day("2024-07-08", lai=1.3)])
    kept = season_plot_png([*first, day("2024-07-08", "failed", lai=1.3)])
    gone = season_plot_png([*first, day("2024-07-08", "failed")])
    assert len({plain, kept, gone}) == 3
    fig = season_figure([*first, day("2024-07-08", "failed", lai=1.3), day("2024-07-15", "failed")])
    said = [t.get_text() for t in fig.axes[0].get_legend().get_texts()]
    assert "failed: an earlier run's values" in said
    assert "failed: no values (summary.csv says why)" in said
    plt.close(fig)
    # last year's dates under the same site and crop: a series per year over the days of the
    # year, not one axis on which each season was a strip beside a year's gap (session 91)
    fig = season_figure(
        [day("2025-06-20", lai=0.4), day("2025-07-30", "failed"), *first, day("2024-08-02", lai=2)]
    )
    lo, hi = fig.axes[2].get_xlim()
    assert hi - lo <= (datetime.date(2000, 8, 2) - datetime.date(2000, 6, 20)).days + 2 * 7 + 1
    said = [t.get_text() for t in fig.axes[0].get_legend().get_texts()]
    assert (
        "LAI (leaf area / ground area) 2024" in said
        and "LAI (leaf area / ground area) 2025" in said
    )
    assert said.count("failed: no values (summary.csv says why)") == 1
    fig.canvas.draw()
    labels = [t.get_text() for t in fig.axes[2].get_xticklabels()]
    assert any(t.startswith("Jul") for t in labels) and not any("20" in t[:2] for t in labels), (
        labels
    )
    plt.close(fig)


def test_the_reports_warnings_hold_the_reconstruction_against_the_photos():
    """A run printed the reconstruction's net cover against its photos as a warning, but its
    report listed it only inside a table cell, and warnings.json (the season's note) not at
    all (session 93's report audit). The depth maps' caption said grey was "nothing seen" where
    it is the soil too, and keyed no colour."""
    from cropcraft_core.config import param_space
    from cropcraft_core.report import scene_report_html
    from cropcraft_core.surfaces.consistency import consistency_warning
    from tasks.report import run_warnings

    warning = consistency_warning(0.349, 0.038, 0.15)
    assert "no surface under 34.9 % of the plant" in warning and "(net cover -31.1 %" in warning
    upstream = {
        "ingest": {"summary": {"n_images": 50}},
        "poses": {"summary": {}},
        "surfaces": {"summary": {}},
        "rowfit": {"summary": {}},
        "observe": {"summary": {}},
        "consistency": {"summary": {"warning": warning}},
    }
    middle = {p.name: (p.low + p.high) / 2 for p in param_space(CROP)}
    assert run_warnings(CROP, upstream, {"params": middle}) == [warning]
    depth = np.full((20, 30), np.nan)
    depth[5:15, 5:25] = 0.6
    page = scene_report_html("s/soybean/2024-07-01", observed_depth=depth, predicted_depth=depth)
    assert "0.600 m (blue, near)" in page and "alt='colour key'" in page
    assert "grey = no canopy there (the soil, or no surface seen)" in page


def test_a_season_leaves_a_date_another_run_holds_to_that_run(prefect_harness, scene_dir, tmp_path):
    """Two overlapping seasons each ended Failed (their alerts firing) for the date the other
    was running, which both then listed done (session 93's overlap audit). A date another run
    holds is left to it: said, not failed."""
    from cropcraft_core.lease import hold_scene
    from flows.season import run_season

    store = SceneStore(str(tmp_path / "store"))
    date = "2024-07-08"
    for p in sorted((scene_dir / "images").iterdir()):
        store.put_bytes(f"plotB/{CROP}/{date}/images/{p.name}", p.read_bytes())
    with hold_scene(store, SceneKey("plotB", CROP, date), owner="flow run last-night"):
        out = run_season("plotB", CROP, str(tmp_path / "store"), OVERRIDES)
    assert out["state"] == "Completed" and out["failed"] == [] and out["busy"] == [date]
    assert out["scenes"][date].startswith("busy: scene plotB/soybean/2024-07-08 is being run by")
    assert "flow run last-night" in out["scenes"][date]


_WATCHED = """
import logging, signal, sys, time
import flows.watch
from flows.watch import RunWatch, end_this_run
logging.basicConfig(stream=sys.stderr)
if sys.argv[2:] == ["held"]:  # a SIGTERM Prefect holds while it reports to an API gone
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    flows.watch.END_GRACE_S = 1.0
with RunWatch([sys.argv[1]], end_this_run(logging.getLogger("run")), poll_s=0.2, api_lost_s=1.0):
    print("watching", flush=True)
    time.sleep(60)
"""


def _watched(run_id: str, api_url: str, *args: str) -> subprocess.Popen:
    env = {**os.environ, "PREFECT_API_URL": api_url, "PREFECT_SERVER_ANALYTICS_ENABLED": "false"}
    proc = subprocess.Popen(
        [sys.executable, "-c", _WATCHED, run_id, *args],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
    )  # fmt: skip
    assert proc.stdout.readline().strip() == "watching"
    return proc


def test_a_cancel_asked_of_prefect_or_a_lost_api_ends_a_run_in_its_own_process(prefect_harness):
    """A ``cropcraft run`` is the flow itself: a cancel from the UI or ``prefect flow-run
    cancel`` was ignored (the run finished and stayed "Cancelling"), and a Prefect server gone
    mid-run left it waiting for ever on a stage's future, holding the scene (session 95's
    operations audit). The watch ends such a process as SIGTERM does, the cancelled run marked
    Cancelled; a run going on undisturbed is left alone."""
    from prefect import flow
    from prefect.client.orchestration import get_client
    from prefect.client.schemas.objects import StateType
    from prefect.settings import PREFECT_API_URL
    from prefect.states import Cancelling, Running

    @flow
    def idle():
        pass

    with get_client(sync_client=True) as client:
        run = client.create_flow_run(idle)
        client.set_flow_run_state(run.id, Running())
        proc = _watched(str(run.id), PREFECT_API_URL.value())
        time.sleep(1.0)
        assert proc.poll() is None  # running: left alone
        client.set_flow_run_state(run.id, Cancelling())
        assert proc.wait(timeout=30) == -signal.SIGTERM
        assert f"flow run {run.id} was cancelled in Prefect" in proc.stderr.read()
        assert client.read_flow_run(run.id).state.type == StateType.CANCELLED
    with socket.socket() as s:  # a port nothing listens on: the server gone
        s.bind(("127.0.0.1", 0))
        gone = f"http://127.0.0.1:{s.getsockname()[1]}/api"
    proc = _watched(str(run.id), gone)
    assert proc.wait(timeout=30) == -signal.SIGTERM
    assert f"the Prefect API at {gone} has not answered for" in proc.stderr.read()
    # a SIGTERM that does not end the process (Prefect's engine waiting on the API gone: the
    # run was seen hanging minutes after its crash) is followed by the process ending itself
    proc = _watched(str(run.id), gone, "held")
    assert proc.wait(timeout=30) == 143
    assert "has not answered" in proc.stderr.read().splitlines()[-1]
