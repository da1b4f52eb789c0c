"""The service sub-commands of ``cropcraft``: ``run``, ``season``, ``status`` and ``demo``.

``flows/cli.py`` registers them with :func:`add_service_commands`. Every command validates its
input (scene names, store reachability, photos present, settings) before Prefect starts, and a
``CropCraftError`` becomes one line and exit code 2 in ``flows.cli.main``. One ``--store``
option everywhere (default ``$CROPCRAFT_STORE``, else ``./cropcraft-data``).
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import shutil
import sys
import threading
import time
from collections.abc import Callable, Mapping
from contextlib import contextmanager, nullcontext
from typing import Any

from cropcraft_core.errors import ConfigError

# --------------------------------------------------------------------------- shared options


def _add_common(p: argparse.ArgumentParser, runner: bool = True) -> None:
    p.add_argument(
        "--store",
        default=os.environ.get("CROPCRAFT_STORE"),
        metavar="URI",
        help="scene store root: a folder or s3://bucket/prefix (env CROPCRAFT_STORE; "
        "default ./cropcraft-data)",
    )
    if runner:
        p.add_argument(
            "--runner",
            default="processes",  # flows.runners.DEFAULT_RUNNER (not imported: it loads Prefect)
            metavar="RUNNER",
            help="processes (default: one spawned process per core, at most 8), threads, "
            "dask (a local cluster: one single-threaded worker a core, at most 8) or "
            "dask://HOST:PORT",
        )
        p.add_argument(
            "--set",
            action="append",
            default=[],
            metavar="SECTION.KEY=VALUE",
            help="config override, e.g. fit.n_evals=200 or observe.image_scale=0.5 (repeatable; "
            "VALUE is JSON, else a string)",
        )
        add_param_option(p)
        p.add_argument(
            "--no-progress",
            action="store_true",
            help="no progress bar: a line every 10 %% of each fit seed and long stage instead",
        )
        p.add_argument(
            "--camera-height",
            type=float,
            metavar="M",
            help="median height of the cameras above the ground (m): sets the metric scale of "
            "SfM poses (else it is measured from the row spacing); = --set poses.camera_height=M",
        )
        p.add_argument(
            "--row-spacing",
            type=float,
            metavar="M",
            help="planting row spacing (m), where it is not the crop's default (0.76): the row "
            "fit and the fitted canopy's rows use it; = --set layout.row_spacing=M",
        )
        p.add_argument(
            "--camera-distance",
            nargs=3,
            metavar=("PHOTO_A", "PHOTO_B", "M"),
            help="measured distance (m) between the spots two photos were taken from (e.g. two "
            "tripod marks): sets the metric scale of SfM poses; = --set "
            'poses.camera_distance=\'["A","B",M]\'',
        )
        p.add_argument(
            "--neighbour-rows",
            type=int,
            metavar="N",
            help="also observe and fit up to N rows on each side of the best row and report "
            "each row's answer and their spread (costs one fit per row; = --set "
            "rows.neighbours=N)",
        )


def add_param_option(p: argparse.ArgumentParser) -> None:
    """``--param NAME=VALUE|LOW:HIGH``: what the user knows of a model parameter (``fit.box``)."""
    p.add_argument(
        "--param",
        action="append",
        default=[],
        metavar="NAME=VALUE|LOW:HIGH",
        help="what you know of a model parameter: a value is fixed, not fitted (e.g. "
        "num_nodes=9 counted in the field), LOW:HIGH narrows its search (repeatable; "
        "a scene's known.json notes hold the same)",
    )


def parse_params(items: list[str] | None) -> dict[str, float | list[float]]:
    """``["num_nodes=9", "leaf_length=0.8:1.1"]`` → ``{"num_nodes": 9.0, "leaf_length":
    [0.8, 1.1]}`` (names and ranges are checked against the crop by ``ParamBox``)."""
    out: dict[str, float | list[float]] = {}
    for item in items or []:
        name, sep, value = item.partition("=")
        if not sep or not name.strip():
            raise ConfigError(f"--param expects NAME=VALUE or NAME=LOW:HIGH, got {item!r}")
        parts = value.split(":")
        try:
            numbers = [float(v) for v in parts]
        except ValueError:
            raise ConfigError(
                f"--param {name.strip()}: {value!r} is not a number or LOW:HIGH"
            ) from None
        if len(numbers) > 2:
            raise ConfigError(f"--param {name.strip()}: {value!r} has more than two numbers")
        out[name.strip()] = numbers[0] if len(numbers) == 1 else numbers
    return out


def overrides_of(args: argparse.Namespace) -> dict[str, Any]:
    """The config overrides of a ``run``/``season`` command line (``--set`` and the shortcuts)."""
    out = parse_sets(args.set)
    for name, value in parse_params(getattr(args, "param", None)).items():
        out[f"fit.box.{name}"] = value
    if getattr(args, "camera_height", None) is not None:
        out["poses.camera_height"] = float(args.camera_height)
    if getattr(args, "neighbour_rows", None) is not None:
        out["rows.neighbours"] = int(args.neighbour_rows)
    if getattr(args, "row_spacing", None) is not None:
        out["layout.row_spacing"] = float(args.row_spacing)
    if getattr(args, "camera_distance", None) is not None:
        a, b, metres = args.camera_distance
        try:
            out["poses.camera_distance"] = [a, b, float(metres)]
        except ValueError:
            raise ConfigError(f"--camera-distance: {metres!r} is not a number of metres") from None
    return out


def parse_value(raw: str) -> Any:
    """A command-line setting's value: JSON where it parses (numbers, lists, true/null), else
    the text itself."""
    try:
        return json.loads(raw)
    except ValueError:
        return raw


def parse_preset(crop: str, items: list[str] | None) -> dict[str, Any]:
    """``["views_along=3", "lambda_lateral=0.25"]`` → the observation preset's overrides,
    checked by building ``crop``'s preset with them (an unknown key or a bad value is a
    ``ConfigError`` with the preset's own message)."""
    from cropcraft_core.errors import CropCraftError
    from cropcraft_core.observe import preset

    out: dict[str, Any] = {}
    for item in items or []:
        key, sep, raw = item.partition("=")
        if not sep or not key.strip():
            raise ConfigError(f"--preset takes KEY=VALUE, got {item!r}")
        out[key.strip()] = parse_value(raw)
    try:
        preset(crop, **out)
    except (CropCraftError, TypeError, ValueError) as exc:
        raise ConfigError(f"--preset: {exc}") from None
    return out


