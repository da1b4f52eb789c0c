"""The ``cropcraft`` command line.

Every sub-command validates its input before doing any work; a ``CropCraftError`` becomes one line
on stderr (``cropcraft: error: …``) and exit code 2. Heavy modules (Prefect, Open3D, torch) are
imported only by the sub-commands that need them.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import signal
import sys
import threading
from contextlib import contextmanager
from pathlib import Path

from cropcraft_core.errors import ConfigError, CropCraftError


def _param_pairs(values: list[str] | None) -> dict[str, float]:
    out: dict[str, float] = {}
    for item in values or []:
        name, sep, value = item.partition("=")
        if not sep or not name:
            raise ConfigError(f"--param expects NAME=VALUE, got {item!r}")
        try:
            out[name.strip()] = float(value)
        except ValueError:
            raise ConfigError(f"--param {name}: {value!r} is not a number") from None
    return out


def _pair(text: str | None, what: str) -> tuple[float, float] | None:
    if text is None:
        return None
    parts = text.split(",")
    try:
        a, b = (float(p) for p in parts)
    except ValueError:
        raise ConfigError(f"{what} expects two numbers W,L in metres, got {text!r}") from None
    return a, b


def _layout(crop: str, args: argparse.Namespace):
    from cropcraft_core.config import default_layout

    plot = _pair(args.plot, "--plot")
    return default_layout(
        crop,
        plot_width=plot[0] if plot else None,
        plot_length=plot[1] if plot else None,
        row_spacing=args.row_spacing,
        density=args.density,
    )


def cmd_generate(args: argparse.Namespace) -> int:
    from cropcraft_core.bundle import output_dir, write_bundle
    from cropcraft_core.config import resolve_params
    from cropcraft_core.procedural import generate_canopy

    params = resolve_params(args.crop, _param_pairs(args.param))
    layout = _layout(args.crop, args)
    with output_dir(args.out):
        canopy = generate_canopy(args.crop, params, layout, seed=args.seed)
        metrics = write_bundle(canopy, args.out)
    _print_summary(args.out, metrics)
    return 0


#: What ``make_scene`` writes at the top of its folder (moved into ``--out`` when complete).
SYNTH_ENTRIES = ("images", "depth", "colmap", "transforms.json", "truth", "scene.json")


def _resolution(text: str) -> tuple[int, int]:
    w, sep, h = text.lower().partition("x")
    try:
        if not sep:
            raise ValueError
        return int(w), int(h)
    except ValueError:
        raise ConfigError(
            f"--resolution expects WIDTHxHEIGHT, e.g. 640x480, got {text!r}"
        ) from None


def cmd_synth(args: argparse.Namespace) -> int:
    import shutil
    import tempfile

    from cropcraft_core.bundle import output_dir
    from cropcraft_core.config import resolve_params
    from cropcraft_core.export import publish
    from cropcraft_core.synth import make_scene

    params = resolve_params(args.crop, _param_pairs(args.param))
    layout = _layout(args.crop, args)
    size = _resolution(args.resolution)
    if args.views < 2:
        raise ConfigError(f"a scene needs at least 2 views, got --views {args.views}")
    trajectory = args.trajectory or ("drone" if args.crop == "maize" else "walk")
    with output_dir(args.out) as out:
        tmp = Path(tempfile.mkdtemp(dir=out, prefix=".synth-"))
        try:
            summary = make_scene(
                args.crop,
                tmp,
                params,
                seed=args.seed,
                views=args.views,
                resolution=size,
                trajectory=trajectory,
                layout=layout,
                image_format=args.format,
                drone_height_m=args.drone_height,
                gps_noise_m=args.gps_noise,
            )
            publish(tmp, out, SYNTH_ENTRIES)  # every entry replaced whole, all or none
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
    lo, hi = summary["camera_height_range_m"]
    print(
        f"{summary['views']} {trajectory} views at {size[0]}x{size[1]}, cameras "
        f"{lo:.2f}-{hi:.2f} m high, {summary['plot_plants']} plants in the plot"
    )
    print(f"written to {out.resolve()} (images/, transforms.json, colmap/, depth/, truth/)")
    return 0


def _print_summary(out: str, metrics: dict) -> None:
    from cropcraft_core.metrics import HEADLINE_TRAITS

    keys = [*HEADLINE_TRAITS, "n_faces"]
    width = max(len(k) for k in keys)
    for k in keys:
        v = metrics.get(k)
        print(f"{k:<{width}}  {v:.3f}" if isinstance(v, float) else f"{k:<{width}}  {v}")
    seeds = metrics.get("seeds")
    if seeds:
        lai = seeds["traits"]["lai"]
        print(
            f"LAI over the {seeds['n_seeds']} seeds' answers: median {lai['median']:.3f}, "
            f"range {lai['min']:.3f} to {lai['max']:.3f}"
        )
    print(f"written to {Path(out).resolve()}")


def _fit_config(args: argparse.Namespace):
    from cropcraft_core.fit import FitConfig
    from cropcraft_core.fit.fitting import initial_evals
    from flows.service_cli import parse_params

    cfg = FitConfig(
        box=parse_params(args.param),
        method=args.method,
        n_seeds=args.seeds,
        n_evals=args.evals,
        n_initial=initial_evals(args.evals) if args.initial is None else args.initial,
        combine=args.combine,
        polish_evals=args.polish_evals,
        canopies_per_eval=args.canopies,  # None: the crop's
        **({} if args.estimator is None else {"loss_estimator": args.estimator}),
    )
    if args.method == "poisson":
        if cfg.box:
            raise ConfigError("--param: the poisson baseline fits no model parameters")
        return cfg
    cfg.validate().param_box(args.crop)
    return cfg


def cmd_fit(args: argparse.Namespace) -> int:
    from cropcraft_core.bundle import output_dir
    from cropcraft_core.config.params import check_crop
    from cropcraft_core.errors import InputError
    from cropcraft_core.fit.geometry import fit_geometry

    check_crop(args.crop)
    if not Path(args.geometry).is_file():
        raise InputError(f"{args.geometry}: no such file")
    cfg = _fit_config(args)
    from flows.service_cli import parse_preset

    preset_overrides = parse_preset(args.crop, args.preset)
    layout = _layout(args.crop, args)
    from cropcraft_core.rowfit.neighbours import MAX_NEIGHBOURS

    n = args.neighbour_rows
    if not 0 <= n <= MAX_NEIGHBOURS:
        raise ConfigError(f"--neighbour-rows must be 0 to {MAX_NEIGHBOURS}, got {n}")
    from cropcraft_core.parallel import default_workers, processes

    if args.workers is not None and args.workers < 1:
        raise ConfigError(f"--workers must be at least 1, got {args.workers}")
    from cropcraft_core.fit.mlp import PAIRS_PER_JOB, MLPConfig

    # the seeds' processes (every row's, fitted together); mlp's are its training pairs'
    # (where no network is cached yet)
    rows = 1 + 2 * n
    jobs = {"poisson": 1, "mlp": MLPConfig().n_pairs // PAIRS_PER_JOB}.get(
        args.method, cfg.n_seeds * rows
    )
    with output_dir(args.out), processes(args.workers or default_workers(jobs)) as ex:
        metrics = fit_geometry(
            args.geometry,
            args.crop,
            args.out,
            cfg,
            layout,
            seed=args.seed,
            neighbours=n,
            row_answer=args.rows_answer,
            executor=ex,
            preset_overrides=preset_overrides,
        )
    _print_summary(args.out, metrics)
    if args.method != "poisson":
        from cropcraft_core.fit.geometry import geometry_warnings

        record = json.loads((Path(args.out) / "fit.json").read_text())
        for warning in [*geometry_warnings(record["observation"]), record.get("edge_warning")]:
            if warning:
                print(f"WARNING  {warning}", file=sys.stderr)
    if n:
        table = json.loads((Path(args.out) / "rows.json").read_text())
        cells = "  ".join(f"{r['index']:+d}: {r['traits']['lai']:.3g}" for r in table["rows"])
        print(f"LAI by row (0 = the best row; answer: {table['answer']})  {cells}")
    return 0


BENCHMARKS = {
    "generate": "benchmarks.bench_generate",
    "render": "benchmarks.bench_render",
    "accuracy": "benchmarks.bench_accuracy",
    "fit-speed": "benchmarks.bench_fit_speed",
    "optimizer": "benchmarks.bench_optimizer",
    "pipeline": "benchmarks.bench_pipeline",
    "draws": "benchmarks.bench_draws",
    "rows": "benchmarks.bench_rows",
    "surfaces": "benchmarks.bench_surfaces",
    "nerfacto": "benchmarks.bench_nerfacto",
}


def cmd_bench(args: argparse.Namespace) -> int:
    import importlib

    module = importlib.import_module(BENCHMARKS[args.what])
    return module.main(args.rest)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="cropcraft", description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="command", required=True)

    g = sub.add_parser("generate", help="build a procedural canopy and write meshes, metrics")
    g.add_argument("crop", help="soybean or maize")
    g.add_argument(
        "--param",
        action="append",
        metavar="NAME=VALUE",
        help="model parameter (repeatable); missing ones take the middle of their range",
    )
    g.add_argument("--seed", type=int, default=0)
    g.add_argument("--plot", metavar="W,L", help="plot width (across rows) and length (m)")
    g.add_argument("--row-spacing", type=float, metavar="M")
    g.add_argument("--density", type=float, metavar="PLANTS_PER_M2")
    g.add_argument("--out", required=True, metavar="DIR")
    g.set_defaults(func=cmd_generate)

    y = sub.add_parser(
        "synth", help="render a synthetic photo scene with its poses and truth (test data)"
    )
    y.add_argument("crop", help="soybean or maize")
    y.add_argument("--out", required=True, metavar="DIR")
    y.add_argument(
        "--param",
        action="append",
        metavar="NAME=VALUE",
        help="model parameter (repeatable); missing ones take the middle of their range",
    )
    y.add_argument("--seed", type=int, default=0, help="canopy, trajectory, light and noise")
    y.add_argument("--views", type=int, default=50, help="photos (50)")
    y.add_argument("--resolution", default="640x480", metavar="WxH", help="photo size (640x480)")
    y.add_argument(
        "--trajectory",
        choices=["walk", "drone"],
        help="a person walking around the plot at 1-1.8 m, or a drone at ~13 m "
        "(default: walk for soybean, drone for maize)",
    )
    y.add_argument("--format", choices=["jpg", "png"], default="jpg", help="image format")
    y.add_argument(
        "--drone-height", type=float, metavar="M", help="a drone trajectory's height (13 m)"
    )
    y.add_argument(
        "--gps-noise",
        type=float,
        metavar="M",
        help="tag every photo with its camera's GPS position, off by this many metres (0.02: "
        "a drone with RTK; 0.5-2: consumer GPS; 3-5: a phone); default: no GPS tags",
    )
    y.add_argument("--plot", metavar="W,L", help="plot width (across rows) and length (m)")
    y.add_argument("--row-spacing", type=float, metavar="M")
    y.add_argument("--density", type=float, metavar="PLANTS_PER_M2")
    y.set_defaults(func=cmd_synth)

    f = sub.add_parser("fit", help="fit a metric, z-up mesh or point cloud (LiDAR, other tools)")
    f.add_argument("crop", help="soybean or maize")
    f.add_argument("--geometry", required=True, metavar="FILE.ply")
    f.add_argument("--out", required=True, metavar="DIR")
    f.add_argument(
        "--method", default="bo", choices=["bo", "trust-region", "random", "mlp", "poisson"]
    )
    f.add_argument("--seeds", type=int, default=10, help="optimiser seeds (paper: 10)")
    f.add_argument("--evals", type=int, default=500, help="evaluations per seed (paper: 500)")
    f.add_argument(
        "--initial",
        type=int,
        default=None,
        help="random initial evaluations (200; 40 %% of a budget under 500); at most --evals",
    )
    f.add_argument(
        "--workers",
        type=int,
        metavar="N",
        help="processes the seeds run in, one thread each (default: one per CPU, at most one "
        "per seed of every row fitted; 1: in this process); mlp makes its first training "
        "pairs there",
    )
    from cropcraft_core.fit.fitting import COMBINE_RULES

    f.add_argument(
        "--combine",
        choices=list(COMBINE_RULES),
        help="bo's answer from its seeds: the median or the paper's mean of their best points, "
        "candidates re-scored on fresh canopies and the best refined, the median unless that "
        "refined winner's basin is significantly deeper (guarded), or every candidate refined "
        "and the lowest on fresh canopies unless it ties the median's (floors: each seed "
        "costs about twice as much; fit/select.py); "
        "default: the crop's (soybean guarded, maize reevaluate)",
    )
    f.add_argument(
        "--polish-evals",
        type=int,
        default=60,
        metavar="N",
        help="reevaluate, guarded, floors: Nelder-Mead evaluations refining the best re-scored "
        "candidate (guarded's median; floors: every candidate) (60; 0: none)",
    )
    f.add_argument(
        "--preset",
        action="append",
        metavar="KEY=VALUE",
        help="observation preset setting (repeatable), e.g. views_along=3 views_across=1 to "
        "pool the statistics over 3 row cameras along the row and the rows on each side "
        "(views beyond the geometry are left out)",
    )
    f.add_argument(
        "--canopies",
        type=int,
        metavar="K",
        help="procedural canopies averaged per evaluation (default: the crop's)",
    )
    f.add_argument(
        "--estimator",
        choices=["pooled", "unbiased"],
        help="the loss over several canopies: of their mean statistics (pooled, the paper's) "
        "or its U-statistic without the draw variance (unbiased; opt-in)",
    )
    from flows.service_cli import add_param_option

    add_param_option(f)
    f.add_argument("--seed", type=int, default=0, help="seed of the final canopy and sampling")
    f.add_argument("--plot", metavar="W,L", help="plot of the final canopy (m)")
    f.add_argument("--row-spacing", type=float, metavar="M", help="known planting row spacing")
    f.add_argument("--density", type=float, metavar="PLANTS_PER_M2")
    f.add_argument(
        "--neighbour-rows",
        type=int,
        default=0,
        metavar="N",
        help="also fit up to N rows on each side of the best row that the geometry covers, "
        "each alone, and write their answers and spread to rows.json (one fit per row)",
    )
    from cropcraft_core.metrics.rows import ROW_ANSWERS

    f.add_argument(
        "--rows-answer",
        choices=list(ROW_ANSWERS),
        default="best",
        help="with --neighbour-rows: the answer is the best row's (best, default) or every "
        "parameter's mean over the rows' answers (mean)",
    )
    f.set_defaults(func=cmd_fit)

    b = sub.add_parser("bench", help="benchmarks (speed and accuracy targets)")
    b.add_argument("what", choices=sorted(BENCHMARKS))
    b.add_argument("rest", nargs=argparse.REMAINDER, help="the benchmark's own options")
    b.set_defaults(func=cmd_bench)

    from flows.service_cli import add_service_commands

    add_service_commands(sub)
    return p


#: Seconds ``cropcraft`` lets Prefect wait for its temporary (ephemeral) API server to start.
EPHEMERAL_STARTUP_TIMEOUT_S = 180


#: Seconds a Ctrl-C leaves Prefect to record the interrupted run before ``cropcraft`` ends its
#: child processes and exits (benchmarks/RESULTS.md *#process-runner*).
INTERRUPT_GRACE_S = 15.0


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised as Ctrl-C's ``KeyboardInterrupt`` is (the same clean-up), exit 143."""


