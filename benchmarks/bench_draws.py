"""How far apart two draws of a scene's answer are: one observation, several sets of seeds.

A fit's answer is one draw: its seeds' searches are chaotic in their inputs (a 1e-9 change of
the observation moves a seed: benchmarks/RESULTS.md, *#compile-state*), and the answer rule
picks among the basins they found. A setting judged by one fit per canopy is judged against
that draw's spread, which this measures. Fit a scene with more seeds than the flow's ten::

    cropcraft demo --store DIR --set fit.n_seeds=30
    cropcraft run SITE/CROP/DATE --images ... --set fit.n_seeds=30

then ``cropcraft bench draws SITE/CROP/DATE --store DIR``: the run's stored seeds (the best
row's ``fit/seed-{0..n_seeds-1}.npz``) are split in order into disjoint sets of ``--set-size``
(the flow's ``n_seeds``, ten), and each set is answered by each rule (the crop's default --
soybean's guarded median re-scores on the stored observation -- the seeds' median and the
paper's mean), as the flow's aggregate would have answered with those seeds; seeds 0-9 under
the crop's default are the flow's own answer. Each answer's traits are measured on the scene's
canopy seed (``generate/canopy.json``) and compared with the truth where there is one
(``{scene}/truth/metrics.json``, as the demo stores it, or ``--truth FILE``). Printed per rule:
each set's LAI (error), node count, and over the sets the mean |LAI error| and the spread
(max - min). Nothing is written to the store.
"""

from __future__ import annotations

import argparse
import dataclasses
import io
import json
import math
import time
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.options import at_least, json_file, output_file, write_json

TRAITS = ("lai", "node_count", "leaf_angle_mean_deg")


def load_scene(store, scene) -> dict[str, Any]:
    """What the answers need from a stored run: config, observation, seeds, canopy seed."""
    from cropcraft_core.errors import InputError
    from cropcraft_core.observe import Observation
    from cropcraft_core.optimize import SeedResult
    from flows.scene import stage_configs
    from tasks.common import artefact
    from tasks.fit_seed import fit_config, layout_of

    manifest = store.load_manifest(scene)
    stages = stage_configs(manifest.config, scene.crop)
    config = stages["aggregate"]
    # the run's own seeds, at the keys its seed tasks wrote (not those a run with more
    # seeds left behind)
    keys = {
        s: artefact(scene.prefix, "fit_seed", f"seed-{s}.npz")
        for s in range(fit_config(config).n_seeds)
    }
    missing = [key for key in keys.values() if not store.isfile(key)]
    if missing:
        raise InputError(
            f"{store.url(missing[0])}: fit seed not stored ({len(missing)} of {len(keys)} "
            "missing); run the scene first (with --set fit.n_seeds=30 for three draws)"
        )
    seeds: dict[int, Any] = {}
    for number, key in keys.items():
        with store.open_local(key) as path:
            seeds[number] = SeedResult.load(path)
    observation = Observation.load(
        io.BytesIO(store.get_bytes(f"{scene.prefix}/observe/observation.npz"))
    )
    canopy = store.get_json(f"{scene.prefix}/generate/canopy.json")
    return {
        "config": fit_config(config),
        "layout": layout_of(scene.crop, config),
        "seeds": seeds,
        "observation": observation,
        "canopy_seed": int(canopy["seed"]),
    }


def read_truth(store, scene, truth: str | None) -> dict[str, float] | None:
    """The true traits: ``--truth FILE`` (a ``metrics.json``), else the scene's stored truth
    (the demo's ``truth/metrics.json``), else None."""
    if truth is not None:
        data = json.loads(Path(truth).read_text())
    elif store.isfile(f"{scene.prefix}/truth/metrics.json"):
        data = store.get_json(f"{scene.prefix}/truth/metrics.json")
    else:
        return None
    return {k: float(data[k]) for k in TRAITS if data.get(k) is not None}