def parse_sets(items: list[str]) -> dict[str, Any]:
    """``["fit.n_evals=200", "surfaces.backend=tsdf"]`` → ``{"fit.n_evals": 200, ...}``."""
    out: dict[str, Any] = {}
    for item in items or []:
        key, sep, raw = item.partition("=")
        if not sep or "." not in key:
            raise ConfigError(f"--set expects SECTION.KEY=VALUE, got {item!r}")
        out[key.strip()] = parse_value(raw)
    return out


def _parse_scene(text: str):
    from cropcraft_core.store import SceneKey

    return SceneKey.parse(text)


@contextmanager
def run_progress(bar: bool = True):
    """A run's progress on the console, the same on every local runner (threads and
    processes; the processes runner relays its workers' ticks, :class:`tasks.common.Tick`, to
    this process):

    - on a terminal, unless ``bar`` is off: one tqdm bar, over a long stage's step while it
      runs (the surfaces' stereo, in per cent), then over all seeds' fit evaluations, with
      the lowest loss any seed has reached; the console's log lines print above it, and a
      finished step's bar stays as a line with its time;
    - otherwise (a log file, a nightly job, ``--no-progress``): a line at every 10 % of each
      stage step and of each seed's evaluations, with that seed's best loss so far.

    Prefect's task-run records stay off the console meanwhile (:func:`_task_runs_off_console`);
    the Prefect UI still gets every one of them.
    """
    from tasks.common import Tick, set_progress_sink

    lock = threading.RLock()
    above = nullcontext()
    if bar and sys.stderr.isatty():
        from tqdm import tqdm

        fits: dict[int | str, Tick] = {}
        showing = [""]
        bars: list[tqdm] = []  # made at the first tick: no empty bar over the run's first lines

        left = [""]  # the step whose finished bar was last left on the screen

        def leave_finished() -> None:
            """A finished step's bar stays as a line with its time, no longer redrawn (its
            clock would run on under the next lines)."""
            if bars and bars[0].total and bars[0].n >= bars[0].total:
                bars.pop().close()
                left[0], showing[0] = showing[0], ""

        above = _logs_above_bar(lock, leave_finished)

        def show(what: str, unit: str) -> tqdm:
            """The bar; restarted (its clock and rate too) when it moves to another step."""
            if showing[0] != what:
                leave_finished()
            if not bars:
                bars.append(tqdm(total=0, dynamic_ncols=True, desc=what, unit=unit))
            elif showing[0] != what:
                bars[0].unit = unit
                bars[0].set_description_str(what, refresh=False)
                bars[0].set_postfix_str("", refresh=False)
                bars[0].reset()
            showing[0] = what
            return bars[0]

        def sink(tick: Tick) -> None:
            with lock:
                if tick.kind == "stage":
                    if tick.done >= tick.total and left[0] == str(tick.key) != showing[0]:
                        return  # the finished step's closing tick again
                    pbar = show(str(tick.key), "%")
                    pbar.total, pbar.n = tick.total, tick.done
                    if tick.done >= tick.total:  # a stage's steps run one after the other
                        leave_finished()  # (closing draws the bar's last state)
                        return
                else:
                    fits[tick.key] = tick
                    pbar = show("fit (BO evaluations)", "eval")
                    pbar.total = sum(t.total for t in fits.values())
                    pbar.n = sum(t.done for t in fits.values())
                    bests = [t.best for t in fits.values() if t.best is not None]
                    if bests:
                        pbar.set_postfix_str(f"best loss {min(bests):.4g}", refresh=False)
                pbar.refresh()

        def close() -> None:
            for pbar in bars:
                pbar.close()

    else:
        seen: dict[tuple[str, int | str], int] = {}

        def sink(tick: Tick) -> None:
            step = max(1, tick.total // 10)
            with lock:
                before = seen.get((tick.kind, tick.key), 0)
                seen[(tick.kind, tick.key)] = tick.done
                crossed = tick.done // step > before // step  # each 10 % mark
                finished = tick.done == tick.total != before  # once at the end
                if not (crossed or finished):
                    return
                if tick.kind == "stage":
                    text = f"{tick.key} {round(100 * tick.done / max(1, tick.total))} %"
                else:
                    loss = "" if tick.best is None else f", best loss {tick.best:.4g}"
                    text = f"fit seed {tick.key}: {tick.done}/{tick.total} evaluations{loss}"
                print(f"{time.strftime('%H:%M:%S')} | {text}", file=sys.stderr, flush=True)

        def close() -> None:
            return None

    set_progress_sink(sink)
    try:
        with _task_runs_off_console(), _named_errors_in_one_line(), above:
            yield
    finally:
        set_progress_sink(None)
        close()


@contextmanager
def _logs_above_bar(lock: threading.RLock, before: Callable[[], None]):
    """While the bar is up, a record the console's log handlers print (the flow's stage lines,
    warnings) takes its own line above the bar, which is redrawn under it, instead of being
    written over the bar's line; ``before()`` runs first (under ``lock``). Every stream
    handler of the root logger writing to a terminal gets its ``emit`` wrapped (the same
    handler instance serves Prefect's other console loggers); the wrap comes off when the run
    ends."""
    from tqdm import tqdm

    handlers = [
        h
        for h in logging.getLogger().handlers
        if isinstance(h, logging.StreamHandler) and _is_terminal(h.stream)
    ]
    for h in handlers:

        def emit(record: logging.LogRecord, plain=h.emit, stream=h.stream) -> None:
            with lock:
                before()
                with tqdm.external_write_mode(file=stream):
                    plain(record)

        h.emit = emit  # an instance attribute: removing it brings the class's back
    try:
        yield
    finally:
        for h in handlers:
            vars(h).pop("emit", None)


def _is_terminal(stream: Any) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):  # no isatty, or a closed file
        return False


