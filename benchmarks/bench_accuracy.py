"""Synthetic accuracy benchmark (the paper's Table "Synthetic data evaluation").

    cropcraft bench accuracy --crop soybean [--scenes 30] [--methods bo,trust-region,random,mlp]
                             [--quick] [--crn-ablation] [--json FILE]

For each scene: true parameters drawn uniformly (seeded), the true canopy built with its own
seed, its depth rendered from the row camera as the observation (no background), a fit per
method, and the fitted canopy measured like the truth. Prints LAIE, LAIPE (and its median), AME,
ASDE, NDPE, NCPE per method beside the paper's synthetic numbers. ``--quick`` is a reduced
budget (quarter resolution, 2 seeds × 60 evaluations, 6 scenes) for smoke runs and tests.
``--crn-ablation`` adds a BO row without common random numbers.
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import dataclass

import numpy as np

from cropcraft_core.config import default_layout, param_space
from cropcraft_core.fit import FitConfig, fit_observation, observe_canopy
from cropcraft_core.metrics import canopy_metrics, evaluate
from cropcraft_core.observe import preset
from cropcraft_core.procedural import generate_canopy

PAPER = {  # Table "Synthetic data evaluation": LAIE, NDPE, NCPE
    ("soybean", "bo"): {"LAIE": 0.97, "NDPE": 0.21, "NCPE": 0.23},
    ("maize", "bo"): {"LAIE": 0.13, "NDPE": 0.05, "NCPE": 0.08},
    ("soybean", "trust-region"): {"LAIE": 2.49, "NDPE": 0.48, "NCPE": 0.91},
    ("maize", "trust-region"): {"LAIE": 1.46, "NDPE": 0.13, "NCPE": 0.70},
}
COLUMNS = ("LAIE", "LAIPE", "LAIPE_median", "AME", "ASDE", "NDPE", "NCPE")


@dataclass(frozen=True)
class Budget:
    scenes: int
    fit: FitConfig
    scale: float  # image resolution relative to the paper's 994 × 738


def budget(
    quick: bool,
    scenes: int | None,
    method: str,
    crn: bool = True,
    overrides: dict | None = None,
    scale: float | None = None,
) -> Budget:
    """The quick or default budget, with optional FitConfig overrides (n_seeds, n_evals, ...)."""
    o = {k: v for k, v in (overrides or {}).items() if v is not None}
    if quick:
        fit = {"n_seeds": 2, "n_evals": 60, "n_initial": 25, **o}
        cfg = FitConfig(method=method, common_random_numbers=crn, **fit)
        return Budget(scenes or 6, cfg, scale or 0.25)
    cfg = FitConfig(method=method, common_random_numbers=crn, **o)
    return Budget(scenes or 30, cfg, scale or 1.0)


def scene_truth(crop: str, index: int, seed: int = 2024):
    rng = np.random.default_rng([seed, index])
    params = {s.name: float(rng.uniform(s.low, s.high)) for s in param_space(crop)}
    canopy = generate_canopy(crop, params, default_layout(crop), seed=100_000 + index)
    return params, canopy


def run(
    crop: str,
    methods: list[str],
    quick: bool,
    scenes: int | None,
    crn_ablation: bool = False,
    log=print,
    overrides: dict | None = None,
    scale: float | None = None,
) -> dict:
    runs = [(m, m, True) for m in methods]
    if crn_ablation and "bo" in methods:
        runs.append(("bo-no-crn", "bo", False))
    b0 = budget(quick, scenes, "bo", overrides=overrides, scale=scale)
    size = {"image_width": round(994 * b0.scale), "image_height": round(738 * b0.scale)}
    p = preset(crop, **size)
    truths, observations = [], []
    for i in range(b0.scenes):
        params, canopy = scene_truth(crop, i)
        truths.append({"params": params, **canopy_metrics(canopy, gap_fraction=False)})
        observations.append(observe_canopy(canopy, p, meta={"scene": i}))
    out = {
        "crop": crop,
        "quick": quick,
        "scenes": b0.scenes,
        "methods": {},
        "budget": {**b0.fit.to_dict(), "image_scale": b0.scale},
    }
    for label, method, crn in runs:
        b = budget(quick, scenes, method, crn, overrides, scale)
        preds, seconds = [], []
        for i, obs in enumerate(observations):
            t = time.perf_counter()
            mlp_cfg = None
            if method == "mlp" and quick:
                from cropcraft_core.fit.mlp import MLPConfig, predict_params

                mlp_cfg = MLPConfig(n_pairs=400, epochs=60)
                params = predict_params(obs, mlp_cfg)
            else:
                params = fit_observation(obs, b.fit).params
            fitted = generate_canopy(crop, params, default_layout(crop), seed=100_000 + i)
            preds.append({"params": params, **canopy_metrics(fitted, gap_fraction=False)})
            seconds.append(time.perf_counter() - t)
            log(
                f"  {crop} {label} scene {i}: LAI {preds[-1]['lai']:.2f} "
                f"(true {truths[i]['lai']:.2f}) in {seconds[-1]:.0f} s"
            )
        errs = evaluate(preds, truths)
        lai_pe = [
            abs(p_["lai"] - t_["lai"]) / t_["lai"] for p_, t_ in zip(preds, truths, strict=True)
        ]
        errs["LAIPE_median"] = float(np.median(lai_pe))
        out["methods"][label] = {
            "errors": errs,
            "seconds_per_scene": float(np.mean(seconds)),
            "predictions": preds,
        }
    out["truths"] = truths
    return out


def print_table(res: dict) -> None:
    crop = res["crop"]
    b = res.get("budget", {})
    print(
        f"\nSynthetic accuracy, {crop}, {res['scenes']} scenes"
        f"{' (quick budget)' if res['quick'] else ''}: {b.get('n_seeds')} seeds x "
        f"{b.get('n_evals')} evaluations ({b.get('n_initial')} initial), row camera at "
        f"{b.get('image_scale')} x 994x738"
    )
    head = f"{'method':<16}" + "".join(f"{c:>13}" for c in COLUMNS) + f"{'s/scene':>10}"
    print(head)
    print("-" * len(head))
    for label, r in res["methods"].items():
        e = r["errors"]
        cells = "".join(f"{e[c]:>13.3f}" if e.get(c) is not None else f"{'-':>13}" for c in COLUMNS)
        print(f"{label:<16}{cells}{r['seconds_per_scene']:>10.1f}")
        paper = PAPER.get((crop, label))
        if paper:
            cells = "".join(f"{paper[c]:>13.2f}" if c in paper else f"{'':>13}" for c in COLUMNS)
            print(f"{'  paper ' + label:<16}{cells}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--crop", required=True, choices=["soybean", "maize"])
    ap.add_argument("--scenes", type=int)
    ap.add_argument("--methods", default="bo,trust-region,random,mlp")
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--crn-ablation", action="store_true")
    ap.add_argument("--json")
    ap.add_argument("--seeds", type=int, help="override optimiser seeds per scene")
    ap.add_argument("--evals", type=int, help="override evaluations per seed")
    ap.add_argument("--initial", type=int, help="override random initial evaluations")
    ap.add_argument("--canopies", type=int, help="override canopies averaged per evaluation")
    ap.add_argument("--image-scale", type=float, help="row camera resolution / 994x738")
    a = ap.parse_args(argv)
    methods = [m.strip() for m in a.methods.split(",") if m.strip()]
    overrides = {
        "n_seeds": a.seeds,
        "n_evals": a.evals,
        "n_initial": a.initial,
        "canopies_per_eval": a.canopies,
    }
    res = run(
        a.crop, methods, a.quick, a.scenes, a.crn_ablation, overrides=overrides, scale=a.image_scale
    )
    print_table(res)
    if a.json:
        with open(a.json, "w") as f:
            json.dump(res, f, indent=2, default=float)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
