"""Fitting a plot over several of its rows: the best row's answer against the rows' mean.

    cropcraft bench rows --crop soybean [--first 0] [--scenes 12] [--neighbours 1]
                         [--image-scale 0.5] [--budget 10x500] [--workers 2]
                         [--checkpoint-dir DIR] [--json FILE] [--quick]

The accuracy benchmark's synthetic scenes (``bench_accuracy.scene_observation``: true
parameters drawn with the scene's seed, the true canopy, its depth from the row camera), each
also observed with the row camera moved by ±1 … ±``neighbours`` row spacings across the same
canopy (its other rows: other plants), as the scene flow's ``rows.neighbours`` observes a
plot. Every row is fitted alone at ``--budget``; the table compares, per answer rule, the
centre row's answer (the paper's one row) with the scene flow's ``rows.answer=mean`` (every
parameter's mean over the rows' answers, ``cropcraft_core.metrics.rows.rows_answer``) and the
mean of the rows' LAI, each fitted canopy built with the truth's canopy seed and measured like
the truth (LAIE, LAIPE and its median, the share within 15 %, AME, NDPE, NCPE).

Each (scene, row) is one job (``--workers`` single-threaded processes); ``--checkpoint-dir``
keeps every seed's checkpoint and each finished row's answers, so a killed run continues.
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

import numpy as np

from benchmarks.options import (
    at_least,
    folder,
    output_file,
    positive,
    seeds_by_evals,
    write_json,
)
from cropcraft_core.config import default_layout
from cropcraft_core.errors import ConfigError
from cropcraft_core.export.atomic import atomic_write_text
from cropcraft_core.metrics import canopy_metrics, evaluate
from cropcraft_core.parallel import processes, run_jobs
from cropcraft_core.procedural import generate_canopy
from cropcraft_core.store import config_hash

COLUMNS = ("LAIE", "LAIPE", "LAIPE_median", "LAI_within_15", "AME", "NDPE", "NCPE")
#: The answers compared per rule: the centre row alone, the rows' mean answer (one canopy),
#: the mean of the rows' LAI (a number only).
ANSWERS = ("centre row", "rows' mean", "mean of rows' LAI")


def row_observation(crop: str, index: int, row: int, scale: float):
    """Scene ``index``'s truth record and its observation over row ``row`` (0: the accuracy
    benchmark's own; ±k: the row camera moved by k planting row spacings)."""
    from benchmarks.bench_accuracy import scene_observation, scene_truth
    from cropcraft_core.fit import observe_canopy

    truth, obs = scene_observation(crop, index, scale)
    if row == 0:
        return truth, obs
    _, canopy = scene_truth(crop, index)
    spacing = default_layout(crop).row_spacing
    p = obs.preset
    return truth, observe_canopy(canopy, p, camera=p.row_camera((0.0, spacing * row)))


def _job(args) -> tuple[int, int, dict]:
    """Fit one row of one scene; ``{rule: params}`` (read back when kept)."""
    from benchmarks.bench_pipeline import fit_rules

    crop, index, row, scale, budget, options, ckpt = args
    # the folder is the crop's, scale's and row's (_where); the name the fit's settings
    name = f"answers-{budget}" + (f"-{config_hash(options)[:12]}" if options else "")
    kept = None if ckpt is None else Path(ckpt) / f"{name}.json"
    if kept is not None and kept.is_file():
        return index, row, json.loads(kept.read_text())
    _, obs = row_observation(crop, index, row, scale)
    seeds = None if ckpt is None else Path(ckpt) / "seeds"
    answers, _ = fit_rules(obs, budget, seeds, **options)
    if kept is not None:
        atomic_write_text(kept, json.dumps(answers, indent=1) + "\n")
    return index, row, answers


def _where(root: Path | None, crop: str, scale: float, index: int, row: int) -> str | None:
    """The checkpoint folder of one row of one scene: its seeds and kept answers. Crop and image
    scale name it too (another scale is another observation; its answers are not these)."""
    if root is None:
        return None
    return str(root / f"{crop}-scale{scale:g}" / f"scene{index}-row{row:+d}")


def _errors(preds: list[dict], truths: list[dict]) -> dict:
    errs = evaluate(preds, truths) if "node_count" in preds[0] else {}
    pe = np.array([abs(p["lai"] / t["lai"] - 1) for p, t in zip(preds, truths, strict=True)])
    lai = np.array([p["lai"] for p in preds]) - np.array([t["lai"] for t in truths])
    errs.update(
        LAIE=float(np.sqrt(np.mean(lai**2))),
        LAIPE=float(pe.mean()),
        LAIPE_median=float(np.median(pe)),
        LAI_within_15=float(np.mean(pe <= 0.15)),
    )
    return errs