@contextmanager
def interrupt_deadline(grace_s: float = INTERRUPT_GRACE_S):
    """Ctrl-C that always ends the command: the first SIGINT raises ``KeyboardInterrupt`` as
    usual (Prefect marks the run crashed, the stages stop); if the process is still alive
    ``grace_s`` later, or at a second SIGINT, every child process (pool workers, Prefect's
    temporary server) is ended and the process exits with 130.

    Needed where a stage does not stop: seeds on the threads runner, or workers a signal did
    not reach, go on fitting (a terminal's Ctrl-C no longer stops Prefect's temporary server,
    which runs apart: :func:`flows.runners.keep_temporary_server_apart`). Only in the main
    thread, and not where SIGINT is ignored (a background job). SIGTERM (a scheduler's stop,
    ``kill``, ``timeout``) ends the command as Ctrl-C does, with exit 143.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.getsignal(signal.SIGINT)
    if previous is signal.SIG_IGN:
        yield
        return
    interrupted = threading.Event()
    terminated = threading.Event()

    def force() -> None:
        said, code = ("terminated", 143) if terminated.is_set() else ("interrupted", 130)
        print(f"cropcraft: {said}; ending its processes", file=sys.stderr, flush=True)
        end_children()
        os._exit(code)

    def on_sigint(signum: int, frame: object) -> None:
        if interrupted.is_set():
            force()
        interrupted.set()
        timer = threading.Timer(grace_s, force)
        timer.daemon = True
        timer.start()
        raise Terminated if terminated.is_set() else KeyboardInterrupt

    def on_sigterm(signum: int, frame: object) -> None:
        # a scheduler's stop, `kill`, `timeout`: as a Ctrl-C, exit 143. During a flow run
        # Prefect's own handler takes SIGTERM and hands it back here once its run has
        # crashed (the stage's end): then every child, Prefect's temporary server too, ends
        # (the server outlived the run, orphaned)
        terminated.set()
        on_sigint(signum, frame)

    previous_term = signal.getsignal(signal.SIGTERM)
    signal.signal(signal.SIGINT, on_sigint)
    if previous_term in (signal.SIG_DFL, None):
        signal.signal(signal.SIGTERM, on_sigterm)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
        if previous_term in (signal.SIG_DFL, None):
            signal.signal(signal.SIGTERM, previous_term or signal.SIG_DFL)


def end_children(timeout_s: float = 5.0) -> None:
    """Terminate every descendant process of this one, then kill those still alive."""
    import psutil

    try:
        children = psutil.Process().children(recursive=True)
    except psutil.Error:
        return
    for child in children:
        try:
            child.terminate()
        except psutil.Error:
            pass
    _, alive = psutil.wait_procs(children, timeout=timeout_s)
    for child in alive:
        try:
            child.kill()
        except psutil.Error:
            pass


def disk_full_line(exc: BaseException) -> str | None:
    """One line for an error a full disk caused, else None: an ENOSPC in the error's causes,
    or a server error of the temporary Prefect server whose database's disk is (nearly) full
    (its own "database or disk is full" stays in the server; the run ended with pages of
    tracebacks and "500 Internal Server Error": session 94's disk audit)."""
    from cropcraft_core.store import disk_hint

    hint = disk_hint(exc)
    if hint is not None:
        return f"{type(exc).__name__}: {exc}; {hint}"
    if type(exc).__name__ == "PrefectHTTPStatusError" and re.search(r"\b500\b", str(exc)):
        from flows.service_cli import prefect_home_full

        said = prefect_home_full()
        if said is not None:
            return f"Prefect's server failed ({str(exc).splitlines()[0]}): {said}"
    return None


def _termination_signal() -> type[BaseException]:
    """Prefect's ``TerminationSignal`` (its engine raises it once a cancelled run has ended,
    :mod:`flows.watch`), where Prefect is loaded; else :class:`Terminated`."""
    if "prefect" not in sys.modules:
        return Terminated
    from prefect.exceptions import TerminationSignal

    return TerminationSignal


def main(argv: list[str] | None = None) -> int:
    # an offline batch service: no telemetry calls to the outside (they fail here anyway)
    os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
    # Prefect's own 20 s wait for its temporary server is too short on a fresh 2-core machine:
    # the first start creates and migrates ~/.prefect/prefect.db (19.7 s measured idle), and
    # `cropcraft demo` timed out there while it was also making the scene
    os.environ.setdefault(
        "PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS", str(EPHEMERAL_STARTUP_TIMEOUT_S)
    )
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        with interrupt_deadline():
            return args.func(args)
    except CropCraftError as e:
        print(f"cropcraft: error: {e}", file=sys.stderr)
        return 2
    except Exception as e:  # a full disk outside the store: Prefect's database, the scratch
        said = disk_full_line(e)
        if said is None:
            raise
        print(f"cropcraft: error: {said}", file=sys.stderr)
        return 2
    except (Terminated, _termination_signal()):  # Prefect's own after a cancel (flows/watch)
        from flows.watch import stop_reason

        print(f"cropcraft: {stop_reason() or 'terminated'}", file=sys.stderr)
        return 143
    except KeyboardInterrupt:
        print("cropcraft: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