class _BelowWarning:
    """A logging filter: drops records of ``prefix`` loggers below WARNING."""

    def __init__(self, prefix: str) -> None:
        self.prefix = prefix

    def filter(self, record: logging.LogRecord) -> bool:
        return record.levelno >= logging.WARNING or not record.name.startswith(self.prefix)


@contextmanager
def _task_runs_off_console():
    """Keep Prefect's task-run INFO records (each task's "Finished in state Completed()", the
    fit's own 10 % lines) off this process's console, as the ``processes`` runner's workers
    already do (they start with ``PREFECT_LOGGING_LEVEL=WARNING``, :func:`_before_flow_run`).
    The flow's stage lines stay; the records still reach the Prefect API."""
    from prefect.logging.handlers import PrefectConsoleHandler

    handlers = [h for h in logging.getLogger().handlers if isinstance(h, PrefectConsoleHandler)]
    quiet = _BelowWarning("prefect.task_runs")
    for h in handlers:
        h.addFilter(quiet)
    try:
        yield
    finally:
        for h in handlers:
            h.removeFilter(quiet)


@contextmanager
def _named_errors_in_one_line():
    """Named errors print in one line on the console of this process and of the pool's
    workers it starts meanwhile (:func:`flows.runners.named_errors_in_one_line`)."""
    from flows.runners import ONE_LINE_ERRORS_ENV, named_errors_in_one_line

    before = os.environ.get(ONE_LINE_ERRORS_ENV)
    os.environ[ONE_LINE_ERRORS_ENV] = "1"  # the processes runner's workers, spawned from here
    undo = named_errors_in_one_line()
    try:
        yield
    finally:
        undo()
        if before is None:
            os.environ.pop(ONE_LINE_ERRORS_ENV, None)
        else:
            os.environ[ONE_LINE_ERRORS_ENV] = before


