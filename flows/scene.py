"""The scene flow: photos of one plot on one date → canopy, traits, bundle and report.

    ingest → poses → surfaces → rowfit → observe → fit_seed × n (mapped) → aggregate
           → generate → metrics → export → report
    rowfit → consistency (the surfaces against the photos, beside the fit) → report

Each stage is one task of ``tasks/`` (read the store, call ``cropcraft_core``, write the store,
return a small record); this module only validates the request, resolves the configuration,
wires the tasks and keeps the scene's manifest up to date.

Idempotence. Every task's cache key is ``{scene}/.prefect/{stage}/{sha256(stage, version,
scene, stage-config hash, upstream artefact hashes, seed)}`` (``tasks.common.stage_key``) and
its result is persisted there, under the scene store's root. So a rerun with the same inputs is
``Cached`` everywhere; a changed stage config recomputes that stage and, where its outputs
change, everything after it; a run that failed in one seed reruns only that seed and what
follows. :func:`cached_result` walks the same keys without Prefect, which answers an unchanged
scene in about a second.
"""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import json
import math
import os
import time
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path, PurePosixPath
from typing import Any, Literal

from prefect import flow, get_run_logger, unmapped

from cropcraft_core.errors import ConfigError, CropCraftError, InputError
from cropcraft_core.lease import SceneLease, hold_scene, refuse_if_busy
from cropcraft_core.sfm.ingest import IMAGE_EXTENSIONS
from cropcraft_core.store import SceneKey, SceneStore, config_hash, sha256_bytes
from flows.runners import DEFAULT_RUNNER, make_task_runner
from flows.watch import watch_this_run
from tasks.common import fingerprint, get_task, photos_left_out, stage_key
from tasks.fit_seed import row_spacing_used

# --------------------------------------------------------------------------- configuration

#: Embedded defaults of every stage (the paper's settings; override by section and key).
DEFAULTS: dict[str, dict[str, Any]] = {
    "layout": {},
    "ingest": {"max_size": None, "min_images": 3},
    "poses": {
        "matcher": "auto",
        "sift_peak_threshold": None,  # None: run_sfm's (SIFT_PEAK_THRESHOLD)
        "guided_matching": False,  # epipolar re-matching: slower and less accurate on canopies
        # each SfM camera starts from the focal length in its photos' EXIF (false: from
        # COLMAP's guess, 1.2 x the longer side; for photos whose EXIF is known to be wrong)
        "exif_focal": True,
        "seed": 0,
        "num_threads": 2,
        # imported poses in metres and gravity-aligned: true, false, or "auto" (a
        # transforms.json of an AR capture is; a COLMAP model, or a transforms.json that
        # ns-process-data made from an SfM project, with applied_transform, is not)
        "imported_metric": "auto",
        # all poses are levelled (z up, plot-centred); SfM and non-metric imported ones are
        # also scaled to ~metres by:
        "camera_height": None,  # measured median camera height (m): exact scale
        "camera_distance": None,  # [photo A, photo B, metres between their cameras]: exact scale
        "prior_camera_height": None,  # assumed one (None: the crop's typical capture)
        # ... or, where neither is given, by the photos' own EXIF GPS positions where they
        # spread far enough against their error to set it (cropcraft_core.sfm.gps)
        "gps": True,
    },
    # bbox "auto": the crop's scene box around the levelled frame's origin; the crop's own
    # settings (cropcraft_core.surfaces.CROP_SURFACES: maize splats points) go over these
    "surfaces": {"backend": "tsdf", "bbox": "auto", "n_points": 100_000},
    # the paper's row-fit scene box is in nerfstudio's normalised frame; ours is the surfaces'
    "rowfit": {"seed": 0, "scale": None, "preset": {"box_center": None, "box_size": None}},
    # the surfaces against the photos at the photos' own cameras (a diagnostic; nothing the fit
    # reads): photos compared, height (m) from which a surface is raised, the |net| cover
    # share past which a run warns (None: the crop's, cropcraft_core.surfaces.consistency.
    # NET_WARN: soybean 0.15, maize none)
    "consistency": {"max_views": 12, "min_height": 0.02, "warn": None},
    # prediction_blur: metres by which the fit blurs its predictions (0: none, the paper's);
    # "auto": the surfaces' own softening of the leaves near their edges (tsdf: 0.8 voxel;
    # cropcraft_core.surfaces.prediction_blur_m). Not the default: better on three of six
    # canopies, worse on three; only one of the six observations matches its true mesh
    # better blurred (benchmarks/RESULTS.md, #blur, #blur-match)
    "observe": {"image_scale": 1.0, "prediction_blur": 0.0, "preset": {}},
    "fit": {
        "method": "bo",
        "n_seeds": 10,
        "n_evals": 500,
        "n_initial": 200,
        # known parameters: name -> value (fixed) or [low, high] (``FitConfig.box``)
        "box": {},
        "common_random_numbers": True,
        "refit_every": 10,
        # what BO's GP models: the loss ("none") or its logarithm ("log"); None: the crop's
        # (FitConfig, DEFAULT_GP_OUTPUT)
        "gp_output": None,
        "local_share": None,  # share of each seed's evaluations spent last on Nelder-Mead
        # "pooled" (the loss of the canopies' mean statistics) or "unbiased" (without their
        # draw variance; FitConfig.loss_estimator)
        "loss_estimator": "pooled",
        # (None: the crop's, FitConfig)
        "canopies_per_eval": None,  # None: the crop's default (FitConfig)
        "combine": None,  # None: the crop's (FitConfig); "median", "mean" (paper's), "reevaluate",
        # "guarded", "floors" (opt-in: each seed polishes its point, so its seeds are its own)
        "reevaluate_canopies": 16,
        "polish_starts": 1,  # "reevaluate": refine the lowest re-scored candidate(s) ...
        "polish_evals": 60,  # ... by Nelder-Mead on the same canopies (0: none)
    },
    # the best row's neighbours, each observed and fitted as the best row (0: the paper's one
    # row); a neighbour whose view lacks surface over more than max_no_surface and more than
    # the best row's own view is left out
    # answer: "best" (the best row's, the others reported beside it) or "mean" (every
    # parameter's mean over the rows' answers: not better on 12 benchmark scenes, RESULTS
    # #rows-34); see cropcraft_core.metrics.rows.ROW_ANSWERS
    # snap: None places the k-th neighbour's camera k row spacings from the best row's (on the
    # row pattern); a fraction in (0, 0.5) moves it onto a fitted row within that fraction of
    # a spacing (plots not planted evenly; the fitted side rows are plain RANSAC lines, 7 cm
    # off on the demo's canopy through SfM: cropcraft_core.rowfit.neighbours)
    "rows": {"neighbours": 0, "max_no_surface": 0.18, "answer": "best", "snap": None},
    "generate": {"seed": 0},
    # seed: the gap-fraction sensors' (None: the canopy's, as cropcraft generate measures it)
    "metrics": {"gap_fraction": True, "seed": None, "seed_traits": True},
    "export": {},
    "report": {"n_thumbnails": 6, "thumbnail_px": 192},
}

#: Sections whose keys are free-form (checked by the core function that uses them).
_OPEN_SECTIONS = {"layout", "surfaces"}
_OPEN_KEYS = {"preset", "box"}


def _set_dotted(cfg: dict, dotted: str, value: Any) -> None:
    section, _, key = dotted.partition(".")
    if section not in cfg:
        raise ConfigError(
            f"unknown config section {section!r} in override {dotted!r}: one of {', '.join(cfg)}"
        )
    if not key:
        if not isinstance(value, Mapping):
            raise ConfigError(f"override {dotted!r} must be a mapping of settings")
        for k, v in value.items():
            _set_dotted(cfg, f"{section}.{k}", v)
        return
    head, _, rest = key.partition(".")
    if section not in _OPEN_SECTIONS and head not in cfg[section]:
        raise ConfigError(
            f"unknown setting {dotted!r}: {section} has {', '.join(cfg[section]) or 'none'}"
        )
    if rest:
        if head not in _OPEN_KEYS and section not in _OPEN_SECTIONS:
            raise ConfigError(f"setting {section}.{head} takes a value, not {dotted!r}")
        target = cfg[section].setdefault(head, {})
        if not isinstance(target, dict):
            raise ConfigError(f"setting {section}.{head} is not a mapping")
        target[rest] = value
    else:
        if head in _OPEN_KEYS and not isinstance(value, Mapping):
            raise ConfigError(f"setting {dotted!r} must be a mapping of settings, got {value!r}")
        cfg[section][head] = value


#: The surfaces backends a scene flow takes as its own ``surfaces_backend`` parameter (the UI
#: offers them as a choice): :data:`cropcraft_core.surfaces.BACKENDS` but the benchmarks' truth.
SurfacesBackend = Literal["tsdf", "points", "nerfacto"]


def with_backend(
    overrides: Mapping[str, Any] | None, backend: SurfacesBackend | None
) -> dict[str, Any]:
    """``overrides`` over ``surfaces.backend = backend`` (``None``: the crop's default backend).

    A deployment names its backend in this parameter, not in ``overrides``: Prefect merges a
    run's parameters into the deployment's one level deep, so a run's own ``overrides`` would
    replace the deployment's whole and drop its backend. A run's own ``surfaces.backend``
    override still wins.
    """
    if backend is None:
        return dict(overrides or {})
    return {"surfaces.backend": backend, **dict(overrides or {})}


#: Settings whose value may be of another kind than their default's (checked where used).
_OTHER_KINDS = {("observe", "prediction_blur"), ("poses", "imported_metric")}


