"""Fit speed, side by side in one run.

    cropcraft bench fit-speed [--json FILE] [--evals N] [--seeds N] [--skopt-seeds N]
                              [--skopt-first K] [--local-share S] [--arms ours,skopt,ours+local]

(a) a full soybean fit at paper settings (10 seeds × 500 evaluations at 994 × 738), seeds run in
    parallel processes (one per core) — target ≤ 10 minutes wall on the 2-core machine (the paper
    reports 16 minutes for each single seed);
(b) one seed of our optimiser and of scikit-optimize's ``gp_minimize`` (the paper's optimiser:
    Matérn + EI, 200 initial points) on the same objective and budget: wall time, optimiser
    overhead per iteration, final loss — target ≥ 10× less optimiser time at equal or lower final
    loss (mean over ``--skopt-seeds`` seeds, numbered from ``--skopt-first``: a scikit-optimize
    seed takes ~40 CPU-minutes, so the five can be run over several sittings and joined);
    ``--local-share S`` adds a third arm, ``ours+local``: our optimiser with its closing local
    search (the last S of the evaluations on Nelder-Mead from the lowest point; not the fit's
    default). ``--arms`` runs a subset, so an arm measured in an earlier sitting on the same host
    (scikit-optimize's, the long one) need not run again;
(c) where the time goes per evaluation (generate / render / histograms / optimiser).

``--json FILE`` is rewritten (atomically) after each of (b)'s seeds finishes, with
``"complete": false`` until the run ends, so a stopped run keeps the rows it had.
"""

from __future__ import annotations

import argparse
import os
import time
from collections.abc import Callable

import numpy as np

from benchmarks.options import at_least, output_file, write_json
from cropcraft_core.config import default_layout
from cropcraft_core.errors import ConfigError
from cropcraft_core.fit import FitConfig, fit_seed, observe_canopy
from cropcraft_core.fit.fitting import seed_objective
from cropcraft_core.observe import preset
from cropcraft_core.parallel import processes, run_jobs
from cropcraft_core.procedural import generate_canopy

TRUTH = {
    "leaf_length": 1.1,
    "petiole_length": 1.3,
    "petiole_angle": 2.0,
    "internode_length": 1.2,
    "num_nodes": 9.5,
}


def _optimizer_seconds(r) -> float:
    """Optimiser CPU seconds (robust on a shared machine), else its wall seconds."""
    cpu = float(getattr(r, "cpu_seconds_optimizer", float("nan")))
    return cpu if np.isfinite(cpu) else float(r.seconds_optimizer)


def _observation():
    canopy = generate_canopy("soybean", TRUTH, default_layout("soybean"), seed=4242)
    return observe_canopy(canopy, preset("soybean"))


def _one_seed(args):
    seed, n_evals, n_initial = args
    obs = _observation()
    t = time.perf_counter()
    r = fit_seed(obs, seed, FitConfig(n_evals=n_evals, n_initial=n_initial))
    return {
        "seed": seed,
        "wall_s": time.perf_counter() - t,
        "best": float(r.best_y),
        "optimizer_s": _optimizer_seconds(r),
        "objective_s": float(r.seconds_objective),
        "forward": r.extra.get("forward_timings", {}) if hasattr(r, "extra") else {},
    }


def full_fit(n_seeds: int, n_evals: int, n_initial: int, workers: int) -> dict:
    t = time.perf_counter()
    with processes(workers) as ex:  # spawned, one thread each, gone with this process (as (b))
        seeds = list(run_jobs(ex, _one_seed, [(s, n_evals, n_initial) for s in range(n_seeds)]))
    return {"wall_s": time.perf_counter() - t, "seeds": seeds, "workers": workers}


#: (b)'s arms, in the order each seed's jobs are queued: scikit-optimize's first, the long one
ARMS = ("skopt", "ours", "ours+local")