def _before_flow_run() -> None:
    """What a command does before it starts a flow run: the Prefect server it would report to
    checked (:func:`check_prefect_api`), Prefect's INFO logging off the console of
    processes started from here on (the ``processes`` runner's workers; this process
    configured its logging when Prefect loaded, and :func:`run_progress` quiets its task
    runs), and a temporary server, where one is needed, kept out of Ctrl-C's reach
    (:func:`flows.runners.keep_temporary_server_apart`)."""
    check_prefect_api()
    os.environ.setdefault("PREFECT_LOGGING_LEVEL", "WARNING")
    from flows.runners import keep_temporary_server_apart

    keep_temporary_server_apart()


#: Free space (bytes) a temporary Prefect server's database folder needs before a run: a run
#: records a few hundred kB there (flow and task runs, logs, events).
PREFECT_HOME_MIN_FREE = 64 << 20


def prefect_home_free() -> tuple[str, int]:
    """``(PREFECT_HOME, free bytes on its disk)``: where a temporary server keeps its database."""
    from prefect.settings import PREFECT_HOME

    home = str(PREFECT_HOME.value())
    probe = home
    while probe and not os.path.exists(probe):
        probe = os.path.dirname(probe)
    return home, shutil.disk_usage(probe or ".").free


def prefect_home_full() -> str | None:
    """What to say where the disk holding the temporary Prefect server's database
    (``PREFECT_HOME``) has under :data:`PREFECT_HOME_MIN_FREE` free, else None."""
    home, free = prefect_home_free()
    if free >= PREFECT_HOME_MIN_FREE:
        return None
    return (
        f"the disk holding Prefect's database ({home}, PREFECT_HOME) has {free / 2**20:.0f} MB "
        "free: free space there, or point PREFECT_HOME at a disk with room"
    )


def check_prefect_home() -> None:
    """A ConfigError where the disk holding the temporary Prefect server's database is
    (nearly) full (:func:`prefect_home_full`): the run ended in pages of the server's
    tracebacks and a "500 Internal Server Error", exit 1, the disk never named (session 94's
    disk audit)."""
    said = prefect_home_full()
    if said is not None:
        raise ConfigError(said)


def check_prefect_api() -> None:
    """Where ``PREFECT_API_URL`` is set, a ConfigError unless that server answers its health
    check: a stopped server or a mistyped URL gave three tracebacks (~115 lines) from inside
    the flow's start. Unset, runs start a temporary server of their own."""
    from prefect.settings import PREFECT_API_URL

    url = PREFECT_API_URL.value()
    if not url:
        check_prefect_home()
        return
    from prefect.client.orchestration import get_client

    try:
        with get_client(sync_client=True) as client:
            failure = client.api_healthcheck()
    except Exception as exc:
        failure = exc
    if failure is not None:
        raise ConfigError(
            f"the Prefect server at PREFECT_API_URL={url} does not answer "
            f"({type(failure).__name__}: {failure}); start it (prefect server start) or unset "
            "PREFECT_API_URL to run on a temporary server"
        )


def _print_summary(out: Mapping[str, Any]) -> None:
    states = out.get("states", {})
    ran = sorted(k for k, v in states.items() if v != "Cached")
    cached = sorted(k for k, v in states.items() if v == "Cached")
    print(f"scene    {out['scene']}  (store {out['store']})")
    print(f"ran      {', '.join(ran) or '-'}")
    print(f"cached   {', '.join(cached) or '-'}")
    from cropcraft_core.metrics.traits import HEADLINE_UNITS

    for k, v in out.get("metrics", {}).items():
        unit = f"  {HEADLINE_UNITS[k]}" if k in HEADLINE_UNITS else ""
        print(f"  {k:<22} {v:.4g}{unit}" if isinstance(v, float) else f"  {k:<22} {v}{unit}")
    _print_frame(out)
    _print_fit_warnings(out)
    _print_coverage(out)
    _print_left_out(out)
    _print_rows(out)
    print(f"report   {out['report']}")
    print(f"bundle   {out['bundle']}")


def _print_frame(out: Mapping[str, Any]) -> None:
    """The planting row spacing the run fitted with, and where its metric scale came from."""
    used = out.get("row_spacing")
    if used:
        where = (
            "given"
            if used.get("given")
            else "the crop's default: give --row-spacing M where the rows are otherwise"
        )
        print(f"rows     {used['m']:g} m apart ({where})")
    source = out.get("scale_source")
    if source:
        print(f"scale    {SCALE_SOURCES.get(source, source)}")


#: What each row-fit scale source means, for the run's summary.
SCALE_SOURCES = {
    "metric_poses": "from the imported poses, in metres",
    "camera_height": "from the camera height given",
    "camera_distance": "from the camera distance given",
    "gps": "from the photos' GPS positions",
    "row_spacing": "from the rows' spacing against the layout's",
    "user_hint": "from rowfit.scale, given",
    "assumed_metric": "assumed from the crop's usual capture height, measured by nothing "
    "(give --camera-height M)",
}