def _check_kinds(cfg: dict[str, Any]) -> None:
    """Every setting whose default is a boolean, whole number, number or text holds one of the
    same kind (a whole number may be written 1e1; it is stored as 10): ``--set`` keeps a value
    that is not JSON as text, so ``fit.n_seeds=abc`` or ``poses.guided_matching=False`` (not
    JSON's false, and true as Python reads a non-empty text) must stop here, not in a stage
    after the photos were ingested."""
    for section, defaults in DEFAULTS.items():
        if section in _OPEN_SECTIONS:
            continue
        for key, default in defaults.items():
            if (section, key) in _OTHER_KINDS or default is None or isinstance(default, dict):
                continue
            v = cfg[section][key]
            name = f"{section}.{key}"
            if isinstance(default, bool):
                if not isinstance(v, bool):
                    raise ConfigError(f"{name} must be true or false, got {v!r}")
            elif isinstance(default, int):
                whole = isinstance(v, float) and math.isfinite(v) and v == int(v)
                if not (isinstance(v, int) and not isinstance(v, bool)) and not whole:
                    raise ConfigError(f"{name} must be a whole number, got {v!r}")
                cfg[section][key] = int(v)
            elif isinstance(default, float):
                if not isinstance(v, int | float) or isinstance(v, bool) or not math.isfinite(v):
                    raise ConfigError(f"{name} must be a number, got {v!r}")
            elif isinstance(default, str) and not isinstance(v, str):
                raise ConfigError(f"{name} must be text, got {v!r}")
    for (section, key), low in _LEAST.items():
        if cfg[section][key] < low:
            raise ConfigError(f"{section}.{key} must be at least {low}, got {cfg[section][key]!r}")
    if cfg["generate"]["seed"] >= 2**32:  # the canopy's random streams take 32 bits
        raise ConfigError(f"generate.seed must be below 2**32, got {cfg['generate']['seed']}")
    if cfg["poses"]["matcher"] not in ("auto", "exhaustive", "sequential"):
        raise ConfigError(
            f"poses.matcher must be auto, exhaustive or sequential, got {cfg['poses']['matcher']!r}"
        )
    for (section, key), (low, what) in _LEAST_OR_NULL.items():
        v = cfg[section][key]
        if (
            v is not None
            and (not isinstance(v, int | float) or isinstance(v, bool) or not low <= v < math.inf)
            or v == 0
        ):
            raise ConfigError(f"{section}.{key} must be {what} or null, got {v!r}")


#: Least values of whole-number settings that no core function checks before its stage runs.
_LEAST = {
    ("ingest", "min_images"): 1,
    ("poses", "num_threads"): 1,
    ("poses", "seed"): 0,
    ("rowfit", "seed"): 0,
    ("generate", "seed"): 0,
    ("report", "n_thumbnails"): 0,
    ("report", "thumbnail_px"): 16,
}
#: ... and of number settings that may be null (their stage's own default; 0: positive).
_LEAST_OR_NULL = {
    ("ingest", "max_size"): (16, "at least 16"),
    ("poses", "sift_peak_threshold"): (0, "a positive number"),
    ("poses", "camera_height"): (0, "a positive number of metres"),
    ("poses", "prior_camera_height"): (0, "a positive number of metres"),
    ("rowfit", "scale"): (0, "a positive number"),
}