def _compare_one(args) -> tuple[str, dict]:
    """One seed of one optimiser on the shared objective (run in a worker process);
    ``ours+local`` is ours with ``local_share`` of the evaluations on the closing local search
    (the other arms: the crop's default, none)."""
    method, s, n_evals, n_initial, local_share = args
    from cropcraft_core.optimize.skopt_reference import run_skopt

    obs = _observation()
    share = local_share if method == "ours+local" else None
    cfg = FitConfig(n_evals=n_evals, n_initial=n_initial, local_share=share)
    t = time.perf_counter()
    if method == "skopt":  # the objective fit_seed optimises (soybean: two canopies an
        obj, box, _ = seed_objective(obs, s, cfg)  # evaluation), over its box
        r = run_skopt(obj, box.bounds, n_evals=n_evals, n_initial=n_initial, seed=s)
    else:
        r = fit_seed(obs, s, cfg)
    return method, {
        "seed": s,
        "wall_s": time.perf_counter() - t,
        "best": float(r.best_y),
        "optimizer_s": _optimizer_seconds(r),
        "local_evals": int(r.config.get("local_evals") or 0),
    }


def skopt_vs_ours(
    n_evals: int,
    n_initial: int,
    n_seeds: int,
    workers: int = 1,
    first: int = 0,
    arms: tuple[str, ...] = ("ours", "skopt"),
    local_share: float | None = None,
    on_row: Callable[[dict], None] | None = None,
) -> dict:
    """Seeds ``first`` … ``first + n_seeds - 1`` of each arm once; ``workers`` processes,
    one BLAS thread each (the optimiser times are process CPU seconds, so they do not depend on
    the sharing). Each seed's jobs are queued in ``ARMS``' order, scikit-optimize's first.
    ``on_row(rows)`` after each finished job (the rows so far), so a stopped run keeps them."""
    if "ours+local" in arms and local_share is None:
        raise ConfigError("the arm ours+local needs a local_share")
    seeds = range(first, first + n_seeds)
    order = [m for m in ARMS if m in arms]
    jobs = [(m, s, n_evals, n_initial, local_share) for s in seeds for m in order]
    rows: dict[str, list] = {m: [] for m in arms}
    with processes(workers) as ex:
        for method, row in run_jobs(ex, _compare_one, jobs):
            rows[method].append(row)
            print(f"    {method} seed {row['seed']}: {row}", flush=True)
            if on_row is not None:
                on_row(rows)
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="cropcraft bench fit-speed", description=__doc__.splitlines()[0]
    )
    ap.add_argument("--json", type=output_file)
    ap.add_argument("--evals", type=at_least(2), default=500)
    ap.add_argument("--initial", type=at_least(2), default=200)
    ap.add_argument("--seeds", type=at_least(1), default=10)
    ap.add_argument("--skopt-seeds", type=at_least(0), default=5)
    ap.add_argument(
        "--skopt-first", type=at_least(0), default=0, help="(b)'s first seed (default 0)"
    )
    ap.add_argument(
        "--local-share",
        type=float,
        default=None,
        help="add the arm ours+local: ours with this share of the evaluations on its closing "
        "local search (0 < S < 1)",
    )
    ap.add_argument(
        "--arms",
        default=None,
        help=f"(b)'s arms, comma-separated, from {','.join(ARMS)} (default: ours,skopt, and "
        "ours+local with --local-share)",
    )
    ap.add_argument("--skip-full", action="store_true")
    ap.add_argument(
        "--workers",
        type=at_least(1),
        default=os.cpu_count() or 2,
        help="processes for (a) and (b)",
    )
    a = ap.parse_args(argv)
    if a.skip_full and not a.skopt_seeds:  # it wrote {"complete": true} and exited 0
        ap.error("--skip-full with --skopt-seeds 0 leaves nothing to run")
    if a.initial > a.evals:
        ap.error(f"--initial {a.initial} exceeds --evals {a.evals}")
    if a.local_share is not None and not 0.0 < a.local_share < 1.0:
        ap.error(f"--local-share must be between 0 and 1, got {a.local_share}")
    if a.arms is None:
        arms = ("ours", "skopt") + (("ours+local",) if a.local_share is not None else ())
    else:
        arms = tuple(dict.fromkeys(x.strip() for x in a.arms.split(",") if x.strip()))
        bad = [x for x in arms if x not in ARMS]
        if bad or not arms:
            ap.error(f"--arms: unknown arm(s) {bad or a.arms!r}; choose from {', '.join(ARMS)}")
        if "ours+local" in arms and a.local_share is None:
            ap.error("--arms ours+local needs --local-share")
    out: dict = {}
    if not a.skip_full:
        out["full"] = full_fit(a.seeds, a.evals, a.initial, workers=a.workers)
        f = out["full"]
        per = np.mean([s["wall_s"] for s in f["seeds"]])
        print(
            f"(a) full soybean fit: {a.seeds} seeds × {a.evals} evals at 994×738 on "
            f"{f['workers']} processes: {f['wall_s'] / 60:.1f} min wall (target ≤ 10 min); "
            f"{per:.0f} s per seed (paper: 16 min per seed)"
        )
        fw = {
            k: np.sum([s["forward"].get(k, 0.0) for s in f["seeds"]])
            for k in ("generate", "render", "stats", "calls")
        }
        opt = np.sum([s["optimizer_s"] for s in f["seeds"]])
        n_eval = a.seeds * a.evals
        n = max(fw["calls"], 1)  # canopies: soybean's evaluation averages two
        print(
            "(c) per evaluation ({:.0f} canopies): generate {:.1f} ms, render {:.1f} ms, "
            "histograms {:.1f} ms, optimiser {:.1f} ms; per canopy: generate {:.1f} ms, "
            "render {:.1f} ms, histograms {:.1f} ms".format(
                n / n_eval,
                1e3 * fw["generate"] / n_eval,
                1e3 * fw["render"] / n_eval,
                1e3 * fw["stats"] / n_eval,
                1e3 * opt / n_eval,
                1e3 * fw["generate"] / n,
                1e3 * fw["render"] / n,
                1e3 * fw["stats"] / n,
            )
        )
    if a.skopt_seeds:
        if a.local_share is not None:
            out["local_share"] = a.local_share

        def partial(rows: dict) -> None:  # (b)'s rows so far, in case the run is stopped
            if a.json:
                write_json(a.json, {**out, "compare": rows, "complete": False})

        out["compare"] = rows = skopt_vs_ours(
            a.evals,
            a.initial,
            a.skopt_seeds,
            a.workers,
            first=a.skopt_first,
            arms=arms,
            local_share=a.local_share,
            on_row=partial,
        )
        last = a.skopt_first + a.skopt_seeds - 1
        print(
            f"(b) one seed, {a.evals} evals ({a.initial} initial), "
            f"mean of {a.skopt_seeds} (seeds {a.skopt_first}–{last}):"
        )
        print(
            f"    {'optimiser':<12}{'wall s':>10}{'optimiser s':>14}{'s/iter':>10}{'best loss':>12}"
        )
        for k, rs in rows.items():
            w = np.mean([r["wall_s"] for r in rs])
            o = np.mean([r["optimizer_s"] for r in rs])
            b = np.mean([r["best"] for r in rs])
            print(f"    {k:<12}{w:>10.1f}{o:>14.1f}{o / (a.evals - a.initial):>10.3f}{b:>12.4f}")
        out["verdict"] = {}
        for k in ("ours", "ours+local"):
            if "skopt" in rows and k in rows:
                ratio = np.mean([r["optimizer_s"] for r in rows["skopt"]]) / max(
                    np.mean([r["optimizer_s"] for r in rows[k]]), 1e-9
                )
                # the target's both halves: a run whose loss half failed printed only the time's
                ours_loss = float(np.mean([r["best"] for r in rows[k]]))
                their_loss = float(np.mean([r["best"] for r in rows["skopt"]]))
                fast, low = bool(ratio >= 10.0), bool(ours_loss <= their_loss)
                out["verdict"][k] = {
                    "time_ratio": float(ratio),
                    "loss_vs_skopt": ours_loss / their_loss - 1.0 if their_loss else None,
                    "met": fast and low,
                }
                print(
                    f"    {k} against skopt: optimiser time {ratio:.1f}× less (target ≥ 10×: "
                    f"{'yes' if fast else 'NO'}); best loss {ours_loss:.4f} against "
                    f"{their_loss:.4f} (target ≤: {'yes' if low else 'NO'}): "
                    f"{'met' if fast and low else 'NOT met'}"
                )
    if a.json:
        write_json(a.json, {**out, "complete": True})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