def _print_fit_warnings(out: Mapping[str, Any]) -> None:
    """Too few photos, the rows against a camera-height hint, and an answer pressing the
    parameter box."""
    for key in ("photos_warning", "scale_warning", "edge_warning"):
        if out.get(key):
            print(f"WARNING  {out[key]}")


def _print_left_out(out: Mapping[str, Any]) -> None:
    """The photos the run left out, by name and reason (``report.left_out_lines``)."""
    from cropcraft_core.report import left_out_lines

    for line in left_out_lines(out.get("photos_left_out")):
        print(f"WARNING  {line}")


def _print_rows(out: Mapping[str, Any]) -> None:
    """Each fitted row's LAI and main-stem nodes, and the LAI's spread over the rows."""
    rows = out.get("rows")
    if not rows:
        return
    lai, nodes = rows["lai"], rows["node_count"]
    cells = "  ".join(
        f"{int(k):+d}: {lai[k]:.3g} ({nodes[k]:.3g} nodes)"
        for k in sorted(lai, key=int)
        if lai[k] is not None and nodes[k] is not None
    )
    s = rows["lai_spread"]
    how = rows.get("answer", "best")
    answer = "the best row's" if how == "best" else f"the {how} of the rows' answers"
    print(f"LAI by row (0 = the best row; the answer is {answer})  {cells}")
    if s.get("mean") is not None:
        print(
            f"LAI over {rows['n_rows']} rows: mean {s['mean']:.3g}, sd {s['sd']:.3g}, "
            f"range {s['min']:.3g} to {s['max']:.3g}"
        )


def _print_coverage(out: Mapping[str, Any]) -> None:
    """The share of the row camera's view without a fully supported reconstructed surface, and
    its warning."""
    seen = (out.get("observation") or {}).get("no_surface_fraction")
    if seen is None:
        return
    print(f"row view without a fully supported surface: {100 * seen:.1f} %")
    if out["observation"].get("warning"):
        print(f"WARNING  {out['observation']['warning']}")
    c = out.get("consistency")
    if c and c.get("net") is not None:
        from cropcraft_core.surfaces.consistency import describe

        print(f"surfaces against {c['views']} photos: {describe(c['unreconstructed'], c['extra'])}")
        if c.get("warning"):
            print(f"WARNING  {c['warning']}")


# --------------------------------------------------------------------------- run


def _sweep_stale(req: Any) -> None:
    """A cached answer's housekeeping: the scene's temporary objects over an hour old (a
    writer killed after the scene's last record; no lease is taken for a cached answer, so the
    young ones, which a run now writing may own, stay). Never fails the answer."""
    from cropcraft_core.store import SceneStore

    try:
        SceneStore(req.store_root).sweep_tmp(req.scene.prefix)
    except Exception:  # housekeeping
        pass


def cmd_run(args: argparse.Namespace) -> int:
    """``cropcraft run SITE/CROP/DATE [--images URI] [--poses URI]``."""
    from flows.runners import parse_runner
    from flows.scene import (
        cached_result,
        note_sources,
        notes_overridden,
        prepare,
        read_known,
        run_scene,
    )

    scene = _parse_scene(args.scene)
    overrides = overrides_of(args)
    parse_runner(args.runner)  # before prepare makes the store's folder (a refusal makes none)
    req = prepare(
        scene.site, scene.crop, scene.date, args.images, args.poses, overrides, args.store
    )
    for line in notes_overridden(read_known(req.images, scene.crop), overrides):
        print(f"WARNING  {line}")
    hit = None if args.force else cached_result(req)
    if hit is not None:
        note_sources(req, args.images, args.poses)
        _sweep_stale(req)
        _print_summary(hit)
        return 0
    _before_flow_run()
    with run_progress(not args.no_progress):
        out = run_scene(
            scene.site,
            scene.crop,
            scene.date,
            args.images,
            args.poses,
            overrides,
            args.store,
            runner=args.runner,
            refresh=args.force,
        )
    _print_summary(out)
    return 0


# --------------------------------------------------------------------------- season