def resolve_config(crop: str, overrides: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """The scene config: :data:`DEFAULTS` with ``overrides`` applied and checked.

    overrides: nested (``{"fit": {"n_evals": 60}}``) or dotted (``{"fit.n_evals": 60,
    "observe.preset.lambda_sobel": 2}``). Unknown sections or settings, and values a core
    config refuses, raise ConfigError before any work starts.
    """
    cfg = copy.deepcopy(DEFAULTS)
    try:
        from cropcraft_core.surfaces import (
            CROP_SURFACES,
            NERF_PAPER,
            SurfacesConfig,
            resolve_bbox,
        )
    except ImportError:  # the surfaces package is optional in a partial checkout
        SurfacesConfig = None
    else:  # the crop's measured surfaces settings, under the user's overrides
        cfg["surfaces"].update(CROP_SURFACES.get(crop, {}))
    for k, v in (overrides or {}).items():
        _set_dotted(cfg, str(k), v)
    _check_kinds(cfg)
    given = dict(overrides or {})
    if "fit.n_initial" not in given and "n_initial" not in (given.get("fit") or {}):
        from cropcraft_core.fit.fitting import initial_evals

        # 40 % of the budget, the paper's 200 of 500: a budget of 200 kept 200 random points
        # and no GP step (a random search named bo), and one under 200 was refused
        cfg["fit"]["n_initial"] = initial_evals(cfg["fit"]["n_evals"])
    if SurfacesConfig is not None and cfg["surfaces"].get("backend") == "nerfacto":
        # the paper's settings and the far-plane margin, under the user's own; written out so
        # that the stage's key holds them (surfaces trained with nerfstudio's far plane, before
        # the margin, are not served again)
        nerf = {**NERF_PAPER.get(crop, {}), "nerf_far_margin": SurfacesConfig.nerf_far_margin}
        for k, v in nerf.items():
            cfg["surfaces"].setdefault(k, v)
    from cropcraft_core.config import default_layout
    from cropcraft_core.config.layout import CanopyLayout
    from cropcraft_core.fit import FitConfig
    from cropcraft_core.observe import check_prediction_blur
    from cropcraft_core.observe import preset as observe_preset
    from cropcraft_core.rowfit import preset as rowfit_preset

    known = {f.name for f in dataclasses.fields(CanopyLayout)}
    unknown = sorted(set(cfg["layout"]) - known)
    if unknown:  # named, not CanopyLayout.__init__'s "unexpected keyword argument"
        raise ConfigError(
            f"unknown setting layout.{unknown[0]}: the layout's are "
            + ", ".join(f"layout.{k}" for k in sorted(known))
        )
    try:
        default_layout(crop, **cfg["layout"])
    except TypeError as exc:
        raise ConfigError(f"invalid layout override {cfg['layout']}: {exc}") from None
    try:
        fit = FitConfig(**cfg["fit"]).validate()
        fit.param_box(crop)
        if fit.method == "bo":  # the optimiser's own settings, checked here not at the seeds
            fit.bo_config(crop).validate()
    except ConfigError as exc:  # named as the user sets them
        raise ConfigError(f"fit settings (fit.*): {exc}") from None
    # a layout keys its stages as numbers: --row-spacing 1's 1.0 is --set layout.row_spacing=1
    # (whole numbers as ints, as --set and known.json have always written them: their stores'
    # stages stay keyed as they were)
    cfg["layout"] = {
        k: int(v) if isinstance(v, float) and v.is_integer() else v
        for k, v in cfg["layout"].items()
    }
    # a known parameter keys its fit as a number: known.json's 9 (or --set's) is --param's 9.0
    cfg["fit"]["box"] = {
        k: [float(x) for x in v] if isinstance(v, list | tuple) else float(v)
        for k, v in cfg["fit"]["box"].items()
    }
    n_points = cfg["surfaces"]["n_points"]
    if not isinstance(n_points, int) or isinstance(n_points, bool) or n_points < 1:
        raise ConfigError(f"surfaces.n_points must be a whole number >= 1, got {n_points!r}")
    if cfg["fit"]["method"] == "mlp":  # refused here, not at the seeds after SfM and surfaces
        raise ConfigError(
            "fit.method=mlp: the scene flow maps optimiser seeds (bo, trust-region, random); "
            "the mlp baseline predicts in one step: `cropcraft fit --method mlp --geometry "
            "FILE.ply` or `cropcraft bench accuracy --methods mlp`"
        )
    rowfit_preset(crop, **cfg["rowfit"]["preset"])
    observe_preset(crop, **cfg["observe"]["preset"])
    if SurfacesConfig is not None:
        s = {k: v for k, v in cfg["surfaces"].items() if k not in ("bbox", "n_points")}
        SurfacesConfig.from_dict(s)
        resolve_bbox(cfg["surfaces"]["bbox"], crop)
    cd = cfg["poses"]["camera_distance"]
    if cd is not None and not (
        isinstance(cd, list | tuple)
        and len(cd) == 3
        and all(isinstance(x, str) and x for x in cd[:2])
        and isinstance(cd[2], int | float)
        and not isinstance(cd[2], bool)
        and 0 < cd[2] < math.inf
    ):
        raise ConfigError(
            "poses.camera_distance must be [photo A, photo B, metres between their cameras] "
            f"or null, got {cd!r}"
        )
    if cd is not None and cfg["poses"]["camera_height"] is not None:
        raise ConfigError("give poses.camera_height or poses.camera_distance, not both")
    if not 0 < float(cfg["observe"]["image_scale"]) <= 4:
        raise ConfigError("observe.image_scale must be in (0, 4]")
    if "prediction_blur_m" in cfg["observe"]["preset"]:
        raise ConfigError(
            "observe.preset.prediction_blur_m is set by the observe stage: set "
            "observe.prediction_blur ('auto' or metres) instead"
        )
    check_prediction_blur(cfg["observe"]["prediction_blur"], "observe.prediction_blur")
    c = cfg["consistency"]
    mv = c["max_views"]
    if not isinstance(mv, int) or isinstance(mv, bool) or mv < 1:
        raise ConfigError(f"consistency.max_views must be a whole number >= 1, got {mv!r}")
    for key in ("min_height", "warn"):
        v = c[key]
        if v is None and key == "warn":
            continue
        if not isinstance(v, int | float) or isinstance(v, bool) or not 0 <= v < 1:
            raise ConfigError(f"consistency.{key} must be a number in [0, 1), got {v!r}")
    from cropcraft_core.rowfit.neighbours import MAX_NEIGHBOURS

    n = cfg["rows"]["neighbours"]
    if not isinstance(n, int) or isinstance(n, bool) or not 0 <= n <= MAX_NEIGHBOURS:
        raise ConfigError(
            f"rows.neighbours must be a whole number of rows on each side, 0 to "
            f"{MAX_NEIGHBOURS}, got {n!r}"
        )
    from cropcraft_core.metrics.rows import ROW_ANSWERS

    if cfg["rows"]["answer"] not in ROW_ANSWERS:
        raise ConfigError(
            f"rows.answer must be one of {', '.join(ROW_ANSWERS)}, got {cfg['rows']['answer']!r}"
        )
    x = cfg["rows"]["max_no_surface"]
    if not isinstance(x, int | float) or isinstance(x, bool) or not 0 < x <= 1:
        raise ConfigError(f"rows.max_no_surface must be a fraction in (0, 1], got {x!r}")
    snap = cfg["rows"]["snap"]
    if snap is not None and (
        not isinstance(snap, int | float) or isinstance(snap, bool) or not 0 < snap < 0.5
    ):
        raise ConfigError(
            f"rows.snap must be null (cameras k row spacings apart) or a fraction of a row "
            f"spacing in (0, 0.5), got {snap!r}"
        )
    if cfg["poses"]["imported_metric"] not in (True, False, "auto"):
        raise ConfigError(
            f"poses.imported_metric must be true, false or auto, got "
            f"{cfg['poses']['imported_metric']!r}"
        )
    seed = cfg["metrics"]["seed"]
    if seed is not None and (not isinstance(seed, int) or isinstance(seed, bool) or seed < 0):
        raise ConfigError(f"metrics.seed must be null or a whole number >= 0, got {seed!r}")
    _check_camera_height(crop, cfg["poses"]["camera_height"])
    return cfg


#: The camera heights (m) a capture can have, whatever the crop: a phone held low to a drone at
#: the 120 m most countries allow. Outside, the height is refused as a slip of units: 140 (cm)
#: given for soybean photos passed and the run failed in the stereo naming the poses and the
#: box, never the height. (A factor of 20 from the crop's usual height refused a 30 m soybean
#: drone flight as centimetres and a phone at 0.6 m over maize: session 96's capture audit.)
CAMERA_HEIGHT_RANGE_M = (0.3, 120.0)


def _check_camera_height(crop: str, height: float | None) -> None:
    from cropcraft_core.sfm.frame import PRIOR_CAMERA_HEIGHT_M

    low, high = CAMERA_HEIGHT_RANGE_M
    if height is None or low <= height <= high:
        return
    usual = PRIOR_CAMERA_HEIGHT_M.get(crop)
    unit = "centimetres" if height > high else "another unit"
    raise ConfigError(
        f"poses.camera_height {height:.10g} m is outside the {low:g}-{high:g} m photos are taken "
        f"from"
        + (f" ({crop}'s usual capture height is {usual:g} m)" if usual else "")
        + f": is it in {unit}? (give the cameras' median height above the ground in metres)"
    )


def _layout_given(layout: Mapping[str, Any], crop: str | None) -> dict[str, Any]:
    """The layout settings that differ from the crop's default layout: one written out at its
    default value (``layout.row_spacing=0.76`` for soybean) is the same layout, keyed as if
    not given, not a refit of every stage that builds canopies."""
    if crop is None:
        return dict(layout)
    from cropcraft_core.config import default_layout

    default = default_layout(crop)
    return {k: v for k, v in layout.items() if getattr(default, k, object()) != v}


def stage_configs(cfg: Mapping[str, Any], crop: str | None = None) -> dict[str, dict[str, Any]]:
    """The config each task sees (and its cache key hashes): its own section, plus the planting
    layout for the stages that build canopies. With ``crop``, the fit settings left to the
    crop's defaults are written out -- the answer rule (``DEFAULT_COMBINE``), the canopies
    averaged per evaluation (``DEFAULT_CANOPIES``), what BO's GP models (``DEFAULT_GP_OUTPUT``)
    and BO's closing local search (``DEFAULT_LOCAL_SHARE``) -- so that a release changing a
    default re-aggregates or refits cached seeds instead of serving the old default's answer;
    likewise the surfaces' ``"auto"`` scene box is written out as the crop's box
    (``SCENE_BOX``). (nerfacto's defaults are written out by :func:`resolve_config`.)"""
    from cropcraft_core.fit.fitting import AGGREGATE_ONLY, FitConfig

    layout = {"layout": _layout_given(cfg["layout"], crop)}
    fit = dict(cfg["fit"])
    if not fit.get("box"):  # the whole box hashes as before the setting existed
        fit.pop("box", None)
    if fit.get("loss_estimator", "pooled") == "pooled":  # likewise the paper's estimator
        fit.pop("loss_estimator", None)
    agg_only: dict[str, Any] = {}
    if crop is not None:
        resolved = FitConfig(**fit).resolved(crop)
        fit["canopies_per_eval"] = resolved.canopies_per_eval
        fit["local_share"] = resolved.local_share
        fit["gp_output"] = resolved.gp_output
        agg_only["combine"] = resolved.combine
        # The paper's optimiser is hashed as it was before these settings existed, so that
        # seeds fitted then are still served; any other optimiser (or default) is a key of
        # its own.
        if resolved.papers_optimiser(crop):
            fit.pop("gp_output")
            fit.pop("local_share")
    # settings only the aggregate stage reads: changing them must not refit the seeds
    seed_fit = {k: v for k, v in fit.items() if k not in AGGREGATE_ONLY}
    if agg_only.get("combine", fit.get("combine")) == "floors":
        # each seed polishes its own point in its mapped task (select.seed_floor), so its
        # record carries the floor and is keyed apart from the other rules' seeds
        seed_fit.update(
            {k: fit[k] for k in ("reevaluate_canopies", "polish_evals")}, combine="floors"
        )
    agg = {**fit, **agg_only}
    observe = dict(cfg["observe"])
    if observe.get("prediction_blur") == 0:  # unblurred predictions keyed as before the setting
        observe.pop("prediction_blur")
    poses = dict(cfg["poses"])
    if poses.get("exif_focal") is True:  # photos without EXIF focal run SfM as before it
        poses.pop("exif_focal")
    if poses.get("gps") is True:  # photos without GPS are levelled as before it
        poses.pop("gps")
    surfaces = dict(cfg["surfaces"])
    if crop is not None and surfaces.get("bbox") == "auto":
        try:
            from cropcraft_core.surfaces import resolve_bbox
        except ImportError:  # a partial checkout: the surfaces stage will say so itself
            pass
        else:
            surfaces["bbox"] = resolve_bbox("auto", crop).tolist()
    return {
        "ingest": dict(cfg["ingest"]),
        "poses": poses,
        "surfaces": surfaces,
        "rowfit": {**cfg["rowfit"], **layout},
        # the row fit's colour rule for the photos' plant (None: the crop's)
        "consistency": {
            "max_views": cfg["consistency"]["max_views"],
            "min_height": cfg["consistency"]["min_height"],
            "plant_a_below": cfg["rowfit"]["preset"].get("plant_a_below"),
            "warn": _net_warn(cfg, crop),
        },
        # pooled over neighbouring rows, the observation needs their spacing; otherwise it is
        # keyed as before the setting existed
        "observe": {
            **observe,
            **(layout if int(cfg["observe"]["preset"].get("views_across", 0)) > 0 else {}),
        },
        # every row is observed alike: the observe stage's settings, and the row spacing
        "observe_rows": {
            **observe,
            "max_side": cfg["rows"]["neighbours"],
            "max_no_surface": cfg["rows"]["max_no_surface"],
            "snap_fraction": cfg["rows"]["snap"],
            **layout,
        },
        "fit_seed": {**seed_fit, **layout},
        "aggregate": {**agg, **layout},
        "rows": {"seed": cfg["generate"]["seed"], "answer": cfg["rows"]["answer"], **layout},
        "generate": {**cfg["generate"], **layout},
        "metrics": dict(cfg["metrics"]),
        "export": dict(cfg["export"]),
        "report": {**cfg["report"], **layout},
    }


# --------------------------------------------------------------------------- the request


@dataclasses.dataclass(frozen=True)
class SceneRequest:
    """A validated scene run: everything the wiring needs, nothing large."""

    scene: SceneKey
    store_root: str
    images: str
    poses: str | None
    config: dict[str, Any]
    inputs: dict[str, dict[str, str]]
    """Fingerprints: ``{"images": {...}, "poses": {...}}`` (poses only when given)."""

    @property
    def stages(self) -> dict[str, dict[str, Any]]:
        return stage_configs(self.config, self.scene.crop)


def default_images_uri(store: SceneStore, scene: SceneKey) -> str:
    """The scene's photo inbox in the store: ``{site}/{crop}/{date}/images/``."""
    return store.url(f"{scene.prefix}/images")


def default_poses_uri(store: SceneStore, scene: SceneKey) -> str | None:
    """``images/transforms.json`` in the scene's inbox, when there is one."""
    key = f"{scene.prefix}/images/transforms.json"
    return store.url(key) if store.isfile(key) else None


#: Field notes beside a date's photos: the model parameters measured in the field that day
#: (e.g. ``{"num_nodes": 9}``, the main-stem trifoliate nodes, one fewer than a V-stage; a value, or
#: ``[low, high]``), the fit's known parameters for that date (``fit.box``). Settings given to
#: the run (``--param``, ``--set fit.box...``) go over them.
KNOWN_FILE = "known.json"

#: Capture facts a :data:`KNOWN_FILE` may hold beside the parameters, each the setting it is
#: (the run's own flag goes over it): a season's one drone date among walks gives its height
#: there, where ``season --camera-height`` would give every date the same.
CAPTURE_NOTES = {"camera_height": "poses.camera_height", "row_spacing": "layout.row_spacing"}


def known_settings(
    known: Mapping[str, Any], overrides: Mapping[str, Any] | None = None
) -> dict[str, Any]:
    """The field notes as config overrides: parameters as ``fit.box.NAME``, capture facts as
    their settings (:data:`CAPTURE_NOTES`). A run given another scale (``overrides``' camera
    distance) leaves the notes' camera height out: the run's scale goes over it."""
    out = {CAPTURE_NOTES.get(k, f"fit.box.{k}"): v for k, v in known.items()}
    if _other_scale(overrides):
        out.pop(CAPTURE_NOTES["camera_height"], None)
    return out


def _other_scale(overrides: Mapping[str, Any] | None) -> str | None:
    """The flag of a scale the run was given other than a camera height, else None."""
    o = overrides or {}
    if o.get("poses.camera_distance") is not None:
        return "--camera-distance"
    if o.get("rowfit.scale") is not None:
        return "--set rowfit.scale"
    return None


def read_known(images_uri: str, crop: str) -> dict[str, Any]:
    """The :data:`KNOWN_FILE` in the photos' folder (local or fsspec URL), checked against
    ``crop``'s parameters; {} when there is none. A file that is not a JSON object of valid
    parameters is an InputError naming it."""
    from fsspec.core import url_to_fs

    from cropcraft_core.config import ParamBox

    uri = str(images_uri).rstrip("/") + "/" + KNOWN_FILE
    try:
        fs, path = url_to_fs(uri)
        if not fs.isfile(path):
            return {}
        raw = fs.cat_file(path)
    except FileNotFoundError:
        return {}
    except Exception as exc:  # s3fs lets botocore's credential and endpoint errors through
        raise InputError(f"cannot read {uri}: {type(exc).__name__}: {exc}") from exc
    try:
        known = json.loads(raw)
    except ValueError as exc:
        raise InputError(f"{uri}: not valid JSON ({exc})") from None
    if not isinstance(known, dict):
        raise InputError(
            f"{uri}: must be a JSON object of {crop} parameters (a value or [low, high] each) "
            f"and capture facts ({', '.join(CAPTURE_NOTES)}), got {type(known).__name__}"
        )
    for name in CAPTURE_NOTES:
        v = known.get(name)
        if name in known and not (
            isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v) and v > 0
        ):
            raise InputError(f"{uri}: {name} must be a positive number of metres, got {v!r}")
    try:
        ParamBox.of(crop, {k: v for k, v in known.items() if k not in CAPTURE_NOTES})
    except ConfigError as exc:
        raise InputError(f"{uri}: {exc}") from None
    return known


