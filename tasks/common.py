"""Plumbing shared by every stage task: the cache key, the stage-task decorator, store access,
stage records, input fingerprints and the progress hook.

A stage task is one arrow of the scene graph (``shared/DESIGN.md``): it reads its inputs from the
scene store by key, calls one ``cropcraft_core`` function, writes its outputs to the store and
returns a small **stage record** (a JSON-able dict, never an array)::

    {"stage": "observe", "scene": "plotA/soybean/2024-07-01",
     "artefacts": {"observation": "plotA/soybean/2024-07-01/observe/observation.npz", ...},
     "hashes": {"plotA/.../observation.npz": "<sha256>", ...},
     "summary": {...a few numbers...}, "seconds": 1.23}

Cache key (see :func:`stage_key`)::

    {scene}/.prefect/{stage}/{sha256(canonical JSON of {stage, scene, stage version,
                                                         config hash, upstream artefact hashes,
                                                         extra (e.g. the seed)})}

The upstream hashes are a record's ``identity`` where it has one (the ingest's: its images
and its manifest's content, not the folder the photos were read from), so the same photos read
again from a copy or with new modification times leave every later stage cached.

The key is also the path of Prefect's persisted result under the result storage, which is the
scene store's root (a local ``Path`` or an fsspec ``RemoteFileSystem`` block for ``s3://``), so
cached results live in the same store as the artefacts, beside the scene they belong to, hidden
from ``SceneStore.list`` by the leading dot. Two runs with the same scene, stage config and
upstream artefact bytes share a key, whatever flow run, machine or worker computes them.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import Any, NamedTuple

from prefect import task

from cropcraft_core.errors import ConfigError, InputError
from cropcraft_core.store import (
    SceneKey,
    SceneStore,
    canonical_json,
    config_hash,
    environment_versions,
    sha256_bytes,
)

#: Pipeline stages in order (``fit_seed`` is mapped over optimiser seeds; ``observe_rows`` and
#: ``rows`` run only when the scene is also fitted over the best row's neighbours, and then
#: ``fit_seed`` and ``aggregate`` run once per neighbour too).
STAGES = (
    "ingest",
    "poses",
    "surfaces",
    "rowfit",
    "consistency",
    "observe",
    "observe_rows",
    "fit_seed",
    "aggregate",
    "rows",
    "generate",
    "metrics",
    "export",
    "report",
)

#: Folder (per scene) holding Prefect's persisted stage results; dot = hidden from listings.
CACHE_DIR = ".prefect"

#: Bump a stage's version when the format or meaning of its outputs changes: old cache entries
#: then stop matching and the stage (and everything after it) is recomputed.
STAGE_VERSIONS: dict[str, int] = {
    **{stage: 1 for stage in STAGES},
    # 2: ingest reads each photo's focal length from its EXIF (``focal_px``): photos with one
    # are read again and get a new identity (SfM starts from it); photos without one keep theirs
    # 3: ... and its GPS position (``gps``), which can set SfM poses' scale: photos with one get
    # a new identity, photos without keep theirs (and everything after ingest stays cached)
    "ingest": 3,
    # 2: imported poses are levelled too (metric ones on their gravity axis, unscaled), read
    # as metric only where their source is an AR capture ("auto"), their intrinsics scaled to
    # the ingested photos; every lens is recorded with its model
    # 3: auto matching closes the capture's loop (the last photos with the first) before it
    # matches every pair: another pair set, another model, where the sequential pass fell short
    "poses": 3,
    # 2: TSDF truncation 3.5 voxels by default (3 thinned the leaves of SfM reconstructions)
    # 3: photos are undistorted into their pinhole cameras first (SfM's SIMPLE_RADIAL k and
    # imported lenses were dropped)
    # 4: TSDF fusion without the half-pixel shift, its blocks from every depth (not every
    # fourth pixel); stereo at most 1024 px a side (mvs_max_side)
    "surfaces": 4,
    # 2: the best row's direction from the lateral profile's period, not its raw sharpness
    # (which the TSDF's voxel lattice pulled to the scene axes, 6.2° off on one reconstruction)
    # 3: ... and the camera clears the colour band too (soybean 0.25 m), in which the
    # observation's mask drops green leaves while a prediction keeps them
    # 4: a user's camera height is taken above the fitted ground plane, not levelling's ground;
    # maize's row-spacing scale from plant points within 3 m (was the rows' 2 m ROI)
    # 5: a row-spacing scale that the refit does not confirm is not applied (the scale-1 fit,
    # ``assumed_metric``; it was applied as ``row_spacing``, 19 % off on one scene); a scene
    # whose scale was confirmed writes the same bytes, so its observation and fit stay cached
    # 6: nadir photos at a hand-held scale whose canopy a drone could show (under 15 % of
    # the cameras' height) stop with a named error (soybean drone flights read LAI 0.09 for
    # 1.26); every other scene writes the same bytes and stays cached downstream
    # 7: maize's ground plane moves down to a parallel plane under it holding half its soil
    # points (``lower_ground_share``: a 25 m flight's plane lay on the canopy's top); a scene
    # whose ground has none writes the same bytes; a GPS scale records the rows' period at it
    "rowfit": 7,
    # 2: maize's depth bins start just above the observed canopy (depth_top_margin 0.25);
    # soybean's observations come out the same bytes, so their fits stay cached
    # 3: a pooled row camera outside the reconstruction is left out of the pool (session 50);
    # single-camera observations come out the same bytes, so their fits stay cached
    "observe": 3,
    "observe_rows": 2,
    # 2: predictions are cut by the observation's box (height >= 0.1 m, |y| limit) like the
    # observation itself; before, the low leaves it drops counted on the predicted side only
    "fit_seed": 2,
    "aggregate": 2,
    # 2: the soybean leaflet's tip face wound like its other faces (canopy.ply's normals);
    # the depth renders, and so every fit, are the same to the bit
    "generate": 2,
    # 2: n_faces_total counts the generated canopy's faces, not those of the wider canopy the
    # gap-fraction rays cross; the sensors' seed defaults to the canopy's (as in generate)
    "metrics": 2,
    # 2: params.json as cropcraft generate's and fit's (plants in the plot and in all; "fit"
    # holds the answer's fit record, not only its settings)
    "export": 2,
    # 2: the page opens with the run's warnings (the console's, lost by morning)
    # 3: ... the reconstruction's net cover against the photos among them (and in
    # warnings.json, the season's note); the depth maps' caption and colour key
    "report": 3,
}

#: Stage folder in the store per stage (``fit_seed`` and ``aggregate`` share ``fit/``).
STAGE_FOLDERS: dict[str, str] = {
    "ingest": "ingest",
    "poses": "poses",
    "surfaces": "surfaces",
    "rowfit": "rowfit",
    "consistency": "consistency",
    "observe": "observe",
    "observe_rows": "observe",
    "fit_seed": "fit",
    "aggregate": "fit",
    "rows": "rows",
    "generate": "generate",
    "metrics": "metrics",
    "export": "export",
    "report": "report",
}


# --------------------------------------------------------------------------- cache key


def upstream_hashes(upstream: Mapping[str, Any] | None) -> dict[str, dict[str, str]]:
    """``{name: {store key: sha256}}`` of upstream stage records (or input fingerprints).

    Each value of ``upstream`` is a stage record (its ``identity`` where it has one, else its
    ``hashes``) or a plain ``{name: hash}`` mapping (an input fingerprint).
    """
    out: dict[str, dict[str, str]] = {}
    for name, rec in sorted((upstream or {}).items()):
        if rec is None:
            continue
        if not isinstance(rec, Mapping):
            raise ConfigError(f"upstream {name!r} must be a stage record, got {type(rec)}")
        hashes = (rec.get("identity") or rec["hashes"]) if "hashes" in rec else rec
        out[str(name)] = {str(k): str(v) for k, v in dict(hashes).items()}
    return out


#: Settings a stage's task reads that do not change its result, keyed at one value: a fit
#: seed's count of fellow seeds only sizes its threads (seed 3 of 12 is seed 3 of 10), so a fit
#: raised from 10 to 12 seeds fits two more, not twelve (10: keys as before this existed).
KEYED_AS: dict[str, dict[str, Any]] = {"fit_seed": {"n_seeds": 10}}


def stage_log() -> Any:
    """The run's logger inside a Prefect run (its records in the UI), else the ``cropcraft``
    logger: a stage task called as a plain function (``task.fn``) still says what it warns."""
    import logging

    from prefect import get_run_logger
    from prefect.exceptions import MissingContextError

    try:
        return get_run_logger()
    except MissingContextError:
        return logging.getLogger("cropcraft")


def stage_key(
    stage: str,
    scene: str,
    config: Any,
    upstream: Mapping[str, Any] | None,
    extra: Mapping[str, Any] | None = None,
) -> str:
    """The cache key (and result path) of one stage run: see the module docstring.

    scene: ``site/crop/date``; config: the stage's own config (JSON-able);
    upstream: upstream stage records; extra: other identity (the optimiser seed).
    """
    if stage not in STAGE_VERSIONS:
        raise ConfigError(f"unknown stage {stage!r}: one of {', '.join(STAGES)}")
    SceneKey.parse(scene)  # validates
    if isinstance(config, Mapping) and stage in KEYED_AS:
        config = {**config, **{k: v for k, v in KEYED_AS[stage].items() if k in config}}
    identity = {
        "stage": stage,
        "version": STAGE_VERSIONS[stage],
        "scene": scene,
        "config": config_hash(config if config is not None else {}),
        "upstream": upstream_hashes(upstream),
        "extra": {k: v for k, v in sorted((extra or {}).items()) if v is not None},
    }
    digest = sha256_bytes(canonical_json(identity))
    return f"{scene}/{CACHE_DIR}/{stage}/{digest}"


def cache_key_fn(context: Any, parameters: dict[str, Any]) -> str:
    """Prefect ``cache_key_fn``: :func:`stage_key` from the task's name and parameters.

    Parameters named ``scene``, ``config``, ``upstream``, ``seed`` and ``row`` make the identity
    (``seed`` and ``row`` only when given, so a best-row seed keys as before rows existed); every
    other parameter (the store root, source URIs) is deliberately not part of it: the same
    inputs in another place give the same results.
    """
    return stage_key(
        context.task.name,
        parameters["scene"],
        parameters.get("config"),
        parameters.get("upstream"),
        {"seed": parameters.get("seed"), "row": parameters.get("row")},
    )


def stage_task(name: str, **options: Any) -> Callable[[Callable[..., dict]], Any]:
    """Decorator: a Prefect task for stage ``name`` with the CropCraft cache policy.

    Results are persisted (JSON) under their cache key in the flow's result storage; a task run
    whose key already has a result finishes ``Cached`` without running.
    """
    if name not in STAGE_VERSIONS:
        raise ConfigError(f"unknown stage {name!r}")
    defaults: dict[str, Any] = {
        "name": name,
        "cache_key_fn": cache_key_fn,
        "persist_result": True,
        "result_serializer": "json",
        "cache_result_in_memory": False,
        "log_prints": False,
    }
    defaults.update(options)
    return task(**defaults)


#: stage → (module, task attribute); imported on first use by :func:`get_task`.
TASK_OBJECTS: dict[str, tuple[str, str]] = {
    "ingest": ("tasks.ingest", "ingest"),
    "poses": ("tasks.poses", "poses"),
    "surfaces": ("tasks.surfaces", "surfaces"),
    "rowfit": ("tasks.rowfit", "rowfit"),
    "consistency": ("tasks.consistency", "consistency"),
    "observe": ("tasks.observe", "observe"),
    "observe_rows": ("tasks.observe", "observe_rows"),
    "fit_seed": ("tasks.fit_seed", "fit_seed_task"),
    "aggregate": ("tasks.aggregate", "aggregate"),
    "rows": ("tasks.rows", "rows"),
    "generate": ("tasks.generate", "generate"),
    "metrics": ("tasks.metrics", "metrics"),
    "export": ("tasks.export", "export"),
    "report": ("tasks.report", "report"),
}


def get_task(stage: str) -> Any:
    """The Prefect task of ``stage``."""
    import importlib

    module, attr = TASK_OBJECTS[stage]
    return getattr(importlib.import_module(module), attr)


def core(stage: str, module: str, *names: str) -> Any:
    """Import ``names`` from the core module a stage needs; CropCraftError("stage X not
    available: ...") when that part of ``cropcraft_core`` is missing from this installation."""
    import importlib

    from cropcraft_core.errors import CropCraftError

    try:
        mod = importlib.import_module(module)
        values = tuple(getattr(mod, n) for n in names)
    except (ImportError, AttributeError) as exc:
        raise CropCraftError(
            f"stage {stage} not available: {module} cannot provide {', '.join(names)} ({exc}); "
            "install a CropCraft version that includes it"
        ) from exc
    return values[0] if len(values) == 1 else values


# --------------------------------------------------------------------------- store plumbing


def open_store(
    root: str, *, scene: str | None = None, lease: str | None = None, what: str = "a stage"
) -> SceneStore:
    """The scene store at ``root`` (credentials from the worker's own environment).

    Every stage opens its store first, on whatever worker runs it, so this is also where the
    worker's process is made fit for array work: :func:`cropcraft_core.parallel.reuse_freed_memory`
    undoes the small malloc thresholds a Dask nanny pins on its workers (a no-op elsewhere).

    ``lease``: the token of the run's scene lease (``scene``'s; not part of any cache key).
    Each write into the store then first asks that the run still holds the scene
    (:func:`~cropcraft_core.lease.require_holder`): a stage on a Dask worker goes on after its
    run ended (a Ctrl-C, a killed command, a lost client) and would write over a rerun's files,
    as a killed run's pool workers did (session 93's overlap audit).
    """
    from cropcraft_core.parallel import reuse_freed_memory

    reuse_freed_memory()
    store = SceneStore(root)
    if lease is not None and scene is not None:
        from cropcraft_core.lease import require_holder

        key = SceneKey.parse(scene)
        store.before_write = lambda: require_holder(store, key, lease, what)
    return store


def load_observation(store: SceneStore, upstream: Mapping[str, Any]):
    """The :class:`~cropcraft_core.observe.Observation` of ``upstream["observe"]``."""
    import io

    from cropcraft_core.observe import Observation

    key = key_of(upstream["observe"], "observation")
    try:
        return Observation.load(io.BytesIO(store.get_bytes(key)))
    except InputError as exc:
        if store.url(key) in str(exc):
            raise
        raise InputError(f"{store.url(key)}: {exc}") from exc


def stage_folder(scene: str, stage: str, row: int | None = None) -> str:
    """Store folder (key) of ``stage``'s artefacts: ``{scene}/{folder}``, for a neighbour row
    ``row`` ``{scene}/{folder}/row_p1`` (:func:`artefact`)."""
    if row is None:
        return f"{scene}/{STAGE_FOLDERS[stage]}"
    from cropcraft_core.rowfit.neighbours import row_label

    return f"{scene}/{STAGE_FOLDERS[stage]}/{row_label(row)}"


def artefact(scene: str, stage: str, name: str, row: int | None = None) -> str:
    """Store key of an artefact of ``stage`` (``{scene}/{folder}/{name}``); for a neighbour row
    ``row`` (±k, see ``cropcraft_core.rowfit.neighbours``) ``{scene}/{folder}/row_p1/{name}``."""
    return f"{stage_folder(scene, stage, row)}/{name}"


def make_record(
    stage: str,
    scene: str,
    artefacts: Mapping[str, str],
    hashes: Mapping[str, str],
    summary: Mapping[str, Any] | None = None,
    seconds: float = 0.0,
    identity: Mapping[str, str] | None = None,
) -> dict[str, Any]:
    """A stage record: ``artefacts`` {name: key}, ``hashes`` {key: sha256}, a small summary,
    and ``environment``: the numeric libraries of the process that computed it
    (:func:`cropcraft_core.store.environment_versions`; a cached record keeps the one that
    computed it).

    ``identity`` ({key: sha256}, optional): what later stages key on instead of ``hashes``,
    for an artefact whose bytes hold provenance that no later stage reads (the ingest
    manifest names the folder it read). ``hashes`` stay the bytes written: the check that a
    cached record's artefacts are still in the store uses them."""
    record = {
        "stage": stage,
        "scene": scene,
        "artefacts": dict(artefacts),
        "hashes": dict(sorted(hashes.items())),
        "summary": dict(summary or {}),
        "seconds": float(seconds),
        "environment": environment_versions(),
    }
    if identity is not None:
        record["identity"] = dict(sorted(identity.items()))
    return record


def key_of(record: Mapping[str, Any], name: str) -> str:
    """Store key of artefact ``name`` of an upstream record (InputError if it has none)."""
    try:
        return record["artefacts"][name]
    except (KeyError, TypeError):
        stage = record.get("stage") if isinstance(record, Mapping) else "?"
        raise InputError(f"stage {stage!r} record has no artefact {name!r}") from None


@contextlib.contextmanager
def workdir(prefix: str) -> Iterator[Path]:
    """A private local scratch folder for tools that need real files; removed afterwards.

    Its name carries this process's pid and host (``cropcraft-export@PID.HOST-…``): a stage
    whose process was ended without unwinding (a deployment's run cancelled from Prefect, a
    worker killed) left it behind, 40 MB an export (session 92's deployment audit), and no
    later run removed it. Each new one first sweeps such folders of this host whose process
    is gone (:func:`sweep_scratch`)."""
    sweep_scratch()
    owner = f"{os.getpid()}.{_host_tag()}"
    with tempfile.TemporaryDirectory(prefix=f"cropcraft-{prefix}@{owner}-") as d:
        yield Path(d)


_SCRATCH_NAME = re.compile(r"^cropcraft-\w+@(\d+)\.([0-9a-f]{8})-")


def _host_tag() -> str:
    import hashlib
    import socket

    return hashlib.sha256(socket.gethostname().encode()).hexdigest()[:8]


def sweep_scratch(base: str | Path | None = None) -> list[str]:
    """Remove the scratch folders (:func:`workdir`) in ``base`` (the temp folder) that a
    process of this host made and that process is gone; returns their paths. A folder of a
    live process, another host's, or one this user cannot remove stays."""
    import shutil

    from cropcraft_core.parallel import process_gone

    base = Path(base or tempfile.gettempdir())
    host, gone = _host_tag(), []
    try:
        entries = list(os.scandir(base))
    except OSError:
        return gone
    for entry in entries:
        m = _SCRATCH_NAME.match(entry.name)
        if not m or m.group(2) != host or not entry.is_dir(follow_symlinks=False):
            continue
        if not process_gone(int(m.group(1))):  # alive (another user's too)
            continue
        shutil.rmtree(entry.path, ignore_errors=True)
        if not os.path.exists(entry.path):
            gone.append(entry.path)
    return gone


def checkpoint_dir() -> Path:
    """Local folder for per-seed optimiser checkpoints: ``$CROPCRAFT_WORK/checkpoints``, by
    default the temp folder's ``cropcraft-<user id>/checkpoints``, the user's own (mode 0700):
    a folder every user shared belonged to whoever made it first, so the next user's seeds
    failed on a bare PermissionError, and could resume another user's checkpoint of the same
    cache key. A folder this process cannot write is a ConfigError naming the setting."""
    base = os.environ.get("CROPCRAFT_WORK")
    if not base:
        who = os.getuid() if hasattr(os, "getuid") else os.environ.get("USERNAME", "user")
        base = os.path.join(tempfile.gettempdir(), f"cropcraft-{who}")
    path = Path(base) / "checkpoints"
    try:
        path.mkdir(mode=0o700, parents=True, exist_ok=True)
    except OSError as exc:
        raise ConfigError(
            f"cannot create the optimiser's checkpoint folder {path}: {exc}; set "
            "CROPCRAFT_WORK to a folder this user can write"
        ) from None
    if not os.access(path, os.W_OK | os.X_OK):
        raise ConfigError(
            f"the optimiser's checkpoint folder {path} is not writable by this user; set "
            "CROPCRAFT_WORK to a folder this user can write"
        )
    return path


class Timer:
    """``with Timer() as t: ...`` then ``t.seconds`` (wall clock)."""

    def __enter__(self) -> Timer:
        self._t0 = time.perf_counter()
        self.seconds = 0.0
        return self

    def __exit__(self, *exc: object) -> None:
        self.seconds = time.perf_counter() - self._t0


# --------------------------------------------------------------------------- input fingerprints


def fingerprint(uri: str, *, what: str = "images") -> dict[str, str]:
    """``{name: identity}`` of the files at a folder or file URI (local path or fsspec URL).

    The identity is the object's size plus its ETag / checksum / modification time, whatever the
    backend reports: cheap (no file is read), and any edit, replacement or re-upload changes it.
    A file gives one entry; a folder of images one per file directly in it (what ingest reads),
    a poses folder one per file anywhere under it (a COLMAP project keeps its model in
    ``sparse/0/``), named by relative path; hidden files and folders are skipped. Listings are
    read afresh (fsspec caches an S3 folder's listing for the process's life, which would hide
    photos uploaded since). Raises InputError naming the URI when nothing is there.
    """
    from fsspec.core import url_to_fs

    from cropcraft_core.sfm.ingest import (
        IMAGE_EXTENSIONS,
        UNSUPPORTED_EXTENSIONS,
        check_photo_links,
        is_listed_file,
    )

    try:
        fs, path = url_to_fs(os.fspath(uri))
        with contextlib.suppress(Exception):
            fs.invalidate_cache(path)
        root = str(path).rstrip("/")
        if fs.isfile(path) and what == "images":
            raise InputError(f"image source {uri!r} is a file, not a folder of photos")
        if fs.isfile(path):
            infos = {root.rsplit("/", 1)[-1]: fs.info(path)}
            ply = named_ply(fs, root) if what == "poses" else None
            if ply is not None:  # a transforms.json's sparse points are part of the poses
                with contextlib.suppress(OSError):
                    infos[ply[0]] = fs.info(ply[1])
        else:
            depth = 1 if what == "images" else None
            found = fs.find(path, maxdepth=depth, detail=True).items()
            infos = {
                str(name)[len(root) + 1 :]: i
                for name, i in found
                if is_listed_file(fs, i) and str(name).startswith(root + "/")
            }
            if what == "images":
                check_photo_links(fs, [i for _, i in found], uri)
            for name, i in list(infos.items()):
                if i.get("islink") and getattr(fs, "local_file", False):  # the target's size, time
                    infos[name] = {**i, **fs.info(os.path.realpath(i["name"]))}
    except FileNotFoundError:
        infos = {}
    except InputError:
        raise
    except Exception as exc:  # s3fs lets botocore's credential and endpoint errors through
        raise InputError(f"cannot list {what} at {uri!r}: {type(exc).__name__}: {exc}") from exc
    out: dict[str, str] = {}
    for name, info in infos.items():
        if any(part.startswith(".") for part in name.split("/")):
            continue
        if what == "images" and not name.lower().endswith(
            IMAGE_EXTENSIONS + UNSUPPORTED_EXTENSIONS
        ):
            continue  # an unsupported photo is part of the input: ingest names it
        tag = (
            info.get("ETag")
            or info.get("etag")
            or info.get("checksum")
            or info.get("md5")
            or info.get("mtime")
            or info.get("LastModified")
            or info.get("last_modified")
            or ""
        )
        out[name] = f"{info.get('size')}:{str(tag).strip(chr(34))}"
    if not out:
        deeper = _photos_below(uri) if what == "images" else []
        hint = ""
        if len(deeper) == 1:
            hint = f"; the photos are in {deeper[0]!r} below it: give that folder"
        elif deeper:
            listed = ", ".join(map(repr, deeper[:8])) + (", ..." if len(deeper) > 8 else "")
            hint = (
                f"; the photos are in {len(deeper)} folders below it ({listed}): put the "
                "scene's photos in one folder and give that"
            )
        raise InputError(
            f"no {what} found at {uri!r}: check the URI (a folder of JPEG/PNG photos, or a "
            f"poses file / COLMAP model folder){hint}"
        )
    return dict(sorted(out.items()))


def _photos_below(uri: str, depth: int = 3) -> list[str]:
    """The subfolders (relative paths, up to ``depth`` levels down) of ``uri`` that hold
    JPEG/PNG photos: a camera's card copied whole keeps them in ``DCIM/100MEDIA`` (and
    ``101MEDIA`` after 999 photos), and only the folder itself is read. [] where there is
    none (or it cannot be listed)."""
    from cropcraft_core.sfm.ingest import photos_below

    # photos ``depth`` levels below ``uri`` lie ``depth - 1`` below its subfolders
    found = photos_below(uri, depth - 1)
    return list(dict.fromkeys(rel.rsplit("/", 1)[0] for rel in found))


def named_ply(fs: Any, path: str, text: str | bytes | None = None) -> tuple[str, str] | None:
    """``(name relative to the file, path on fs)`` of the sparse-point PLY that the
    ``transforms.json`` at ``path`` names in ``ply_file_path``, where that file is there; None
    for a file naming none (or no JSON). ``text``: the file's contents, where already read."""
    from cropcraft_core.sfm.poses import transforms_ply

    try:
        rel = transforms_ply(json.loads(fs.cat_file(path) if text is None else text))
        if rel is None:
            return None
        ply = f"{path.rsplit('/', 1)[0]}/{rel}" if "/" in path else rel
        return (rel, ply) if fs.isfile(ply) else None
    except (OSError, UnicodeDecodeError, ValueError):
        return None


# --------------------------------------------------------------------------- progress


class Tick(NamedTuple):
    """One progress report. ``kind="fit"``: an optimiser evaluation finished; ``key`` is the
    optimiser seed (``"row_p1/3"`` for seed 3 of a neighbour row's fit), ``done`` / ``total``
    its evaluations and ``best`` its lowest loss so far (``None`` before the first).
    ``kind="stage"``: a long stage's step moved on; ``key`` names it (``"surfaces: stereo"``),
    ``done`` / ``total`` its progress (per cent for the surfaces)."""

    scene: str
    key: int | str
    done: int
    total: int
    best: float | None = None
    kind: str = "fit"


_progress_lock = threading.Lock()
ProgressSink = Callable[[Tick], None]
_progress_sink: ProgressSink | None = None


def set_progress_sink(sink: ProgressSink | None) -> None:
    """Install ``sink(tick)``, called with each :class:`Tick` (the CLI's console progress,
    ``flows.service_cli.run_progress``).

    Tasks running in this process report (threads runner), and so do the workers of the
    ``processes`` runner, through a queue (``flows.runners.LocalProcessPool``), and a Dask
    cluster's workers, through the scheduler's events (:func:`deliver`; ``flows.dask_runner``).
    """
    global _progress_sink
    with _progress_lock:
        _progress_sink = sink


#: The Dask event topic on which a Dask worker's tasks report their progress; the run's Dask
#: client (``flows.runners``) hands each to its own process's sink.
PROGRESS_TOPIC = "cropcraft-progress"
#: A fit seed's ticks a Dask worker sends: every ``1/FIT_TICKS_SENT`` of its evaluations and
#: its last (each a message through the scheduler; the console prints every 10 %).
FIT_TICKS_SENT = 100


def deliver(tick: Tick) -> None:
    """Hand ``tick`` to the installed sink (no-op without one; a failing sink is ignored).
    In a Dask worker, which has no sink, it goes to the scheduler as an event on
    :data:`PROGRESS_TOPIC` for the run's client (a fit seed's ticks thinned to
    :data:`FIT_TICKS_SENT`): the ``dask`` runners printed no progress at all (session 92's Dask
    audit)."""
    sink = _progress_sink
    if sink is not None:
        with contextlib.suppress(Exception):
            sink(tick)
    elif "distributed" in sys.modules:  # only a Dask worker's process can have a worker
        step = max(1, tick.total // FIT_TICKS_SENT)
        if tick.kind == "fit" and tick.done % step and tick.done != tick.total:
            return
        with contextlib.suppress(Exception):  # not in a worker (ValueError), or it closes
            from distributed import get_worker

            get_worker().log_event(PROGRESS_TOPIC, tick._asdict())


def deliver_event(event: tuple[float, Any]) -> None:
    """A Dask client's handler of :data:`PROGRESS_TOPIC`: ``event``, ``(time, tick as a
    dict, to which the scheduler adds the sending ``worker``)``, handed to this process's sink
    as a :class:`Tick`."""
    with contextlib.suppress(Exception):  # a malformed event is dropped, never the client
        deliver(Tick(**{k: v for k, v in event[1].items() if k in Tick._fields}))


def report_progress(
    scene: str, seed: int | str, done: int, total: int, best: float | None = None
) -> None:
    """One fit evaluation finished: a ``fit`` :class:`Tick`."""
    deliver(Tick(scene, seed, int(done), int(total), best, "fit"))


def report_stage(scene: str, what: str, done: int, total: int) -> None:
    """A long stage's step moved on: a ``stage`` :class:`Tick` (``what``: e.g.
    ``"surfaces: stereo"``)."""
    deliver(Tick(scene, what, int(done), int(total), None, "stage"))


def stage_progress(scene: str, stage: str) -> Callable[[str, float], None]:
    """A core function's ``progress(step, fraction)`` for ``stage``: to the console's progress
    (:func:`report_stage`, in per cent, as ``"{stage}: {step}"``) and to the run's log at every
    25 %."""
    log = stage_log()
    logged: dict[str, int] = {}

    def progress(step: str, fraction: float) -> None:
        pct = int(round(100 * min(1.0, max(0.0, float(fraction)))))
        report_stage(scene, f"{stage}: {step}", pct, 100)
        if pct // 25 > logged.get(step, 0) // 25:  # each 25 % mark (a lone 100 % too)
            log.info("%s: %s %d %%", stage, step, pct)
        logged[step] = pct

    return progress


def photos_left_out(records: Mapping[str, Any]) -> dict[str, list[str]]:
    """The photos a run left out, by reason, from its stage records (a flow's records, or a
    stage's upstream): without a pose in the imported poses, not registered by SfM, not seeing
    the scene box, copies of another photo (:data:`cropcraft_core.report.LEFT_OUT_WHY`)."""
    return {
        "unposed": records["poses"]["summary"].get("unposed", []),
        "unregistered": records["poses"]["summary"].get("unregistered", []),
        "outside_box": records["surfaces"]["summary"].get("photos_left_out", []),
        "duplicates": records["ingest"]["summary"].get("duplicate_names", []),
        "in_subfolders": records["ingest"]["summary"].get("in_subfolders", []),
    }