def cmd_season(args: argparse.Namespace) -> int:
    """``cropcraft season SITE/CROP``: every dated scene with photos and no results."""
    from flows.season import run_season

    site, _, crop = args.site_crop.strip("/").partition("/")
    if not site or not crop or "/" in crop:
        raise ConfigError(f"season expects SITE/CROP (e.g. plotA/soybean), got {args.site_crop!r}")
    _before_flow_run()
    with run_progress(not args.no_progress):
        out = run_season(site, crop, args.store, overrides_of(args), runner=args.runner)
    for date, state in out["scenes"].items():
        print(f"{date}  {state}")
        for warning in out.get("notes", {}).get(date, []):
            print(f"            WARNING  {warning}")
    if out.get("unchanged"):
        done = out["unchanged"]
        listed = ", ".join(done[:6]) + (", ..." if len(done) > 6 else "")
        print(f"finished {len(done)} date(s), no new photos, not run again: {listed}")
    for name in out.get("misnamed", []):
        print(f"{name}  not run: the folder has photos but its name is not a date (YYYY-MM-DD)")
    for name in out.get("astray", []):
        date = name.partition("/")[0]
        print(f"{name}  not run: its photos are not in {date}/images/: move them into it")
    for warning in out.get("warnings", []):
        print(f"WARNING  {warning}")
    why = out.get("summary_error") or out.get("summary_note") or "?"
    print(f"summary  {out.get('csv') or 'not written: ' + why}")
    print(f"plot     {out.get('png') or 'none: no date has results yet'}")
    return 0 if out.get("state", "Completed") == "Completed" else 1


# --------------------------------------------------------------------------- status


def scene_status(store_uri: str | None, scene_text: str, overrides=None) -> list[dict[str, Any]]:
    """Per stage: manifest status (done/failed/running/pending; ``interrupted``: recorded as
    running but no run holds the scene now), whether its result for the
    photos the last run read (``Manifest.sources``: the inbox, a folder or a URL) and its
    recorded config (or ``overrides``) is cached (``fit_seed``: how many seeds, the best
    row's and then the neighbour rows', e.g. ``10+20 seeds``), its time and error."""
    from cropcraft_core.errors import InputError
    from cropcraft_core.store import SceneStore
    from flows.scene import cache_walk, prepare
    from tasks.common import STAGES

    scene = _parse_scene(scene_text)
    store = SceneStore(store_uri)  # read only: connect's probe created a mistyped store's folder
    if store._local and not store.fs.isdir(store._root_path):
        raise InputError(f"no store at {store.root}: check --store (or CROPCRAFT_STORE)")
    if not store._local:  # a missing bucket read as a scene never run (session 91's S3 audit)
        bucket = store._root_path.split("/", 1)[0]
        try:
            there = store.fs.exists(bucket)
        except Exception as exc:
            raise InputError(f"cannot read the store {store.root}: {exc}") from None
        if not there:
            raise InputError(
                f"no store at {store.root}: its bucket {bucket!r} does not exist (check "
                "--store or CROPCRAFT_STORE, and AWS_ENDPOINT_URL)"
            )
    try:
        manifest = store.load_manifest(scene)
    except InputError:
        manifest = None
    states: dict[str, str] = {}
    unknown = False  # the cache cannot be judged: the last run's inputs are not readable
    if manifest is not None:
        try:
            recorded = overrides if overrides is not None else manifest.config
            src = manifest.sources  # where the last run read its photos (None: the inbox)
            req = prepare(
                scene.site,
                scene.crop,
                scene.date,
                src.get("images"),
                src.get("poses"),
                recorded,
                store_uri,
                writing=False,
            )
            states, _ = cache_walk(req)
        except Exception:  # inputs moved: report the manifest only, the cache as unknown
            states, unknown = {}, True
    neighbours = ((manifest.config if manifest else {}).get("rows") or {}).get("neighbours", 0)
    from cropcraft_core.lease import scene_holder

    live = manifest is not None and scene_holder(store, scene) is not None
    rows = []
    for stage in STAGES:
        rec = manifest.stages.get(stage) if manifest else None
        if stage == "fit_seed":  # the best row's seeds, then the neighbour rows' ("10+20")
            seeds = [k for k, v in states.items() if k.startswith("fit_seed-") and v == "Cached"]
            n = sum("@" not in k for k in seeds)
            others = len(seeds) - n
            cached = (f"{n}+{others} seeds" if others else f"{n} seeds") if seeds else "no"
        else:
            cached = "yes" if states.get(stage) == "Cached" else "no"
        if unknown:  # "no" read as lost results; a rerun from the photos' new place is cached
            cached = "?"
        status = rec.status if rec else "pending"
        if status == "running" and not live:  # its run ended before recording it
            status = "interrupted"
        if rec is None and stage in ("observe_rows", "rows") and not neighbours:
            status = "off"  # the scene is fitted over its best row only (rows.neighbours = 0)
        rows.append(
            {
                "stage": stage,
                "status": status,
                "cached": cached,
                "seconds": rec.seconds if rec else None,
                "error": rec.error if rec else None,
            }
        )
    return rows