def run(
    crop: str,
    first: int = 0,
    scenes: int = 12,
    neighbours: int = 1,
    scale: float = 0.5,
    budget: str = "10x500",
    workers: int = 1,
    checkpoint_dir: str | None = None,
    log=print,
    fit_options: dict | None = None,
) -> dict:
    """The table (see the module docstring); ``fit_options``: further ``FitConfig`` fields for
    every row's fit (``--quick``: a small re-scoring), part of the kept answers' names."""
    from cropcraft_core.metrics.rows import rows_answer

    if neighbours < 1:
        raise ConfigError("bench rows needs at least one neighbour row on each side")
    rows = list(range(-neighbours, neighbours + 1))
    indices = list(range(first, first + scenes))
    root = None if checkpoint_dir is None else Path(checkpoint_dir)
    jobs = [
        (crop, i, k, scale, budget, dict(fit_options or {}), _where(root, crop, scale, i, k))
        for i in indices
        for k in rows
    ]
    fitted: dict[tuple[int, int], dict] = {}
    with processes(workers) as ex:
        for i, k, answers in run_jobs(ex, _job, jobs):
            fitted[i, k] = answers
            log(f"  {crop} scene {i} row {k:+d}: fitted")
    from benchmarks.bench_accuracy import canopy_seed

    truths = [row_observation(crop, i, 0, scale)[0] for i in indices]
    layout = default_layout(crop)

    def measure(params: dict, i: int) -> dict:  # on the scene's own true canopy's seed
        canopy = generate_canopy(crop, params, layout, seed=canopy_seed(i))
        return {"params": params, **canopy_metrics(canopy, gap_fraction=False)}

    table: dict[str, dict[str, dict]] = {}
    per_scene = []
    for rule in fitted[indices[0], 0]:
        preds = {name: [] for name in ANSWERS}
        for i in indices:
            each = {k: measure(fitted[i, k][rule], i) for k in rows}
            mean = rows_answer({k: {"params": fitted[i, k][rule]} for k in rows}, "mean")
            preds["centre row"].append(each[0])
            preds["rows' mean"].append(measure(mean["params"], i))
            lai = float(np.mean([e["lai"] for e in each.values()]))
            preds["mean of rows' LAI"].append({"lai": lai})
            per_scene.append(
                {"scene": i, "rule": rule, "lai_by_row": {str(k): each[k]["lai"] for k in rows}}
            )
        table[rule] = {name: _errors(p, truths) for name, p in preds.items()}
    return {
        "crop": crop,
        "scenes": indices,
        "rows": rows,
        "image_scale": scale,
        "budget": budget,
        "table": table,
        "per_scene": per_scene,
        "truth_lai": [t["lai"] for t in truths],
    }


def print_table(res: dict) -> None:
    print(
        f"\n{res['crop']}: scenes {res['scenes'][0]}-{res['scenes'][-1]}, rows {res['rows']}, "
        f"{res['budget']} at {res['image_scale']} x 994x738"
    )
    print(f"{'rule':<26}{'answer':<20}" + "".join(f"{c:>14}" for c in COLUMNS))
    for rule, answers in res["table"].items():
        for name, errs in answers.items():
            cells = "".join(f"{errs[c]:>14.3f}" if c in errs else f"{'-':>14}" for c in COLUMNS)
            print(f"{rule:<26}{name:<20}{cells}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="cropcraft bench rows", description=__doc__.splitlines()[0])
    ap.add_argument("--crop", required=True, choices=["soybean", "maize"])
    ap.add_argument("--first", type=at_least(0), default=0, help="first scene number")
    ap.add_argument("--scenes", type=at_least(1), help="how many scenes (default 12; --quick 1)")
    ap.add_argument(
        "--neighbours", type=at_least(1), default=1, help="rows on each side of the centre"
    )
    ap.add_argument("--image-scale", type=positive, help="row camera / 994x738 (default 0.5)")
    ap.add_argument(
        "--budget",
        type=seeds_by_evals,
        help="SEEDSxEVALS per row (default 10x500; --quick 2x20)",
    )
    ap.add_argument(
        "--quick",
        action="store_true",
        help="1 scene, 2x20, quarter resolution, re-scoring on 2 canopies with a 4-step polish",
    )
    ap.add_argument("--workers", type=at_least(1), default=os.cpu_count() or 1)
    ap.add_argument("--checkpoint-dir", type=folder, help="seed checkpoints and each row's answers")
    ap.add_argument("--json", type=output_file)
    a = ap.parse_args(argv)
    res = run(
        a.crop,
        a.first,
        a.scenes if a.scenes is not None else (1 if a.quick else 12),
        a.neighbours,
        a.image_scale if a.image_scale is not None else (0.25 if a.quick else 0.5),
        a.budget if a.budget is not None else ("2x20" if a.quick else "10x500"),
        a.workers,
        a.checkpoint_dir,
        fit_options={"reevaluate_canopies": 2, "polish_evals": 4} if a.quick else None,
    )
    print_table(res)
    if a.json:
        write_json(a.json, res)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