def notes_overridden(known: Mapping[str, Any], overrides: Mapping[str, Any] | None) -> list[str]:
    """The field notes (:data:`KNOWN_FILE`) a run's own settings go over, one line each, e.g.
    "--param leaf_length=1 goes over known.json's 0.9": said, not replaced quietly."""
    out = []
    for name, noted in known.items():
        if name in CAPTURE_NOTES:
            setting = CAPTURE_NOTES[name]
            given = (overrides or {}).get(setting)
            other = _other_scale(overrides) if name == "camera_height" else None
            if given is not None and given != noted:
                flag = f"--{name.replace('_', '-')} {float(given):g}"
                out.append(f"{flag} goes over {KNOWN_FILE}'s {json.dumps(noted)}")
            elif given is None and other:
                out.append(f"{other} goes over {KNOWN_FILE}'s {name} {json.dumps(noted)}")
            continue
        given = (overrides or {}).get(f"fit.box.{name}")
        if given is None:
            given = (((overrides or {}).get("fit") or {}).get("box") or {}).get(name)
        if given is not None and given != noted:
            shown = (
                ":".join(f"{float(x):g}" for x in given)
                if isinstance(given, list | tuple)
                else f"{float(given):g}"
            )
            out.append(f"--param {name}={shown} goes over {KNOWN_FILE}'s {json.dumps(noted)}")
    return out


def known_input(known: Mapping[str, Any]) -> dict[str, str]:
    """The field notes (:data:`KNOWN_FILE`) as a request's input fingerprint: the manifest
    keeps it, so that the season sees notes added or changed after a date's run."""
    return {KNOWN_FILE: config_hash(dict(known))}


def note_sources(req: SceneRequest, images: str | None, poses: str | None) -> None:
    """Record where a run answered wholly from the cache read its inputs (the manifest's
    ``sources``), as a flow run does: the season judges a date's inbox by them. Only where
    the manifest holds this request's inputs and settings (then its stage records stand)."""
    st = SceneStore(req.store_root)
    sources = {"images": _located(images), "poses": _located(poses)}
    try:  # checked and set as one change: a run of other settings may start meanwhile
        st.note_sources(
            req.scene,
            sources,
            inputs=manifest_inputs(req.inputs),
            config_hash=config_hash(req.config),
        )
    except InputError:  # a manifest unreadable now: the next run sets it aside
        return


def prepare(
    site: str,
    crop: str,
    date: str,
    images: str | None = None,
    poses: str | None = None,
    overrides: Mapping[str, Any] | None = None,
    store: str | None = None,
    *,
    timeout_s: float = 5.0,
    writing: bool = True,
) -> SceneRequest:
    """Validate a scene run before any work starts.

    Raises ConfigError (bad site/crop/date characters, unknown settings), StoreError (the store
    cannot be reached or written, within ``timeout_s``) or InputError (no photos at ``images``,
    nothing at ``poses``, a bad :data:`KNOWN_FILE`). ``images`` defaults to the scene's inbox
    in the store, ``poses`` to ``images/transforms.json`` there if present; the parameters in
    the photos' :data:`KNOWN_FILE` are the fit's known ones, under ``overrides``.
    ``writing=False``: the request of a reader (``cropcraft status``), whose store is not
    probed by a write (on a full or read-only store its error read as moved photos, and status,
    which writes nothing, wrote a probe each call: session 94's disk audit).
    """
    scene = SceneKey(site, crop, str(date))
    cfg = resolve_config(crop, overrides)
    unopened = SceneStore(store)  # a local root's folders that connecting creates: a refused
    made = unopened._folders_to_make()  # request leaves them as they were (none)
    st = SceneStore.connect(store, timeout_s=timeout_s) if writing else unopened
    try:
        return _checked_request(st, scene, cfg, images, poses, overrides)
    except BaseException:
        for folder in made:  # deepest first; only while empty
            try:
                os.rmdir(folder)
            except OSError:
                break
        raise


def _checked_request(
    st: SceneStore,
    scene: SceneKey,
    cfg: dict[str, Any],
    images: str | None,
    poses: str | None,
    overrides: Mapping[str, Any] | None,
) -> SceneRequest:
    """:func:`prepare`'s checks of the photos, poses and field notes on an open store."""
    uri, poses_uri, inputs, known = scene_inputs(st, scene, images, poses)
    photos = [n for n in inputs["images"] if n.lower().endswith(IMAGE_EXTENSIONS)]
    need = int(cfg["ingest"]["min_images"])
    if len(photos) < need:  # ingest would refuse it, after Prefect and the lease
        from cropcraft_core.sfm.ingest import UNSUPPORTED_EXTENSIONS

        other = sorted(
            {PurePosixPath(n).suffix[1:].upper() for n in inputs["images"]}
            & {e[1:].upper() for e in UNSUPPORTED_EXTENSIONS}
        )
        formats = f" (its {', '.join(other)} files CropCraft does not read: convert them)"
        raise InputError(
            f"{uri} holds {len(photos)} JPEG/PNG photo(s){formats if other else ''}; at least "
            f"{need} are needed"
        )
    cd = cfg["poses"]["camera_distance"]
    if cd is not None:  # the poses stage would refuse them after SfM (matched as it matches)
        from cropcraft_core.sfm.frame import photo_stem

        stems = {photo_stem(n) for n in photos}
        gone = [p for p in cd[:2] if p not in photos and photo_stem(p) not in stems]
        if gone or photo_stem(cd[0]) == photo_stem(cd[1]):
            raise InputError(
                f"poses.camera_distance names {', '.join(map(repr, gone or cd[:1]))}: give two "
                f"different photos of {uri} (e.g. {', '.join(photos[:2])})"
            )
    if known:
        notes = known_settings(known, overrides)
        try:
            cfg = resolve_config(scene.crop, {**notes, **dict(overrides or {})})
        except ConfigError as exc:  # the notes and the run's settings together (all fixed)
            raise ConfigError(
                f"{exc} (with the field notes in {uri.rstrip('/')}/{KNOWN_FILE}: "
                f"{', '.join(f'{k}={json.dumps(v)}' for k, v in known.items())})"
            ) from None
    return SceneRequest(scene, st.root, uri, poses_uri, cfg, inputs)


def scene_inputs(
    st: SceneStore, scene: SceneKey, images: str | None = None, poses: str | None = None
) -> tuple[str, str | None, dict[str, dict[str, str]], dict[str, Any]]:
    """``(photos' URI, poses' URI or None, input fingerprints, field notes)`` of a run over
    ``images`` and ``poses`` (default: the scene's inbox, its ``transforms.json`` where there
    is one): the photos, the poses and the :data:`KNOWN_FILE` notes, as the manifest keeps
    them and the season compares an inbox against them."""
    uri = str(images or default_images_uri(st, scene))
    inputs = {"images": fingerprint(uri, what="images")}
    known = read_known(uri, scene.crop)
    if known:
        inputs["known"] = known_input(known)
    poses_uri = poses if poses is not None else (None if images else default_poses_uri(st, scene))
    if poses_uri:
        inputs["poses"] = fingerprint(str(poses_uri), what="poses")
    return uri, poses_uri and str(poses_uri), inputs, known