def cmd_status(args: argparse.Namespace) -> int:
    """``cropcraft status SITE/CROP/DATE``: what is done, cached and failed."""
    rows = scene_status(args.store, args.scene)
    print(f"{'stage':<12} {'status':<11} {'cached':<9} {'seconds':>8}  error")
    for r in rows:
        sec = f"{r['seconds']:.1f}" if r["seconds"] is not None else "-"
        err = r["error"] or ""  # whole: its cause comes last, after the paths (SfM's did)
        print(f"{r['stage']:<12} {r['status']:<11} {r['cached']:<9} {sec:>8}  {err}")
    if any(r["cached"] == "?" for r in rows):
        print(
            "cached ?: the photos or poses the last run read cannot be read now (moved?), so "
            "what is cached for them cannot be told; a run given their new place says"
        )
    unreadable = _unreadable_manifest(args.store, args.scene)
    if unreadable:  # a finished scene's damaged record read as "never run" (crash audit 91)
        print(
            f"{unreadable}; its stages' results are kept: the next run sets the record aside "
            "and serves what is cached",
            file=sys.stderr,
        )
        return 1
    if all(r["status"] in ("pending", "off") and r["cached"] == "no" for r in rows):
        # a mistyped date or site reads as "not run yet": said, and an exit a script can test
        print(f"no run recorded for {args.scene} in this store", file=sys.stderr)
        return 1
    return 0


def _unreadable_manifest(store_uri: str | None, scene_text: str) -> str | None:
    """Why the scene's run record (``manifest.json``) cannot be read, where it is there and
    cannot; None otherwise."""
    from cropcraft_core.errors import InputError
    from cropcraft_core.store import SceneStore, manifest_key

    scene = _parse_scene(scene_text)
    store = SceneStore(store_uri)
    try:
        if not store.isfile(manifest_key(scene)):
            return None
        store.load_manifest(scene)
    except InputError as exc:
        return str(exc)
    except Exception:  # the store itself: the table above said what it could
        return None
    return None


# --------------------------------------------------------------------------- demo

DEMO_SCENE = ("demo", "soybean", "2024-07-15")
#: The built-in synthetic soybean scene (truth parameters: middle of their ranges): the default
#: scene of the photo pipeline, 50 walk-around photos at 640×480 with metric poses. With 30
#: photos at 480×360 the demo ran faster but read LAI 25–31 % low on three runs; at 50 photos
#: at 640×480 it read 12 and 15 % low on two (6.4 min alone on 2 cores).
DEMO_SYNTH = {"seed": 0, "views": 50, "resolution": (640, 480), "trajectory": "walk"}
#: The demo's settings over the flow's: the CPU surfaces backend (whatever the host has), and
#: otherwise the flow's own defaults, so the demo runs what a user's scene runs: the flow's
#: scene box, its fit budget (10 seeds × 500 evaluations, full-resolution row camera). Until
#: session 45 it gave its own box ([-1.2, 1.2]² × [-0.1, 1.0] m); its row fit then chose the
#: plot's edge row, whose reconstructed leaf edges reach over the soil (LAI +24.5 % on one
#: environment; the flow's box: the central row, +16.2 %; benchmarks/RESULTS.md#carving). The
#: former reduced budget (300 evaluations, half resolution) ran in 220–280 s but its seeds
#: scattered: leaf angle mean 18.5–31.7° against 15.2° over six fresh runs.
DEMO_OVERRIDES: dict[str, Any] = {
    "surfaces.backend": "tsdf",
}
DEMO_TRUTH_KEYS = (
    ("lai", "LAI (m2/m2)"),
    ("leaf_angle_mean_deg", "leaf angle mean (deg)"),
    ("leaf_angle_std_deg", "leaf angle SD (deg)"),
    ("node_count", "node count"),
    ("internode_mean_m", "internode length (m)"),
)


def ensure_demo_inputs(store) -> None:
    """Make the synthetic demo scene once and put its photos (with ``transforms.json``) into
    the scene's inbox and its truth under ``{scene}/truth/``. A store holding a demo scene made
    with other settings (``truth/synth.json`` differs from ``DEMO_SYNTH``, e.g. an older
    release's) gets the current one: its photos are replaced, so the scene flow recomputes
    from ingest on."""
    from cropcraft_core.lease import hold_scene
    from cropcraft_core.store import SceneKey
    from tasks.common import core

    make_scene = core("demo", "cropcraft_core.synth", "make_scene")

    scene = SceneKey(*DEMO_SCENE)
    settings = json.loads(json.dumps(DEMO_SYNTH))  # as stored: tuples become lists
    marker = f"{scene.prefix}/truth/synth.json"
    if store.isfile(marker) and store.get_json(marker) == settings:
        return
    # not while a demo run elsewhere reads the scene (cropcraft_core/lease.py)
    with hold_scene(store, scene, owner="cropcraft demo, making its scene"):
        _remake_demo_inputs(store, scene, settings, marker, make_scene)