def run(
    store_root: str,
    scene_name: str,
    set_size: int | None = None,
    rules: list[str] | None = None,
    truth: str | None = None,
) -> dict[str, Any]:
    from cropcraft_core.errors import InputError
    from cropcraft_core.fit import combine
    from cropcraft_core.fit.fitting import RESCORING_RULES
    from cropcraft_core.metrics.rows import row_traits
    from cropcraft_core.store import SceneKey, SceneStore

    store = SceneStore(store_root)
    scene = SceneKey.parse(scene_name)
    got = load_scene(store, scene)
    cfg = got["config"]
    size = set_size or min(10, len(got["seeds"]))
    numbers = sorted(got["seeds"])
    sets = [numbers[i : i + size] for i in range(0, len(numbers) - size + 1, size)]
    if not sets:
        raise InputError(
            f"{scene}: {len(numbers)} stored seeds make no set of {size}; three draws need "
            f"{3 * size} (run the scene with --set fit.n_seeds={3 * size})"
        )
    rules = rules or list(dict.fromkeys([cfg.combine_rule(scene.crop), "median", "mean"]))
    true = read_truth(store, scene, truth)
    rows: dict[str, list[dict[str, Any]]] = {}
    for rule in rules:
        rows[rule] = []
        rule_cfg = dataclasses.replace(cfg, combine=rule)
        for members in sets:
            t0 = time.perf_counter()
            fit = combine(
                scene.crop,
                [got["seeds"][s] for s in members],
                rule_cfg,
                0.0,
                got["observation"] if rule in RESCORING_RULES else None,
                got["layout"],
            )
            traits = row_traits(scene.crop, fit.params, got["layout"], got["canopy_seed"])
            row: dict[str, Any] = {
                "seeds": f"{members[0]}-{members[-1]}",
                **{k: traits.get(k) for k in TRAITS},
                "params": fit.params,
                "seconds": time.perf_counter() - t0,
            }
            if true and true.get("lai") and traits.get("lai") is not None:
                row["lai_error"] = traits["lai"] / true["lai"] - 1.0
            rows[rule].append(row)
    summary = {}
    for rule, answers in rows.items():
        errs = [a["lai_error"] for a in answers if a.get("lai_error") is not None]
        lais = [a["lai"] for a in answers if a.get("lai") is not None]
        summary[rule] = {
            "mean_abs_lai_error": float(np.mean(np.abs(errs))) if errs else None,
            "lai_spread": float(max(lais) - min(lais)) if lais else None,
            "lai_error_spread": float(max(errs) - min(errs)) if errs else None,
        }
    return {
        "scene": str(scene),
        "store": store.root,
        "set_size": size,
        "n_stored_seeds": len(numbers),
        "truth": true,
        "answers": rows,
        "summary": summary,
    }


def _pct(v: float | None) -> str:
    return "-" if v is None or not math.isfinite(v) else f"{100 * v:+.1f} %"


def sets_of(res: dict[str, Any]) -> list[str]:
    return [a["seeds"] for a in next(iter(res["answers"].values()))]


def print_table(res: dict[str, Any]) -> None:
    true = res["truth"] or {}
    head = f"{res['scene']}: {res['n_stored_seeds']} stored seeds in sets of {res['set_size']}"
    if true.get("lai"):
        head += f"; true LAI {true['lai']:.3f}, nodes {true.get('node_count', math.nan):.2f}"
    sets = sets_of(res)
    if len(sets) < 2:
        head += " (one draw: no spread to measure)"
    print(head)
    head = f"{'rule':<10}" + "".join(f"{'seeds ' + s:>26}" for s in sets)
    print(head + f"{'mean |LAI err|':>16}{'spread':>10}")
    for rule, answers in res["answers"].items():
        cells = "".join(
            f"{a['lai']:>9.3f} ({_pct(a.get('lai_error')):>8}) {a['node_count']:>5.1f}n"
            for a in answers
        )
        s = res["summary"][rule]
        spread = s["lai_error_spread"]
        print(
            f"{rule:<10}{cells}{_pct(s['mean_abs_lai_error']).lstrip('+'):>16}"
            + (f"{100 * spread:>8.1f} pt" if spread is not None else f"{s['lai_spread']:>10.3f}")
        )


def main(argv: list[str] | None = None) -> int:
    from cropcraft_core.fit.fitting import COMBINE_RULES, OPT_IN_RULES

    ap = argparse.ArgumentParser(prog="cropcraft bench draws", description=__doc__.splitlines()[0])
    ap.add_argument(
        "scene",
        help="SITE/CROP/DATE of a stored run (fitted with more seeds than one set, e.g. 20+)",
    )
    ap.add_argument(
        "--store",
        default=None,
        help="scene store root (env CROPCRAFT_STORE; default ./cropcraft-data)",
    )
    ap.add_argument(
        "--set-size",
        type=at_least(1),
        default=None,
        help="seeds per draw (default: the flow's 10, or every stored seed where fewer)",
    )
    ap.add_argument(
        "--rule",
        action="append",
        choices=[r for r in COMBINE_RULES if r not in OPT_IN_RULES],  # floors: seed tasks
        help="answer rule (repeatable; default: the crop's, median, mean)",
    )
    ap.add_argument("--truth", type=json_file, default=None, help="metrics.json of the true canopy")
    ap.add_argument("--json", type=output_file, default=None)
    a = ap.parse_args(argv)
    res = run(a.store, a.scene, a.set_size, a.rule, a.truth)
    print_table(res)
    if a.json:
        write_json(a.json, res)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