def manifest_inputs(inputs: Mapping[str, Mapping[str, str]]) -> dict[str, str]:
    """A request's input fingerprints as the manifest keeps them: ``{"images:IMG_1.jpg":
    identity, "poses:transforms.json": identity, ...}``."""
    return {f"{k}:{n}": v for k, fp in inputs.items() for n, v in fp.items()}


def _located(uri: str | None) -> str | None:
    """A run's ``images`` / ``poses`` argument as the manifest keeps it: a local path made
    absolute (``cropcraft status`` may run from another folder), a URL as given."""
    if uri is None:
        return None
    return str(uri) if "://" in str(uri) else os.path.abspath(str(uri))


def result_storage(store_root: str) -> Any:
    """Prefect result storage at the scene store's root: a ``Path`` for a local store; for
    object storage a ``RemoteFileSystem`` block saved on the Prefect server as
    ``cropcraft-results-<hash of the root>`` (Prefect only accepts saved blocks there). The
    block carries the root and the endpoint only; credentials come from the environment of
    whoever reads or writes."""
    store = SceneStore(store_root)
    if store.protocol == "file":
        return Path(store.fs._strip_protocol(store.root))
    from prefect.filesystems import RemoteFileSystem

    opts = store.describe()["storage_options"]
    settings: dict[str, Any] = {}
    endpoint = opts.get("endpoint_url") or (opts.get("client_kwargs") or {}).get("endpoint_url")
    if endpoint:
        settings["endpoint_url"] = endpoint
    block = RemoteFileSystem(basepath=store.root, settings=settings)
    name = "cropcraft-results-" + config_hash({"root": store.root, **settings})[:16]
    block.save(name, overwrite=True)
    return block


# --------------------------------------------------------------------------- the wiring


class _Miss(Exception):
    """A stage has no cached result (cache walk only)."""


def _frame(poses: Mapping[str, Any]) -> dict[str, str]:
    """The poses' frame as the row fit reads it from their record's summary (``metric``, the
    scale's source, the camera height), as an input of its key: poses.json's bytes do not show
    it (a camera height equal to the prior levels the poses alike, yet makes the scale the
    hint's instead of the rows'), so the row fit of the earlier frame was served."""
    s = poses.get("summary") or {}
    return {"frame": _digest({"metric": s.get("metric"), "frame": s.get("frame")})}


def _digest(record: Any) -> str:
    """sha256 of a stage record's part (a summary may hold NaN, e.g. no up disagreement)."""
    text = json.dumps(record, sort_keys=True, separators=(",", ":"), default=str)
    return sha256_bytes(text.encode())


def _summaries(upstream: Mapping[str, Any]) -> dict[str, str]:
    """The upstream records' summaries, as an input of the report's key: the report prints
    them (registered photos, scale source, the consistency warning), and a summary can change
    while its stage's artefacts keep their bytes (``consistency.warn``: the page kept the old
    warning)."""
    return {
        "summaries": _digest(
            {k: rec.get("summary") for k, rec in upstream.items() if isinstance(rec, Mapping)}
        )
    }


def _flatten(upstream: Mapping[str, Any]) -> dict[str, str]:
    out: dict[str, str] = {}
    for rec in upstream.values():
        if isinstance(rec, Mapping) and "hashes" in rec:
            out.update(rec["hashes"])
    return out


@dataclasses.dataclass(frozen=True)
class _Stored:
    """What the store holds of a scene, to judge cached stage records by: ``written``, the
    manifest's sha256 of the last write at each artefact key ({} when the scene has no manifest
    yet), and ``present``, every key under the scene (None when it could not be listed)."""

    written: Mapping[str, str]
    present: frozenset[str] | None
    writing: tuple[str, ...] = ()
    """Folders of attempts that began and were never recorded (``Manifest.writing``): judged
    only where nothing settles them first (a cache walk; a run settles them at its start)."""
    damaged: Callable[[str, str], bool] | None = None
    """Whether an object no longer holds the bytes of the sha256 its stage recorded (cut
    short, edited by hand): such a record is recomputed, not served. On a local store every
    artefact is hashed; on object storage, whose writes land whole, only the small text ones
    a person or the season reads (metrics.json, fit.json, the report: a metrics.json edited
    on the bucket was published), as hashing the rest would fetch every artefact of every
    cached stage each night."""
    local: bool = True
    """Whether :attr:`damaged` sees every artefact (a local store): an unrecorded attempt's
    folder is then judged by its files' bytes, not voided whole."""


#: The artefacts object storage has re-hashed before a cached record is served.
CHECKED_ON_OBJECT_STORAGE = (".json", ".html", ".csv", ".xml", ".txt")


def _damage_check(store: SceneStore) -> Callable[[str, str], bool]:
    """:attr:`_Stored.damaged` for ``store``: each key hashed once."""
    seen: dict[str, str | None] = {}

    def damaged(key: str, recorded: str) -> bool:
        if not store._local and not key.endswith(CHECKED_ON_OBJECT_STORAGE):
            return False
        if key not in seen:
            try:
                seen[key] = store.sha256(key)
            except Exception:  # gone or unreadable: the listing's check, or the stage, says
                seen[key] = None
        return seen[key] != recorded

    return damaged


def _stored(store: SceneStore, scene: SceneKey, *, pending: bool = False) -> _Stored:
    """The store's :class:`_Stored` of ``scene`` now (one manifest read, one listing);
    ``pending``: with the folders of unrecorded attempts (a cache walk's: a run settles them
    before it judges any record, and then lists only its own)."""
    try:
        manifest = store.load_manifest(scene)
        written = manifest.written
        writing = tuple(sorted(set(manifest.writing.values()))) if pending else ()
    except InputError:
        written, writing = {}, ()
    try:
        present: frozenset[str] | None = frozenset(store.list(scene.prefix))
    except Exception:  # judged on ``written`` alone; the stage's own reads will say why
        present = None
    return _Stored(written, present, writing, _damage_check(store), store._local)


def _overwritten(stored: _Stored, rec: dict, scene: SceneKey) -> bool:
    """Whether a cached stage record's artefacts are no longer what the store holds: artefacts
    live at one key per scene and stage, so a run with other settings since wrote over them, or
    someone deleted them. ``stored.written`` has the hash of the last write at each key; a key
    it does not know (a manifest lost, or from before it kept them) counts as unchanged if it
    is there. Such a record is recomputed, not served: the store must hold what a run
    reports."""
    hashes = rec["hashes"]
    # an unrecorded attempt's folder: on object storage its records are not trusted; a local
    # store's files are hashed below instead (the seeds beside a killed aggregate's fit.json
    # stay served: their bytes say so)
    if not stored.local and any(
        k.startswith(f"{folder}/") for k in hashes for folder in stored.writing
    ):
        return True
    inside = f"{scene.prefix}/"
    if stored.present is not None:
        if any(k.startswith(inside) and k not in stored.present for k in hashes):
            return True
    if any(stored.written.get(k, h) != h for k, h in hashes.items()):
        return True
    if stored.damaged is not None:  # damaged in place (cut short, edited): recomputed
        damaged = [k for k, h in hashes.items() if k.startswith(inside) and stored.damaged(k, h)]
        if damaged:
            _log_damaged(damaged)
            return True
    return False


def _log_damaged(keys: list[str]) -> None:
    """Say which stored artefacts no longer hold what their stage wrote (the run's log, or the
    ``cropcraft`` logger outside one)."""
    from tasks.common import stage_log

    with contextlib.suppress(Exception):
        stage_log().warning(
            "%d stored file(s) no longer hold what their stage wrote (cut short or edited?), "
            "so the stage is run again: %s",
            len(keys), ", ".join(keys[:5]) + (", ..." if len(keys) > 5 else ""),
        )  # fmt: skip


def _forget_failure(store: SceneStore, state: Any) -> None:
    """Remove what Prefect persisted of a failed stage: its exception, under a random key at
    the result storage's root, which is the store's root, outside every scene (nothing swept
    it, so each failure of a season's nights left an object at the bucket's root). The run
    reports the error and the manifest keeps it. Only an object of that form, directly at the
    root, is removed; best effort."""
    import re

    key = getattr(getattr(getattr(state, "data", None), "metadata", None), "storage_key", None)
    if not key:
        return
    key = str(key).replace("\\", "/")
    parent, _, name = key.rpartition("/")
    root = store.fs._strip_protocol(store.root).rstrip("/")
    if not re.fullmatch(r"[0-9a-f]{32}", name) or (parent and parent.rstrip("/") != root):
        return
    with contextlib.suppress(Exception):
        store.fs.rm_file(f"{root}/{name}")


def _left_behind(store: SceneStore, scene: SceneKey, stage: str) -> dict[str, str]:
    """{key: sha256} of every object in ``stage``'s store folder that differs from what the
    manifest's ``written`` says was last written there: what a failed attempt of the stage
    replaced before it failed. Recorded, they stop a cached record of other settings that names
    those keys from being served. Reads the folder once, only after a failure; {} when the
    store cannot be read (then the attempt most likely wrote nothing either)."""
    from tasks.common import STAGE_FOLDERS

    try:
        written = _stored(store, scene).written
        current = store.hashes(f"{scene.prefix}/{STAGE_FOLDERS[stage]}")
    except Exception:  # the failure's own cause (e.g. the store) is what gets reported
        get_run_logger().warning("could not check what the failed %s left in the store", stage)
        return {}
    return {k: h for k, h in current.items() if written.get(k) != h}