def _remake_demo_inputs(store, scene, settings: dict, marker: str, make_scene) -> None:
    import tempfile
    from pathlib import Path

    if store.exists(f"{scene.prefix}/images"):
        print("the store's demo scene is incomplete or of other settings: remaking it", flush=True)
        store.delete(marker)  # first: a crash below leaves a scene that is remade next time
        store.delete(f"{scene.prefix}/images", recursive=True)
    print("making the synthetic soybean scene (once) ...", flush=True)
    with tempfile.TemporaryDirectory(prefix="cropcraft-demo-") as tmp:
        make_scene("soybean", tmp, **DEMO_SYNTH)
        store.put_tree(Path(tmp) / "images", f"{scene.prefix}/images")
        store.put_file(Path(tmp) / "transforms.json", f"{scene.prefix}/images/transforms.json")
        for name in ("params.json", "canopy.ply", "metrics.json"):
            store.put_file(Path(tmp) / "truth" / name, f"{scene.prefix}/truth/{name}")
        store.put_json(marker, settings)  # last: the marker that the scene is complete


def _fmt(v: Any) -> str:
    return f"{v:>12.3f}" if isinstance(v, int | float) else f"{'-':>12}"


def _seed_range(trait: Mapping[str, Any] | None) -> str:
    """``   1.119 to 2.111``: a trait's range over the seeds' answers (``metrics.json``'s
    ``seeds``), or nothing where it has none."""
    if not trait or trait.get("min") is None:
        return ""
    return f"   {trait['min']:.3f} to {trait['max']:.3f}"


def cmd_demo(args: argparse.Namespace) -> int:
    """``cropcraft demo``: the built-in synthetic soybean scene through the whole scene flow."""
    from cropcraft_core.store import SceneStore
    from flows.runners import parse_runner
    from flows.scene import cached_result, note_sources, prepare, resolve_config, run_scene

    t0 = time.perf_counter()
    site, crop, date = DEMO_SCENE
    overrides = {**DEMO_OVERRIDES, **overrides_of(args)}
    resolve_config(crop, overrides)  # bad settings and runners: before the store is made
    parse_runner(args.runner)
    store = SceneStore.connect(args.store)
    ensure_demo_inputs(store)
    req = prepare(site, crop, date, None, None, overrides, args.store)
    out = cached_result(req)
    if out is not None:
        note_sources(req, None, None)
    else:
        _before_flow_run()
        with run_progress(not args.no_progress):
            out = run_scene(site, crop, date, None, None, overrides, args.store, args.runner)
    truth = store.get_json(f"{site}/{crop}/{date}/truth/metrics.json")
    metrics = store.get_json(f"{site}/{crop}/{date}/metrics/metrics.json")
    block = metrics.get("seeds") or {}
    seeds = block.get("traits") or {}
    head = f"   the {block.get('n_seeds')} seeds' answers" if seeds else ""
    print(f"\n{'trait':<24}{'estimated':>12}{'true':>12}{head}")
    for key, label in DEMO_TRUTH_KEYS:
        est, tru = metrics.get(key), truth.get(key)
        print(f"{label:<24}{_fmt(est)}{_fmt(tru)}{_seed_range(seeds.get(key))}")
    states = out.get("states", {})
    n_cached = sum(1 for v in states.values() if v == "Cached")
    print()
    _print_frame(out)
    _print_fit_warnings(out)
    _print_coverage(out)
    print(f"stages cached: {n_cached} of {len(states)}")
    print(f"report   {out['report']}")
    print(f"bundle   {out['bundle']}")
    print(f"done in {time.perf_counter() - t0:.1f} s")
    return 0


# --------------------------------------------------------------------------- registration


def add_service_commands(subparsers: argparse._SubParsersAction) -> None:
    """Register ``run``, ``season``, ``status`` and ``demo`` on the ``cropcraft`` parser."""
    r = subparsers.add_parser("run", help="reconstruct one scene (cached, resumable)")
    r.add_argument("scene", metavar="SITE/CROP/DATE")
    r.add_argument("--images", metavar="URI", help="photos (default: the scene's store inbox)")
    r.add_argument("--poses", metavar="URI", help="transforms.json or COLMAP model (else SfM)")
    r.add_argument("--force", action="store_true", help="recompute every stage")
    _add_common(r)
    r.set_defaults(func=cmd_run)

    s = subparsers.add_parser("season", help="every new dated scene of a site, then a summary")
    s.add_argument("site_crop", metavar="SITE/CROP")
    _add_common(s)
    s.set_defaults(func=cmd_season)

    st = subparsers.add_parser("status", help="what is done, cached and failed for a scene")
    st.add_argument("scene", metavar="SITE/CROP/DATE")
    _add_common(st, runner=False)
    st.set_defaults(func=cmd_status)

    d = subparsers.add_parser("demo", help="the whole scene flow on the built-in synthetic scene")
    _add_common(d)
    d.set_defaults(func=cmd_demo)