class _CacheWalk:
    """Executes the wiring by reading persisted stage records only (no Prefect run)."""

    def __init__(self, req: SceneRequest) -> None:
        self.req = req
        self.store = SceneStore(req.store_root)
        self.base = self.store.fs._strip_protocol(self.store.root).rstrip("/")
        self.states: dict[str, str] = {}
        # a walk writes nothing: read it once
        self.stored = _stored(self.store, req.scene, pending=True)

    def _read(self, key: str) -> dict:
        from prefect._internal.result_records import ResultRecord

        path = f"{self.base}/{key}"
        try:
            data = self.store.fs.cat_file(path)
        except (FileNotFoundError, OSError):
            raise _Miss(key) from None
        try:
            return ResultRecord.deserialize(data).result
        except Exception:  # unreadable record: treat as a miss, the flow recomputes
            raise _Miss(key) from None

    def run(self, stage: str, upstream: dict, row: int | None = None, **_: Any) -> dict:
        cfg = self.req.stages[stage]
        key = stage_key(stage, self.req.scene.prefix, cfg, upstream, {"row": row})
        rec = self._read(key)
        if _overwritten(self.stored, rec, self.req.scene):
            raise _Miss(key)
        self.states[_state_name(stage, row)] = "Cached"
        return rec

    def run_rows(self, stage: str, jobs: Mapping[int | None, dict]) -> dict[int | None, dict]:
        return {row: self.run(stage, up, row=row) for row, up in jobs.items()}

    def map_seeds(
        self, jobs: Mapping[int | None, dict], seeds: list[int]
    ) -> dict[int | None, dict[str, dict]]:
        out: dict[int | None, dict[str, dict]] = {}
        cfg = self.req.stages["fit_seed"]
        for row, upstream in jobs.items():
            out[row] = {}
            for s in seeds:
                extra = {"seed": s, "row": row}
                key = stage_key("fit_seed", self.req.scene.prefix, cfg, upstream, extra)
                rec = out[row][f"seed-{s}"] = self._read(key)
                if _overwritten(self.stored, rec, self.req.scene):
                    raise _Miss(key)
                self.states[_state_name(f"fit_seed-{s}", row)] = "Cached"
        return out


def _state_name(stage: str, row: int | None) -> str:
    """A run's name in ``states``: the stage, or ``stage@row_p1`` for a neighbour row's."""
    if row is None:
        return stage
    from cropcraft_core.rowfit import row_label

    return f"{stage}@{row_label(row)}"


def _merged_environment(records: Iterable[Mapping[str, Any]]) -> dict[str, str]:
    """One environment for the seeds of one fit: each library's version, or its versions
    joined by " | " where workers differed (which is worth seeing in a manifest)."""
    versions: dict[str, list[str]] = {}
    for rec in records:
        for name, version in (rec.get("environment") or {}).items():
            seen = versions.setdefault(name, [])
            if version not in seen:
                seen.append(version)
    return {name: " | ".join(v) for name, v in versions.items()}


def _manifest_stage(stage: str, row: int | None) -> str:
    """The manifest record a run reports to: its stage's, or ``rows`` for a neighbour row's
    seeds and answer (the best row's records stay those of the scene's answer)."""
    return stage if row is None else "rows"


class _PrefectRun:
    """Executes the wiring with Prefect tasks, recording each stage in the manifest."""

    def __init__(
        self,
        req: SceneRequest,
        storage: Any,
        refresh: bool = False,
        lease: SceneLease | None = None,
    ) -> None:
        self.req = req
        self.storage = storage
        self.refresh = refresh  # recompute every stage, replacing its cached result
        self.store = SceneStore(req.store_root)
        self.lease = lease  # checked before every stage and record: no writes after a takeover
        self.states: dict[str, str] = {}
        self.log = get_run_logger()

    def _check_lease(self) -> None:
        if self.lease is not None:
            self.lease.check()

    def _task(self, stage: str, refresh: bool = False):
        """The stage's task on the scene's result storage; ``refresh``: recompute and replace
        its cached result (otherwise Prefect's own setting applies)."""
        task = get_task(stage).with_options(result_storage=self.storage)
        return task.with_options(refresh_cache=True) if refresh or self.refresh else task

    def _record(
        self,
        stage: str,
        upstream: dict,
        rec: dict | None,
        error: Any = None,
        row: int | None = None,
    ) -> None:
        self._check_lease()
        scene = self.req.scene
        chash = config_hash(self.req.stages[stage])
        name = _manifest_stage(stage, row)
        recorded = {_state_name(stage, row): None}  # the attempt is accounted for
        if error is not None:  # rec: what the failed attempt left written (see _left_behind)
            self.store.update_stage(
                scene,
                name,
                status="failed",
                config_hash=chash,
                error=error,
                artefacts=(rec or {}).get("hashes"),
                writing=recorded,
            )
            return
        assert rec is not None
        self.store.update_stage(
            scene,
            name,
            status="done",
            config_hash=chash,
            inputs=_flatten(upstream),
            artefacts=rec["hashes"],
            seconds=rec["seconds"],
            environment=rec.get("environment"),
            writing=recorded,
        )

    def _begin(self, stage: str, row: int | None) -> None:
        """Note in the manifest that ``stage`` (of ``row``) may write from now until it is
        recorded (``Manifest.writing``): should this run die in between, the next one hashes
        that folder before it trusts a cached record. The scene's own stages start a new
        attempt of their record (``running``: an earlier attempt's error and seconds go); a
        neighbour row's stages share the ``rows`` record, which they only add to."""
        from tasks.common import stage_folder

        self._check_lease()
        self.store.update_stage(
            self.req.scene,
            _manifest_stage(stage, row),
            status="running" if row is None else None,
            config_hash=config_hash(self.req.stages[stage]),
            writing={_state_name(stage, row): stage_folder(self.req.scene.prefix, stage, row)},
        )

    def _submit(self, stage: str, upstream: dict, refresh: bool = False, **kwargs: Any) -> Any:
        """The stage's task submitted (not waited for)."""
        self._begin(stage, kwargs.get("row"))
        return self._task(stage, refresh).submit(
            store_root=self.req.store_root,
            scene=self.req.scene.prefix,
            config=self.req.stages[stage],
            upstream=upstream,
            lease=None if self.lease is None else self.lease.token,
            **kwargs,
        )

    def run(self, stage: str, upstream: dict, row: int | None = None, **kwargs: Any) -> dict:
        if row is not None:
            kwargs["row"] = row
        return self._finish(stage, upstream, row, self._submit(stage, upstream, **kwargs), kwargs)

    def run_rows(self, stage: str, jobs: Mapping[int | None, dict]) -> dict[int | None, dict]:
        """``stage`` for every row (``jobs``: row → its upstream, None the best row), all
        submitted before any is waited for, so that a Dask cluster runs them side by side
        (the rows' re-scoring takes minutes each); each recorded as :meth:`run` records it,
        and the first failure in row order raised once every row has finished."""
        kwargs = {row: {} if row is None else {"row": row} for row in jobs}
        futures = {row: self._submit(stage, up, **kwargs[row]) for row, up in jobs.items()}
        out: dict[int | None, dict] = {}
        failed: Exception | None = None
        for row, fut in futures.items():
            try:
                out[row] = self._finish(stage, jobs[row], row, fut, kwargs[row])
            except Exception as exc:  # the other rows still finish and are recorded
                failed = failed or exc
        if failed is not None:
            raise failed
        return out

    def _finish(self, stage: str, upstream: dict, row: int | None, fut: Any, kwargs: dict) -> dict:
        """A submitted stage's record, once it has finished: recomputed where its cached
        artefacts were since overwritten; recorded in the manifest either way."""
        name = _state_name(stage, row)
        fut.wait()
        try:
            rec = fut.result()
            cached = fut.state.name == "Cached"
            if cached and _overwritten(_stored(self.store, self.req.scene), rec, self.req.scene):
                self.log.info("%s: cached, but its artefacts were since overwritten", name)
                fut = self._submit(stage, upstream, refresh=True, **kwargs)
                fut.wait()
                rec = fut.result()
        except Exception as exc:
            self.states[name] = fut.state.name
            _forget_failure(self.store, fut.state)
            left = _left_behind(self.store, self.req.scene, stage)
            self._record(stage, upstream, {"hashes": left}, exc, row)
            raise
        self.states[name] = fut.state.name
        self._record(stage, upstream, rec, row=row)
        self.log.info("%s: %s (%.1f s)", name, fut.state.name, rec["seconds"])
        return rec

    def _map_seeds(
        self, upstream: dict, seeds: list[int], row: int | None, refresh: bool = False
    ) -> dict[int, Any]:
        """Submit ``seeds`` of one row's fit (not waited for)."""
        self._begin("fit_seed", row)
        futures = self._task("fit_seed", refresh).map(
            store_root=unmapped(self.req.store_root),
            scene=unmapped(self.req.scene.prefix),
            config=unmapped(self.req.stages["fit_seed"]),
            upstream=unmapped(upstream),
            seed=seeds,
            row=unmapped(row),
            lease=unmapped(None if self.lease is None else self.lease.token),
        )
        return dict(zip(seeds, futures, strict=True))

    def map_seeds(
        self, jobs: Mapping[int | None, dict], seeds: list[int]
    ) -> dict[int | None, dict[str, dict]]:
        """Every row's seeds (``jobs``: row → its fit's upstream, None the best row), all
        submitted before any is waited for, so that a Dask cluster runs them side by side."""
        futures = {row: self._map_seeds(up, seeds, row) for row, up in jobs.items()}
        for futs in futures.values():
            for fut in futs.values():
                fut.wait()
        stored = _stored(self.store, self.req.scene)
        for row, futs in futures.items():
            stale = [
                s
                for s, fut in futs.items()
                if fut.state.name == "Cached" and _overwritten(stored, fut.result(), self.req.scene)
            ]
            if stale:
                self.log.info(
                    "fit seeds %s of %s: cached, but their artefacts were since overwritten",
                    stale,
                    "the best row" if row is None else _state_name("row", row),
                )
                again = self._map_seeds(jobs[row], stale, row, refresh=True)
                for fut in again.values():
                    fut.wait()
                futs.update(again)
        out: dict[int | None, dict[str, dict]] = {}
        errors = []
        for row, futs in futures.items():
            out[row], failed = {}, []
            for s, fut in futs.items():
                self.states[_state_name(f"fit_seed-{s}", row)] = fut.state.name
                try:
                    out[row][f"seed-{s}"] = fut.result()
                except Exception as exc:
                    failed.append((s, exc))
                    _forget_failure(self.store, fut.state)
            done = {
                "hashes": _flatten(out[row]),
                "environment": _merged_environment(out[row].values()),
            }
            if failed:
                where = "" if row is None else f" of {_state_name('row', row)}"
                msg = "; ".join(f"seed {s}{where}: {type(e).__name__}: {e}" for s, e in failed)
                self._record("fit_seed", jobs[row], done, msg, row)
                errors.append((len(failed), msg))
            else:
                seconds = sum(r["seconds"] for r in out[row].values())
                self._record("fit_seed", jobs[row], {**done, "seconds": seconds}, row=row)
        if errors:
            n = sum(k for k, _ in errors)
            msg = "; ".join(m for _, m in errors)
            raise CropCraftError(
                f"{n} of {len(seeds) * len(jobs)} fit seeds failed for {self.req.scene} ({msg}); "
                "the other seeds are saved: rerun the same command to compute only what is "
                "missing"
            )
        return out


#: The rule by which ``poses.imported_metric="auto"`` reads imported poses, keyed with them so
#: that a scene whose poses were read by an earlier rule is read again (SfM scenes and poses
#: read by an explicit true/false keep their keys). 2: a ``transforms.json`` that
#: ns-process-data made from an SfM project (``applied_transform``) is not metric. 3: nor is
#: one from instant-ngp's ``colmap2nerf.py`` (a ``sharpness`` on its frames).
AUTO_METRIC_RULE = {"auto_metric_rule": "3"}

#: Likewise for imported poses read as metric by ``poses.imported_metric=true``: 2, a walk along
#: one side of the plot is levelled on the axis its photos' rows are level with (the cameras'
#: mean optical axis tilted such a frame ~41°). SfM scenes and other imports keep their keys.
METRIC_LEVELLING_RULE = {"metric_levelling_rule": "2"}

#: The stereo sweep's rule where a scene sets ``surfaces.depth_range`` (2: it bounds the
#: horizontal planes' depths too) or ``surfaces.min_ncc`` at its least, -1 (2: unmatched
#: depths are dropped): keyed with the surfaces of such scenes only, whose stored surfaces an
#: earlier rule made. Every other scene keeps its key.
SWEEP_RULE = {"sweep_rule": "2"}


def _wire(ex: Any, req: SceneRequest) -> dict[str, Any]:
    """The scene graph; ``ex`` is :class:`_PrefectRun` or :class:`_CacheWalk`."""
    r: dict[str, Any] = {}
    r["ingest"] = ex.run("ingest", {"inputs": req.inputs["images"]}, images=req.images)
    up = {"ingest": r["ingest"]}
    if req.poses:
        up["inputs"] = req.inputs["poses"]
        if req.config["poses"]["imported_metric"] == "auto":
            up["rule"] = AUTO_METRIC_RULE
        elif req.config["poses"]["imported_metric"] is True:
            up["rule"] = METRIC_LEVELLING_RULE
    r["poses"] = ex.run("poses", up, poses_uri=req.poses)
    up = {"ingest": r["ingest"], "poses": r["poses"]}
    sweep = req.config["surfaces"]
    if sweep.get("depth_range") is not None or sweep.get("min_ncc") == -1:
        up["rule"] = SWEEP_RULE
    r["surfaces"] = ex.run("surfaces", up)
    r["rowfit"] = ex.run(
        "rowfit", {"surfaces": r["surfaces"], "poses": r["poses"], "frame": _frame(r["poses"])}
    )
    r["consistency"] = ex.run(
        "consistency",
        {k: r[k] for k in ("ingest", "poses", "surfaces", "rowfit")},
    )
    r["observe"] = ex.run("observe", {"surfaces": r["surfaces"], "rowfit": r["rowfit"]})
    jobs: dict[int | None, dict] = {None: {"observe": r["observe"]}}
    if req.config["rows"]["neighbours"]:
        from tasks.observe import row_observation_record

        up = {"surfaces": r["surfaces"], "rowfit": r["rowfit"], "observe": r["observe"]}
        r["observe_rows"] = ex.run("observe_rows", up)
        for k in r["observe_rows"]["summary"]["kept"]:
            jobs[int(k)] = {"observe": row_observation_record(r["observe_rows"], k)}
    seeds = list(range(int(req.config["fit"]["n_seeds"])))
    row_seeds = ex.map_seeds(jobs, seeds)
    seed_recs = row_seeds[None]
    # every row's seeds combined (re-scoring, guard) side by side
    aggregates = ex.run_rows("aggregate", {k: {**jobs[k], **row_seeds[k]} for k in jobs})
    r["aggregate"] = aggregates[None]
    if "observe_rows" in r:
        answers = {"aggregate": r["aggregate"]}
        answers.update({f"aggregate@{k}": a for k, a in aggregates.items() if k is not None})
        r["rows"] = ex.run("rows", {"observe_rows": r["observe_rows"], **answers})
    # the scene's answer: the best row's, or the rows' combined (rows.answer)
    answer = r["rows"] if "fit" in r.get("rows", {}).get("artefacts", {}) else r["aggregate"]
    r["generate"] = ex.run("generate", {"aggregate": answer})
    # the seeds' traits beside the answer's (metrics.seeds) where the answer is one fit's
    up = {"generate": r["generate"]} | ({"aggregate": answer} if answer is r["aggregate"] else {})
    r["metrics"] = ex.run("metrics", up)
    r["export"] = ex.run(
        "export", {"generate": r["generate"], "metrics": r["metrics"], "aggregate": answer}
    )
    up = {k: r[k] for k in r if k != "fit_seed"} | dict(seed_recs)
    if answer is not r["aggregate"]:  # the rows' mean (the best row's own fit stays aggregate)
        up["answer"] = answer
    if "observe_rows" in r:  # the neighbour rows' seeds and answers: the page times them too
        from cropcraft_core.rowfit import row_label

        for k in (k for k in jobs if k is not None):
            up.update({f"{n}@{row_label(k)}": rec for n, rec in row_seeds[k].items()})
            up[f"aggregate@{row_label(k)}"] = aggregates[k]
    r["report"] = ex.run("report", up | {"summaries": _summaries(up)})
    r["fit_seeds"] = seed_recs
    return r


def _net_warn(cfg: Mapping[str, Any], crop: str | None) -> float | None:
    """``consistency.warn``, or the crop's (``NET_WARN``) where it is None."""
    warn = cfg["consistency"]["warn"]
    if warn is None and crop is not None:
        from cropcraft_core.surfaces.consistency import NET_WARN

        warn = NET_WARN.get(crop)
    return warn


def _consistency(record: dict | None) -> dict | None:
    """The consistency stage's shares and warning (None without the record)."""
    if record is None:
        return None
    keys = ("views", "photo_plant", "unreconstructed", "extra", "net", "warning")
    return {k: record["summary"].get(k) for k in keys}


def summarize(req: SceneRequest, records: dict[str, Any], states: dict[str, str]) -> dict:
    """The small result of a scene run: where everything is, the key numbers, stage states."""
    store = SceneStore(req.store_root)
    from cropcraft_core.fit.fitting import edge_warning
    from cropcraft_core.observe import coverage_warning
    from cropcraft_core.report import few_photos_warning

    seen = records["observe"]["summary"].get("no_surface_fraction")  # older records: None
    rows = records.get("rows")
    answer = rows if rows is not None and "params" in rows["summary"] else records["aggregate"]
    return {
        "scene": req.scene.prefix,
        "store": req.store_root,
        "config_hash": config_hash(req.config),
        "states": dict(states),
        "observation": {
            "no_surface_fraction": seen,
            "warning": None if seen is None else coverage_warning(seen, req.scene.crop),
            # pooled row cameras (observe.preset.views_*): how many, and those left out
            **{
                k: records["observe"]["summary"][k]
                for k in ("views_pooled", "views_left_out")
                if k in records["observe"]["summary"]
            },
        },
        # the rows against a camera-height hint far from the crop's usual (None: agree, or
        # not asked)
        "scale_warning": records["rowfit"]["summary"].get("scale_warning"),
        # the planting row spacing the rows and the fitted canopy used, and whether the config
        # gave it: a crop's default taken for 0.38 m rows put a metric walk's row camera 63°
        # across them, silently (session 96's field audit)
        "row_spacing": row_spacing_used(req.scene.crop, req.config),
        # where the metric scale came from (the row fit's; assumed_metric: measured by nothing)
        "scale_source": records["rowfit"]["summary"].get("scale_source"),
        # fewer photos than a plot's reconstruction can rest on (None: enough)
        "photos_warning": few_photos_warning(records["ingest"]["summary"].get("n_images")),
        # the surfaces against the photos at the photos' cameras (older stores: None)
        "consistency": _consistency(records.get("consistency")),
        # photos the run left out: without a pose in the imported poses, or not seeing the box
        "photos_left_out": photos_left_out(records),
        "metrics": records["metrics"]["summary"],
        # the neighbour rows' answers beside the best row's (rows.neighbours > 0), else None
        "rows": records["rows"]["summary"] if "rows" in records else None,
        "params": answer["summary"]["params"],
        "params_std": answer["summary"]["params_std"],
        # the answer pressing the search box on several parameters (None: it does not)
        "edge_warning": edge_warning(
            req.scene.crop, answer["summary"]["params"], req.config["fit"].get("box")
        ),
        "report": store.url(records["report"]["artefacts"]["report"]),
        "bundle": store.url(records["export"]["artefacts"]["bundle"]),
        "seconds": {k: v["seconds"] for k, v in records.items() if k != "fit_seeds"},
    }


def cached_result(req: SceneRequest) -> dict | None:
    """The scene's summary if every stage is already cached for this request, and the scene's
    manifest records this request's run, else None (then the flow runs, serving the cached
    stages and recording them: answered here after a failed run of other settings, the
    manifest kept that failure, and status and the season said "failed").

    Reads the persisted stage records along the same keys the flow would compute, without
    starting Prefect.
    """
    st = SceneStore(req.store_root)
    try:
        manifest = st.load_manifest(req.scene)
    except InputError:
        return None
    if (
        manifest.inputs != manifest_inputs(req.inputs)
        or manifest.config_hash != config_hash(req.config)
        or any(rec.status != "done" for rec in manifest.stages.values() if rec.status != "pending")
    ):
        return None
    walk = _CacheWalk(req)
    try:
        records = _wire(walk, req)
    except _Miss:
        return None
    return summarize(req, records, walk.states)


def cache_walk(req: SceneRequest) -> tuple[dict[str, str], str | None]:
    """``(states, first_missing_key)``: how far the cache reaches for this request."""
    walk = _CacheWalk(req)
    try:
        _wire(walk, req)
    except _Miss as miss:
        return walk.states, str(miss)
    return walk.states, None


# --------------------------------------------------------------------------- the flow


def _run_owner() -> str:
    """Who holds a scene's lease, for another run's refusal: this flow run, by name and id."""
    try:
        from prefect.runtime import flow_run

        if flow_run.id:
            return f"flow run {flow_run.name} ({flow_run.id})"
    except Exception:  # pragma: no cover - outside a run
        pass
    return f"process {os.getpid()}"


#: A scene's flow runs are named by the scene, not Prefect's random words: the UI's run list,
#: a season's subflows and the console then say which date each is (session 92's deployment
#: audit: "weightless-hare").
SCENE_RUN_NAME = "{site}/{crop}/{date}"


@flow(
    name="reconstruct-scene",
    flow_run_name=SCENE_RUN_NAME,
    persist_result=False,
    validate_parameters=True,
    task_runner=make_task_runner(),  # a deployment's run; run_scene names its own
)
def reconstruct_scene(
    site: str,
    crop: str,
    date: str,
    images: str | None = None,
    poses: str | None = None,
    overrides: dict[str, Any] | None = None,
    store: str | None = None,
    refresh: bool = False,
    surfaces_backend: SurfacesBackend | None = None,
) -> dict[str, Any]:
    """Reconstruct one scene (``site``/``crop``/``date``) from its photos.

    images: folder or fsspec URL of the photos (default: the scene's inbox in the store,
    ``{site}/{crop}/{date}/images/``). poses: nerfstudio ``transforms.json`` or a COLMAP model
    folder to import instead of running SfM (default: ``images/transforms.json`` in the inbox
    if present); a ``known.json`` beside the photos holds parameters measured in the field
    (:data:`KNOWN_FILE`). overrides: config overrides (see :func:`resolve_config`). store:
    scene store root (default ``$CROPCRAFT_STORE`` or ``./cropcraft-data``). refresh: compute
    every stage anew and replace its cached result (``cropcraft run --force``).
    surfaces_backend: tsdf, points or nerfacto (default: the crop's; an ``overrides``
    ``surfaces.backend`` wins; see :func:`with_backend`).

    Returns :func:`summarize`'s record, with ``states`` telling which stages ran and which
    were ``Cached``.
    """
    t0 = time.perf_counter()
    overrides = with_backend(overrides, surfaces_backend)
    req = prepare(site, crop, date, images, poses, overrides, store)
    st = SceneStore(req.store_root)
    # one run of a scene at a time, from its first write to its last (cropcraft_core/lease.py)
    with hold_scene(st, req.scene, owner=_run_owner()) as lease:
        st.init_manifest(
            req.scene,
            manifest_inputs(req.inputs),
            req.config,
            sources={"images": _located(images), "poses": _located(poses)},
        )
        ex = _PrefectRun(req, result_storage(req.store_root), refresh=refresh, lease=lease)
        # what a run that died between its writes and its records left: before any cached
        # record is judged against ``written``
        settled = st.settle_writing(req.scene)
        if settled:
            ex.log.info(
                "%s: %d objects written by a run that ended before recording them",
                req.scene.prefix,
                len(settled),
            )
        try:  # temporaries of writers killed mid-write: all of them, this run holding the
            # scene before its own first write (one kept under an hour old stayed for good
            # once a rerun finished the scene: session 94's store audit)
            swept = st.sweep_tmp(req.scene.prefix, older_than_s=None)
            if swept:
                ex.log.info("%s: removed %d stale temporary objects", req.scene.prefix, len(swept))
        except Exception as exc:  # housekeeping must not fail the run
            ex.log.warning("%s: could not sweep temporary objects: %s", req.scene.prefix, exc)
        # a cancel asked of Prefect, or its API gone, ends the run (flows/watch.py)
        with watch_this_run(ex.log) or contextlib.nullcontext():
            records = _wire(ex, req)
        lease.check()
    out = summarize(req, records, ex.states)
    for warning in (
        out["photos_warning"],
        out["scale_warning"],
        out["edge_warning"],
        out["observation"]["warning"],
        (out["consistency"] or {}).get("warning"),
    ):
        if warning:
            ex.log.warning("%s: %s", req.scene.prefix, warning)
    out["flow_seconds"] = time.perf_counter() - t0
    try:
        from prefect.runtime import flow_run

        out["flow_run_id"] = str(flow_run.id)
    except Exception:  # pragma: no cover - outside a run
        pass
    # what the UI shows of the run beside its logs: its traits, warnings, stages and files
    from flows.artifacts import publish_scene
    from flows.season import date_warnings

    publish_scene(out, site, crop, date_warnings(st, req.scene), ex.log)
    return out


def run_scene(
    site: str,
    crop: str,
    date: str,
    images: str | None = None,
    poses: str | None = None,
    overrides: Mapping[str, Any] | None = None,
    store: str | None = None,
    runner: str = DEFAULT_RUNNER,
    refresh: bool = False,
    surfaces_backend: SurfacesBackend | None = None,
) -> dict[str, Any]:
    """Validate, then run :func:`reconstruct_scene` on ``runner`` (see ``flows.runners``);
    ``refresh`` recomputes every stage.

    Validation happens here first, so bad input, and a scene another run holds now, fail
    before Prefect starts.
    """
    req = prepare(site, crop, date, images, poses, with_backend(overrides, surfaces_backend), store)
    refuse_if_busy(SceneStore(req.store_root), req.scene)
    warn_local_paths_on_a_remote_cluster(runner, req)
    return reconstruct_scene.with_options(task_runner=make_task_runner(runner))(
        site=site,
        crop=crop,
        date=str(date),
        images=images,
        poses=poses,
        overrides=dict(overrides or {}),
        store=store,
        refresh=refresh,
        surfaces_backend=surfaces_backend,
    )


def warn_local_paths_on_a_remote_cluster(runner: str | None, req: SceneRequest) -> None:
    """A ``dask://HOST:PORT`` runner on another machine runs every stage on that cluster's
    workers, which read and write their own disks: a local store or local photos there are
    other folders (or none), unless they are a mount every worker shares. Warned of, not
    refused, for that reason."""
    import socket
    import warnings

    from flows.runners import parse_runner

    kind, address = parse_runner(runner)
    if kind != "dask" or address is None:
        return
    host = address.removeprefix("tcp://").rpartition(":")[0].strip("[]")
    if host in ("localhost", "127.0.0.1", "::1", socket.gethostname(), socket.getfqdn()):
        return
    local = [
        what
        for what, uri in (("store", req.store_root), ("photos", req.images), ("poses", req.poses))
        if uri and ("://" not in str(uri) or str(uri).startswith("file://"))
    ]
    if local:
        warnings.warn(
            f"the Dask cluster at {host} runs the stages on its own workers, but the "
            f"{' and '.join(local)} are local paths here: unless every worker mounts them at "
            "the same path, give them as URLs the workers reach (s3://...)",
            UserWarning,
            stacklevel=2,
        )


@flow(
    name="process-scene",
    flow_run_name=SCENE_RUN_NAME,
    persist_result=False,
    validate_parameters=True,
)
def process_scene(
    site: str,
    crop: str,
    date: str,
    images: str | None = None,
    poses: str | None = None,
    overrides: dict[str, Any] | None = None,
    store: str | None = None,
    refresh: bool = False,
    surfaces_backend: SurfacesBackend | None = None,
    runner: str = DEFAULT_RUNNER,
) -> dict[str, Any]:
    """One scene with its stages on ``runner`` (``processes``, ``threads``, ``dask`` or
    ``dask://HOST:PORT``): :func:`reconstruct_scene` as a subflow on that task runner, after
    :func:`run_scene`'s validation. The deployment an ad hoc run from the UI takes to a Dask
    cluster (``reconstruct_scene``'s own run on the worker's process pool: its task runner is
    fixed when its file loads). Returns :func:`reconstruct_scene`'s record."""
    return run_scene(
        site, crop, date, images, poses, overrides, store, runner, refresh, surfaces_backend
    )


__all__ = [
    "DEFAULTS",
    "SceneRequest",
    "cache_walk",
    "cached_result",
    "prepare",
    "process_scene",
    "reconstruct_scene",
    "resolve_config",
    "result_storage",
    "run_scene",
    "with_backend",
    "InputError",
]
