"""The scene store: every artefact of every scene, keyed by site, crop, date and stage.

One store is a root URI understood by fsspec:

* ``./cropcraft-data`` (the default, or ``$CROPCRAFT_STORE``): a local folder, no server;
* ``s3://bucket/prefix``: S3 or any S3-compatible server (MinIO, Ceph, moto). The endpoint comes
  from ``storage_options["endpoint_url"]`` (or ``client_kwargs``), else ``$FSSPEC_S3_ENDPOINT_URL``,
  ``$AWS_ENDPOINT_URL_S3`` or ``$AWS_ENDPOINT_URL``; credentials from ``storage_options``
  (``key``/``secret``) or botocore's usual chain (``$AWS_ACCESS_KEY_ID``, profiles, roles);
* any other fsspec URL (``memory://``, ``gs://``, ...).

Layout under the root::

    {site}/{crop}/{date}/manifest.json        inputs, config, code version, stage records
    {site}/{crop}/{date}/images/...           ingested photos
    {site}/{crop}/{date}/{stage}/...          one folder per pipeline stage

Keys are relative POSIX paths under the root (``"plotA/soybean/2024-07-01/sfm/cameras.json"``);
build them with :func:`scene_prefix`, :func:`stage_prefix` and :func:`artefact_key`. Open a store
with ``SceneStore.connect(root)``, which fails fast with :class:`StoreError` (URI redacted) when
the bucket or folder cannot be reached or written, before any work starts. Path segments that
start with a dot are reserved for the store itself (temporary objects, locks) and never appear
in :meth:`SceneStore.list`.

Atomicity guarantee: every ``put_*`` writes to a sibling temporary key
``.../.tmp-<uuid>-<name>`` and moves it into place only after the last byte was written. On a
local folder the move is ``os.replace`` (atomic rename on the same filesystem, after ``fsync``);
on S3 it is a server-side copy followed by a delete, and S3 never exposes a partially copied
object. Either way a reader of the final key sees the previous complete object or the new
complete object, never a partial one; a writer that fails leaves the old value untouched and
removes its temporary object (a writer killed outright may leave a ``.tmp-`` object behind,
invisible to ``list`` and removed by :meth:`SceneStore.sweep_tmp`).

Concurrency: a manifest's read-modify-write (:meth:`SceneStore.update_stage`,
:meth:`SceneStore.init_manifest`) loses no update to other writers -- a thread lock within a
process, an ``flock`` across processes on a local store, and on S3 a conditional PUT that
replaces only the version read (``If-Match``), retried on the newer one. One run of a scene
at a time is :mod:`cropcraft_core.lease`'s, built on the same conditional writes.

Large arrays never travel through Prefect or Dask: a task writes its arrays here and returns the
keys and the sha256 that every ``put_*`` returns; the next task reads them back by key.
:class:`SceneStore` pickles to its root and options, so it can be shipped to workers, but flows
should pass the (credential-free) ``store.root`` and let workers take credentials from their own
environment, so no secret ends up in Prefect's parameter records.

Credentials never appear in ``repr``, log lines, error messages or manifests: everything shown
goes through :func:`redact`.
"""

from __future__ import annotations

import contextlib
import dataclasses
import datetime as _dt
import hashlib
import io
import json
import logging
import os
import re
import shutil
import subprocess
import sys
import tempfile
import threading
import time
import uuid
from collections.abc import Callable, Iterator, Mapping
from functools import lru_cache
from pathlib import Path, PurePosixPath
from typing import Any, BinaryIO, Literal

import fsspec
import numpy as np
from fsspec.core import url_to_fs
from fsspec.implementations.local import LocalFileSystem
from fsspec.spec import AbstractBufferedFile
from pydantic import BaseModel, ConfigDict, Field

from cropcraft_core import __version__
from cropcraft_core.config.params import CROPS
from cropcraft_core.errors import ConfigError, CropCraftError, InputError

__all__ = [
    "DEFAULT_ROOT",
    "STAGE_STATUSES",
    "DiscoveredScene",
    "Manifest",
    "SceneKey",
    "SceneStore",
    "StageRecord",
    "SceneBusyError",
    "StoreError",
    "artefact_key",
    "canonical_json",
    "code_version",
    "config_hash",
    "environment_versions",
    "numeric_kernels",
    "redact",
    "scene_prefix",
    "sha256_bytes",
    "sha256_file",
    "stage_prefix",
]

log = logging.getLogger(__name__)

DEFAULT_ROOT = "./cropcraft-data"
"""Store root when neither an argument nor ``$CROPCRAFT_STORE`` names one."""

TMP_PREFIX = ".tmp-"
"""Basename prefix of in-flight objects; hidden from :meth:`SceneStore.list`."""

MANIFEST_NAME = "manifest.json"
IMAGES_STAGE = "images"
#: The folder of ``{site}/{crop}`` the season summary is written to (not a date).
SEASON_FOLDER = "season"
#: How many levels below a folder of ``{site}/{crop}`` the season looks for photos that are not
#: in an ``images/`` inbox (a camera card's ``DCIM/100MEDIA/`` copied under a date: two).
PHOTO_SEARCH_DEPTH = 3
_CHUNK = 1 << 20


class StoreError(CropCraftError, OSError):
    """The scene store cannot be reached, read or written (network, bucket, permissions)."""


class SceneBusyError(StoreError):
    """Another run holds the scene (:meth:`SceneStore.hold_scene`), or took it over from this
    one after this one stopped renewing its lease."""


# --------------------------------------------------------------------------------------------
# Names and keys
# --------------------------------------------------------------------------------------------

_NAME_RE = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]*\Z")
_DATE_RE = re.compile(r"\d{4}-\d{2}-\d{2}\Z")
_CONTROL_RE = re.compile(r"[\x00-\x1f\x7f]")


def _check_name(value: object, what: str) -> str:
    """Return ``value`` if it is a safe single path segment, else raise ConfigError."""
    if not isinstance(value, str) or not _NAME_RE.match(value) or ".." in value:
        raise ConfigError(
            f"invalid {what} name {value!r}: use letters, digits, '_', '.' and '-', starting "
            "with a letter or digit, with no '..', no '/' and no absolute path"
        )
    return value


def _check_date(value: object) -> str:
    """Return an ISO ``YYYY-MM-DD`` string for ``value`` (str or ``datetime.date``)."""
    if isinstance(value, _dt.datetime):
        raise ConfigError(f"invalid scene date {value!r}: give a date, not a datetime")
    if isinstance(value, _dt.date):
        return value.isoformat()
    if isinstance(value, str) and _DATE_RE.match(value):
        try:
            _dt.date.fromisoformat(value)
        except ValueError:
            pass
        else:
            return value
    raise ConfigError(f"invalid scene date {value!r}: use an ISO date YYYY-MM-DD, e.g. 2024-07-01")


def _is_date(name: str) -> bool:
    """Whether a folder name is a scene date (``YYYY-MM-DD``, a real day)."""
    try:
        _check_date(name)
    except ConfigError:
        return False
    return True


def disk_hint(exc: BaseException) -> str | None:
    """What to do about a full disk or a read-only file system behind ``exc`` (or its causes),
    else None: such errors ended with "check the store URI, endpoint, credentials", which sent
    users the wrong way (session 94's disk audit)."""
    import errno

    seen: set[int] = set()
    while exc is not None and id(exc) not in seen:
        seen.add(id(exc))
        code = getattr(exc, "errno", None)
        if code in (errno.ENOSPC, errno.EDQUOT):
            return "the disk (or the user's quota) is full: free space there, then run again"
        if code == errno.EROFS:
            return "the file system is mounted read-only: give a writable store"
        if "database or disk is full" in str(exc):
            return "the disk is full: free space there, then run again"
        exc = exc.__cause__ or exc.__context__
    return None


def _check_key(key: object, *, allow_empty: bool = False, reserved: bool = False) -> str:
    """Validate a store key (relative POSIX path) and return it without a trailing slash;
    ``reserved``: a dot-named last segment allowed (the store's own objects: a scene's lease)."""
    if not isinstance(key, str):
        raise ConfigError(f"store key must be a string, got {type(key).__name__}")
    stripped = key.rstrip("/")
    if not stripped:
        if allow_empty:
            return ""
        raise ConfigError("empty store key: name an object such as 'site/crop/date/stage/file'")
    if stripped.startswith("/") or "\\" in stripped or "://" in stripped:
        raise ConfigError(
            f"invalid store key {key!r}: keys are relative paths under the store root "
            "(no leading '/', no '\\', no URL scheme)"
        )
    if _CONTROL_RE.search(stripped):
        raise ConfigError(f"invalid store key {key!r}: control characters are not allowed")
    parts = stripped.split("/")
    for i, part in enumerate(parts):
        if part in ("", ".", ".."):
            raise ConfigError(
                f"invalid store key {key!r}: empty, '.' and '..' path segments are not allowed"
            )
        if part.startswith(".") and not (reserved and i == len(parts) - 1):
            raise ConfigError(
                f"invalid store key {key!r}: segments starting with '.' are reserved for the "
                "store's temporary objects"
            )
    return stripped


@dataclasses.dataclass(frozen=True, order=True)
class SceneKey:
    """One scene: a plot (``site``) of one ``crop`` photographed on one ``date``.

    ``site`` matches ``[A-Za-z0-9][A-Za-z0-9_.-]*`` without ``..``; ``crop`` is one of the crops
    CropCraft models (``soybean``, ``maize``); ``date`` is ISO ``YYYY-MM-DD`` (a
    ``datetime.date`` is accepted and stored as its ISO string). Invalid values raise
    :class:`~cropcraft_core.errors.ConfigError` at construction, before any work starts.
    """

    site: str
    crop: str
    date: str

    def __post_init__(self) -> None:
        _check_name(self.site, "site")
        if self.crop not in CROPS:
            raise ConfigError(
                f"unknown crop {self.crop!r} for site {self.site!r}: choose one of "
                f"{', '.join(sorted(CROPS))}"
            )
        object.__setattr__(self, "date", _check_date(self.date))

    @property
    def prefix(self) -> str:
        """The scene's folder key, ``{site}/{crop}/{date}``."""
        return f"{self.site}/{self.crop}/{self.date}"

    def __str__(self) -> str:
        return self.prefix

    @classmethod
    def parse(cls, prefix: str) -> SceneKey:
        """Inverse of :attr:`prefix`: ``SceneKey.parse("plotA/soybean/2024-07-01")``."""
        parts = str(prefix).strip("/").split("/")
        if len(parts) != 3:
            raise ConfigError(f"invalid scene {prefix!r}: expected 'site/crop/YYYY-MM-DD'")
        return cls(*parts)


def scene_prefix(scene: SceneKey) -> str:
    """Key of a scene's folder: ``{site}/{crop}/{date}``."""
    if not isinstance(scene, SceneKey):
        raise ConfigError(f"expected a SceneKey, got {type(scene).__name__}")
    return scene.prefix


def stage_prefix(scene: SceneKey, stage: str) -> str:
    """Key of one stage's folder: ``{site}/{crop}/{date}/{stage}``."""
    return f"{scene_prefix(scene)}/{_check_name(stage, 'stage')}"


def artefact_key(scene: SceneKey, stage: str, name: str) -> str:
    """Key of one artefact: ``{site}/{crop}/{date}/{stage}/{name}`` (``name`` may contain '/')."""
    return _check_key(f"{stage_prefix(scene, stage)}/{_check_key(name)}")


def manifest_key(scene: SceneKey) -> str:
    """Key of a scene's manifest: ``{site}/{crop}/{date}/manifest.json``."""
    return f"{scene_prefix(scene)}/{MANIFEST_NAME}"


# --------------------------------------------------------------------------------------------
# Hashing and canonical JSON
# --------------------------------------------------------------------------------------------


def sha256_bytes(data: bytes | bytearray | memoryview) -> str:
    """Hex sha256 of a bytes-like object."""
    return hashlib.sha256(data).hexdigest()


def sha256_file(path: str | os.PathLike[str]) -> str:
    """Hex sha256 of a local file, read in 1 MiB chunks."""
    digest = hashlib.sha256()
    try:
        with open(path, "rb") as f:
            for chunk in iter(lambda: f.read(_CHUNK), b""):
                digest.update(chunk)
    except FileNotFoundError as exc:
        raise InputError(f"cannot hash {os.fspath(path)!r}: no such file") from exc
    return digest.hexdigest()


def _json_default(obj: Any) -> Any:
    """JSON encoder for the small records CropCraft stores (numpy, pydantic, dataclasses...)."""
    if isinstance(obj, BaseModel):
        return obj.model_dump(mode="json")
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return dataclasses.asdict(obj)
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        if obj.size > 10_000:
            raise TypeError(
                f"refusing to JSON-encode an array of {obj.size} elements: store it with put_npz"
            )
        return obj.tolist()
    if isinstance(obj, (_dt.date, _dt.datetime)):
        return obj.isoformat()
    if isinstance(obj, PurePosixPath | Path):
        return obj.as_posix()
    if isinstance(obj, (set, frozenset)):
        return sorted(obj)
    raise TypeError(f"object of type {type(obj).__name__} is not JSON serialisable")


def canonical_json(obj: Any) -> bytes:
    """UTF-8 canonical JSON: sorted keys, no whitespace, no NaN/Infinity.

    Equal data always gives equal bytes, so the sha256 of this is a stable identity (used for
    :func:`config_hash`).
    """
    try:
        text = json.dumps(
            obj,
            sort_keys=True,
            separators=(",", ":"),
            ensure_ascii=False,
            allow_nan=False,
            default=_json_default,
        )
    except (TypeError, ValueError) as exc:
        raise InputError(
            f"cannot encode value as canonical JSON ({exc}); use plain numbers, strings, lists "
            "and dicts, and None instead of NaN"
        ) from exc
    return text.encode("utf-8")


def config_hash(config: Any) -> str:
    """sha256 of :func:`canonical_json` of a config (dict, pydantic model or dataclass)."""
    return sha256_bytes(canonical_json(config))


@lru_cache(maxsize=1)
def code_version() -> str:
    """``cropcraft_core.__version__``, plus ``+<git describe>`` when run from a git checkout."""
    repo = Path(__file__).resolve().parent.parent
    if not (repo / ".git").exists():
        return __version__
    try:
        out = subprocess.run(
            ["git", "-C", str(repo), "describe", "--always", "--dirty", "--tags"],
            capture_output=True,
            text=True,
            timeout=5,
            check=True,
        )
    except (OSError, subprocess.SubprocessError):
        return __version__
    described = out.stdout.strip()
    return f"{__version__}+{described}" if described else __version__


#: The libraries a stage's numbers are computed with, by distribution name; where one has
#: alternatives (Open3D's CPU and CUDA wheels, OpenCV's builds) the first installed is named.
#: The fit's answer moves with them (benchmarks/RESULTS.md#demo), which is why
#: ``deploy/constraints.txt`` pins them and every stage record says which ran it.
NUMERIC_PACKAGES: tuple[tuple[str, ...], ...] = (
    ("numpy",),
    ("scipy",),
    ("numba",),
    ("llvmlite",),
    ("open3d-cpu", "open3d"),
    ("opencv-python-headless", "opencv-python", "opencv-contrib-python-headless"),
    ("pycolmap",),
    ("torch",),
    ("scikit-learn",),
    ("scikit-optimize",),
)


@lru_cache(maxsize=1)
def environment_versions() -> dict[str, str]:
    """``{distribution: version}`` of :data:`NUMERIC_PACKAGES` in this process, plus
    ``python`` and the CPU-specific kernels that ran (:func:`numeric_kernels`); a library that
    is not installed is left out."""
    from importlib import metadata

    out = {"python": ".".join(str(v) for v in sys.version_info[:3])}
    for names in NUMERIC_PACKAGES:
        for name in names:
            try:
                out[name] = metadata.version(name)
                break
            except metadata.PackageNotFoundError:
                continue
    return {**out, **numeric_kernels()}


def numeric_kernels() -> dict[str, str]:
    """Which CPU-specific kernels this process's numpy and OpenBLAS run: ``numpy-simd``, the
    highest of numpy's dispatch targets that the CPU (less ``NPY_DISABLE_CPU_FEATURES``)
    enables, else its baseline; ``openblas-core``, the core type OpenBLAS chose (or
    ``OPENBLAS_CORETYPE`` set), as threadpoolctl reads it. The same code and libraries give
    other last bits with other kernels, and the fit's answer moves with them: one demo seed
    refitted with numpy's AVX-512 loops off, or with OpenBLAS's Haswell kernels instead of
    SkylakeX, left the stored trajectory after 212 and 6 evaluations (benchmarks/RESULTS.md
    *#seed-traits*). Entries that cannot be read are left out."""
    out: dict[str, str] = {}
    try:
        from numpy._core._multiarray_umath import (  # numpy >= 2
            __cpu_baseline__,
            __cpu_dispatch__,
            __cpu_features__,
        )

        enabled = [t for t in __cpu_dispatch__ if __cpu_features__.get(t)]
        if enabled or __cpu_baseline__:
            out["numpy-simd"] = (enabled or __cpu_baseline__)[-1]
    except ImportError:
        pass
    try:
        from threadpoolctl import threadpool_info
    except ImportError:
        return out
    blas = [i for i in threadpool_info() if i.get("internal_api") == "openblas"]
    # numpy's own OpenBLAS first (scipy may load another)
    blas.sort(key=lambda i: "numpy" not in str(i.get("filepath", "")))
    if blas and blas[0].get("architecture"):
        out["openblas-core"] = str(blas[0]["architecture"])
    return out


# --------------------------------------------------------------------------------------------
# Redaction
# --------------------------------------------------------------------------------------------

_USERINFO_RE = re.compile(r"(?P<scheme>\b[A-Za-z][A-Za-z0-9+.-]*://)[^/@\s?#]+@")
_QUERY_SECRET_RE = re.compile(
    r"(?P<k>[?&](?:x-amz-signature|x-amz-credential|x-amz-security-token|sig|signature|"
    r"token|access_token|key|secret|password|sv|se)=)[^&#\s]*",
    re.IGNORECASE,
)
_SECRET_KEY_RE = re.compile(
    r"key|secret|token|passw|pwd|credential|signature|auth|session|sas", re.IGNORECASE
)


def redact(value: Any) -> Any:
    """Return ``value`` with credentials removed, safe to log or store.

    * a string (URI or message): ``user:pass@`` after a scheme is stripped and secret query
      parameters (``X-Amz-Signature``, ``sig``, ``token``...) are replaced by ``***``;
    * a mapping (fsspec ``storage_options``): values under secret-looking keys (``key``,
      ``secret``, ``token``, ``password``, ``aws_access_key_id``...) become ``"***"``; other
      values are redacted recursively;
    * lists and tuples element-wise; anything else unchanged.
    """
    if isinstance(value, str):
        text = _USERINFO_RE.sub(lambda m: m.group("scheme"), value)
        return _QUERY_SECRET_RE.sub(lambda m: m.group("k") + "***", text)
    if isinstance(value, Mapping):
        out: dict[Any, Any] = {}
        for k, v in value.items():
            secret = isinstance(k, str) and _SECRET_KEY_RE.search(k) and not isinstance(v, bool)
            out[k] = "***" if secret and v is not None else redact(v)
        return out
    if isinstance(value, list | tuple):
        return type(value)(redact(v) for v in value)
    return value


# --------------------------------------------------------------------------------------------
# Manifest
# --------------------------------------------------------------------------------------------

StageStatus = Literal["pending", "running", "done", "failed"]
STAGE_STATUSES: tuple[str, ...] = ("pending", "running", "done", "failed")


def _now() -> _dt.datetime:
    return _dt.datetime.now(_dt.UTC)


class StageRecord(BaseModel):
    """What the manifest remembers about one stage of one scene."""

    model_config = ConfigDict(extra="allow")

    status: StageStatus = "pending"
    """pending | running | done | failed."""
    config_hash: str | None = None
    """sha256 of the canonical JSON of the config this stage ran with."""
    inputs: dict[str, str] = Field(default_factory=dict)
    """Upstream artefacts this stage read: {store key: sha256}."""
    artefacts: dict[str, str] = Field(default_factory=dict)
    """What this stage wrote: {store key: sha256}."""
    started: _dt.datetime | None = None
    """UTC time the current attempt started."""
    finished: _dt.datetime | None = None
    """UTC time it finished (done or failed)."""
    seconds: float | None = None
    """Wall-clock seconds of the attempt."""
    error: str | None = None
    """One-line error of a failed attempt (credentials redacted)."""
    environment: dict[str, str] = Field(default_factory=dict)
    """The numeric libraries' versions in the process that computed the stage
    (:func:`environment_versions`); empty for records written before it was kept."""


class Manifest(BaseModel):
    """A scene's ``manifest.json``: what went in, with which config and code, and what came out.

    Unknown fields written by newer versions are kept on read-modify-write (``extra="allow"``).
    """

    model_config = ConfigDict(extra="allow")

    schema_version: int = 1
    """Version of this layout."""
    site: str
    crop: str
    date: str
    inputs: dict[str, str] = Field(default_factory=dict)
    """Scene inputs (images, imported poses): {name or key: sha256}."""
    sources: dict[str, str | None] = Field(default_factory=dict)
    """Where the last run read its inputs: ``{"images": URL or path, "poses": ...}`` as it was
    given (None: the scene's inbox in the store), so ``cropcraft status`` can check the cache
    for photos that never went to the inbox."""
    config: dict[str, Any] = Field(default_factory=dict)
    """The resolved scene config, as canonical JSON data."""
    config_hash: str = ""
    """sha256 of :func:`canonical_json` of ``config``."""
    code_version: str = ""
    """``cropcraft_core.__version__`` plus ``git describe`` where available."""
    stages: dict[str, StageRecord] = Field(default_factory=dict)
    """Per-stage records, by stage name."""
    written: dict[str, str] = Field(default_factory=dict)
    """{store key: sha256} of what the last write to each artefact key put there, whichever
    run and config wrote it; unlike ``stages`` it survives a config change, so a cached stage
    record can be checked against what the store really holds."""
    writing: dict[str, str] = Field(default_factory=dict)
    """{attempt name: store folder} of every stage attempt that began and has not yet been
    recorded (done or failed): one whose run died in between (killed, out of memory, its record
    refused) may have written there unseen by ``written``. The next run hashes those folders
    into ``written`` before it trusts any cached record (:meth:`SceneStore.settle_writing`), and
    ``cropcraft status`` counts records there as not cached. Survives a config change too."""
    created: _dt.datetime | None = None
    updated: _dt.datetime | None = None

    @property
    def scene(self) -> SceneKey:
        """The scene this manifest describes."""
        return SceneKey(self.site, self.crop, self.date)

    def done_stages(self) -> list[str]:
        """Names of stages whose status is ``done``, sorted."""
        return sorted(name for name, rec in self.stages.items() if rec.status == "done")


@dataclasses.dataclass(frozen=True)
class DiscoveredScene:
    """A small record for the season flow: one dated scene found in the store."""

    scene: SceneKey
    n_images: int
    """Objects under ``{scene}/images/``."""
    has_manifest: bool
    stages: dict[str, str]
    """{stage: status} from the manifest (empty when there is none)."""
    inputs: dict[str, str] = dataclasses.field(default_factory=dict)
    """The manifest's input fingerprints (:attr:`Manifest.inputs`; empty when there is none)."""
    sources: dict[str, str | None] = dataclasses.field(default_factory=dict)
    """Where its last run read them (:attr:`Manifest.sources`)."""

    @property
    def done(self) -> tuple[str, ...]:
        """Stages whose status is ``done``, sorted."""
        return tuple(sorted(s for s, status in self.stages.items() if status == "done"))


# --------------------------------------------------------------------------------------------
# The store
# --------------------------------------------------------------------------------------------


def _backend_errors() -> tuple[type[BaseException], ...]:
    """Exception types raised by fsspec backends for I/O trouble (not programming errors).

    Evaluated only when an exception is being handled; botocore and aiohttp are looked up only
    if already imported (an exception of theirs implies they are), so importing this module
    stays cheap.
    """
    errors: list[type[BaseException]] = [OSError, TimeoutError]
    botocore_exceptions = sys.modules.get("botocore.exceptions")
    if botocore_exceptions is not None:
        errors.append(botocore_exceptions.BotoCoreError)
    aiohttp = sys.modules.get("aiohttp")
    if aiohttp is not None:
        errors.append(aiohttp.ClientError)
    return tuple(errors)


_S3_PROTOCOLS = {"s3", "s3a"}
_manifest_locks: dict[str, threading.Lock] = {}
_manifest_locks_guard = threading.Lock()


def _protocol_of(root: str) -> str:
    return root.split("://", 1)[0].lower() if "://" in root else "file"


def _s3_endpoint(options: Mapping[str, Any]) -> str | None:
    """The S3 endpoint that ``storage_options`` name (``endpoint_url``, top level or in
    ``client_kwargs``), or None."""
    client_kwargs = options.get("client_kwargs") or {}
    return options.get("endpoint_url") or client_kwargs.get("endpoint_url")


def _resolve_s3_options(options: dict[str, Any]) -> dict[str, Any]:
    """Fill the S3 endpoint from the environment when ``storage_options`` do not name one."""
    if not _s3_endpoint(options):
        for var in ("FSSPEC_S3_ENDPOINT_URL", "AWS_ENDPOINT_URL_S3", "AWS_ENDPOINT_URL"):
            if os.environ.get(var):
                options["endpoint_url"] = os.environ[var]
                break
    return options


def _json_bytes(key: str, obj: Any) -> bytes:
    """``obj`` as :meth:`SceneStore.put_json` stores it under ``key``: stable JSON (sorted
    keys, 2-space indent, UTF-8, trailing newline); InputError where it is no JSON."""
    try:
        text = json.dumps(
            obj,
            sort_keys=True,
            indent=2,
            ensure_ascii=False,
            allow_nan=False,
            default=_json_default,
        )
    except (TypeError, ValueError) as exc:
        raise InputError(
            f"cannot write {key!r} as JSON ({exc}); use plain numbers, strings, lists and "
            "dicts, None instead of NaN, and put_npz for arrays"
        ) from exc
    return (text + "\n").encode("utf-8")


def reserved_name(key: str) -> bool:
    """True for the store's own objects: a key whose last segment starts with a dot."""
    return key.rsplit("/", 1)[-1].startswith(".")


_CONDITIONAL_CHECKED: dict[tuple[str, str], str | None] = {}
"""Per (endpoint, bucket): None where the server honours conditional writes, else why not
(:meth:`SceneStore._require_conditional`, probed once per process)."""
_CONDITIONAL_LOCK = threading.Lock()
_UNGUARDED_WARNED: set[tuple[str, str]] = set()
"""(protocol, root) of the stores without cross-process exclusion this process has warned of
(:meth:`SceneStore._warn_unguarded`)."""


def _lost_race(exc: BaseException) -> bool:
    """True where a conditional S3 write failed because another writer changed the object
    (412 Precondition Failed; 409 ConditionalRequestConflict for two at the same moment):
    read again and retry, rather than report a store error."""
    if isinstance(exc, FileExistsError):  # s3fs's If-None-Match failure
        return True
    cause = exc.__cause__ if exc.__cause__ is not None else exc
    response = getattr(cause, "response", None) or {}
    code = str((response.get("Error") or {}).get("Code", ""))
    status = (response.get("ResponseMetadata") or {}).get("HTTPStatusCode")
    return code in {"PreconditionFailed", "ConditionalRequestConflict"} or status in {409, 412}


def _server_age(resp: Mapping[str, Any]) -> float | None:
    """Seconds since an S3 object was written, by the server's clock alone (the response's
    ``Date`` header less ``LastModified``): no trust in this machine's clock."""
    import email.utils

    modified = resp.get("LastModified")
    date = ((resp.get("ResponseMetadata") or {}).get("HTTPHeaders") or {}).get("date")
    if modified is None or not date:
        return None
    try:
        now = email.utils.parsedate_to_datetime(date)
    except (TypeError, ValueError):
        return None
    return max(0.0, (now - modified).total_seconds())


class _HashingWriter:
    """File-like wrapper that hashes and counts every byte written (no seek: stream only).

    Backend errors while writing become StoreError naming the key.
    """

    def __init__(self, raw: BinaryIO, store: SceneStore, key: str) -> None:
        self._raw = raw
        self._store = store
        self._key = key
        self._digest = hashlib.sha256()
        self.size = 0

    def write(self, data: bytes) -> int:
        view = memoryview(data).cast("B")
        with self._store._io("write", self._key, reading=False):
            self._raw.write(view)
        self._digest.update(view)
        self.size += view.nbytes
        return view.nbytes

    def tell(self) -> int:
        return self.size

    def flush(self) -> None:
        if getattr(self._raw, "closed", False):
            return
        with self._store._io("write", self._key, reading=False):
            self._raw.flush()

    def writable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return False

    @property
    def sha256(self) -> str:
        return self._digest.hexdigest()


class AtomicWrite(io.RawIOBase):
    """What :meth:`SceneStore.open_write` yields: a write-only, non-seekable binary stream
    (``write``, ``tell``, ``flush``) plus, after commit, the object's ``sha256`` and ``size``."""

    def __init__(self, key: str, writer: _HashingWriter) -> None:
        super().__init__()
        self.key = key
        self._writer = writer
        self.sha256: str | None = None
        """Hex sha256 of the committed object; None until the ``with`` block succeeded."""
        self.size: int | None = None
        """Bytes committed; None until the ``with`` block succeeded."""

    def write(self, data) -> int:
        """Append bytes."""
        return self._writer.write(data)

    def tell(self) -> int:
        """Bytes written so far."""
        return self._writer.tell()

    def flush(self) -> None:
        """Flush buffered bytes to the temporary object."""
        self._writer.flush()

    def writable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return False


class SceneStore:
    """Artefact store over any fsspec filesystem; see the module docstring for layout and
    guarantees.

    Parameters
    ----------
    root:
        Root URI; default ``$CROPCRAFT_STORE`` or ``./cropcraft-data`` (resolved to an absolute
        path at construction). Credentials in the URI (``s3://user:pass@...``) are refused: give
        them through ``storage_options`` or the environment.
    storage_options:
        Passed to the fsspec filesystem (e.g. ``{"endpoint_url": ..., "key": ..., "secret":
        ...}`` for S3). For ``s3://`` roots without an endpoint, ``$FSSPEC_S3_ENDPOINT_URL``,
        ``$AWS_ENDPOINT_URL_S3`` or ``$AWS_ENDPOINT_URL`` is used.

    Construction never touches the network; call :meth:`check_reachable` before starting work.
    """

    def __init__(self, root: str | os.PathLike[str] | None = None, storage_options=None) -> None:
        raw_root = os.fspath(root) if root is not None else None
        raw_root = raw_root or os.environ.get("CROPCRAFT_STORE") or DEFAULT_ROOT
        self._raw_root = raw_root
        #: Called before each object is moved into place or deleted; what it raises stops the
        #: write, leaving the key as it was (a stage's task: its run still holds the scene,
        #: ``tasks.common.open_store``).
        self.before_write: Callable[[], None] | None = None
        self._storage_options: dict[str, Any] = dict(storage_options or {})
        self.protocol = _protocol_of(raw_root)
        if self.protocol in _S3_PROTOCOLS:
            if _USERINFO_RE.match(raw_root):
                raise ConfigError(
                    f"store URI {redact(raw_root)!r} carries credentials: remove 'user:pass@' "
                    "and give them via storage_options or AWS_ACCESS_KEY_ID/AWS_SECRET_ACCESS_KEY"
                )
            self._storage_options = _resolve_s3_options(self._storage_options)
        try:
            self.fs, path = url_to_fs(raw_root, **self._storage_options)
        except (ValueError, ImportError, TypeError) as exc:
            raise ConfigError(
                f"cannot open store {redact(raw_root)!r}: {redact(str(exc))}; check the URI "
                "scheme and storage_options"
            ) from exc
        self._root_path = path.rstrip("/") or path
        self._local = isinstance(self.fs, LocalFileSystem)
        self.root: str = redact(self.fs.unstrip_protocol(self._root_path))
        """Credential-free URI of the root (safe to log, pass to Prefect, store in records)."""

    @classmethod
    def connect(
        cls,
        root: str | os.PathLike[str] | None = None,
        storage_options=None,
        *,
        timeout_s: float = 5.0,
    ) -> SceneStore:
        """Open a store and :meth:`check_reachable` it: the call flows make before any work."""
        store = cls(root, storage_options)
        store.check_reachable(timeout_s=timeout_s)
        return store

    # ---- plumbing -------------------------------------------------------------------------

    def __repr__(self) -> str:
        return f"SceneStore({self.root!r})"

    def __reduce__(self):
        # a local root as resolved here: a relative one would name another folder in a
        # process started elsewhere (a worker, a spawned seed)
        root = self.fs.unstrip_protocol(self._root_path) if self._local else self._raw_root
        return (SceneStore, (root, self._storage_options))

    def describe(self) -> dict[str, Any]:
        """Root and storage options with secrets redacted (for logs and reports)."""
        return {"root": self.root, "storage_options": redact(self._storage_options)}

    def _full(self, key: str) -> str:
        return f"{self._root_path}/{key}" if key else self._root_path

    def _rel(self, path: str) -> str | None:
        """Key of a backend path, or None when it is not under the root."""
        path = path.rstrip("/")
        base = self._root_path.rstrip("/") + "/"
        return path[len(base) :] if path.startswith(base) else None

    def url(self, key: str) -> str:
        """Full, credential-free fsspec URL of a key (``s3://bucket/prefix/key``,
        ``file:///abs/path``)."""
        key = _check_key(key, allow_empty=True, reserved=True)
        return redact(self.fs.unstrip_protocol(self._full(key)))

    @contextlib.contextmanager
    def _io(self, action: str, key: str, *, reading: bool) -> Iterator[None]:
        """Turn backend exceptions into InputError (missing object on read) or StoreError."""
        try:
            yield
        except CropCraftError:
            raise
        except (IsADirectoryError, NotADirectoryError, FileExistsError) as exc:
            what = (
                "it is a folder, not an object"
                if isinstance(exc, IsADirectoryError)
                else "an object stands where the key's folder would be, or a folder where the "
                "object would be"
            )
            raise InputError(f"cannot {action} {self.url(key)}: {what}") from exc
        except FileNotFoundError as exc:
            where = self.url(key)
            if reading:
                raise InputError(
                    f"cannot {action} {where}: no such object; run the stage that writes it "
                    "first (or check the scene, stage and name)"
                ) from exc
            raise StoreError(
                f"cannot {action} {where}: {redact(str(exc))}; check that the bucket/folder "
                "of the store root exists"
            ) from exc
        except _backend_errors() as exc:
            raise StoreError(
                f"cannot {action} {self.url(key)}: {type(exc).__name__}: {redact(str(exc))}; "
                + (disk_hint(exc) or "check the store URI, endpoint, credentials and permissions")
            ) from exc

    def _tmp_path(self, final: str) -> str:
        parent, _, name = final.rpartition("/")
        return f"{parent}/{TMP_PREFIX}{uuid.uuid4().hex}-{name}"

    def _rm_quiet(self, path: str) -> None:
        try:
            if self._local:
                os.unlink(path)
            else:
                self.fs.rm_file(path)
        except FileNotFoundError:
            pass
        except Exception:  # best effort: cleanup must not mask the real error
            log.warning("could not remove temporary object %s", redact(path))

    def _invalidate(self, path: str) -> None:
        with contextlib.suppress(Exception):
            self.fs.invalidate_cache(path)

    # ---- writing --------------------------------------------------------------------------

    @contextlib.contextmanager
    def open_write(self, key: str) -> Iterator[AtomicWrite]:
        """Atomic binary writer: ``with store.open_write(key) as f: f.write(...)``.

        Bytes go to a temporary sibling key and are moved onto ``key`` only when the block exits
        without an exception; on an exception the temporary object is removed and the previous
        value of ``key`` (if any) is left intact. After the block ``f.sha256`` and ``f.size``
        describe the committed object.
        """
        key = _check_key(key)
        final = self._full(key)
        tmp = self._tmp_path(final)
        with self._io("write", key, reading=False):
            if self._local:
                os.makedirs(os.path.dirname(final), exist_ok=True)
                raw: Any = open(tmp, "wb")  # closed below on every path
            else:
                raw = self.fs.open(tmp, "wb")
        writer = _HashingWriter(raw, self, key)
        handle = AtomicWrite(key, writer)
        try:
            yield handle
            with self._io("write", key, reading=False):
                raw.flush()
                if self._local:
                    os.fsync(raw.fileno())
                raw.close()
                self._commit(tmp, final)
        except BaseException:
            with contextlib.suppress(Exception):
                if isinstance(raw, AbstractBufferedFile) and not raw.closed:
                    raw.discard()  # s3fs: abort a multipart upload instead of completing it
                    raw.closed = True
                else:
                    raw.close()
            self._rm_quiet(tmp)
            handle.close()
            raise
        handle.close()
        handle.sha256 = writer.sha256
        handle.size = writer.size

    def _commit(self, tmp: str, final: str) -> None:
        """Move a finished temporary object onto its final key (:attr:`before_write` first)."""
        if self.before_write is not None:
            try:
                self.before_write()
            except BaseException:
                self._rm_quiet(tmp)
                raise
        if self._local:
            os.replace(tmp, final)
            return
        try:
            self.fs.cp_file(tmp, final)  # S3: server-side CopyObject, atomic for readers
        except BaseException:
            self._rm_quiet(tmp)
            raise
        finally:
            self._invalidate(final)
        self._rm_quiet(tmp)  # if this fails the leftover is hidden and swept later

    def put_bytes(self, key: str, data: bytes | bytearray | memoryview) -> str:
        """Store bytes atomically under ``key``; return their sha256."""
        with self.open_write(key) as f:
            f.write(data)
        assert f.sha256 is not None
        return f.sha256

    def put_json(self, key: str, obj: Any) -> str:
        """Store ``obj`` as stable JSON (sorted keys, 2-space indent, UTF-8, trailing newline).

        Accepts dicts, lists, numbers, strings, pydantic models, dataclasses and small numpy
        values; NaN/Infinity are refused (use None). Returns the sha256 of the stored bytes.
        """
        return self.put_bytes(key, _json_bytes(key, obj))

    def put_npz(self, key: str, arrays: Mapping[str, Any], *, compress: bool = True) -> str:
        """Store named numpy arrays as one ``.npz`` (compressed by default, no pickles).

        ``arrays`` maps names (no '/') to array-likes; object arrays are refused. The arrays are
        streamed into the temporary object, so a failure halfway leaves the old value intact.
        Returns the sha256 of the stored bytes.
        """
        if not isinstance(arrays, Mapping) or not arrays:
            raise InputError(f"put_npz({key!r}) needs a non-empty mapping of name -> array")
        for name in arrays:
            if not isinstance(name, str) or not name or "/" in name:
                raise InputError(f"put_npz({key!r}): invalid array name {name!r}")
        save = np.savez_compressed if compress else np.savez
        with self.open_write(key) as f:
            try:
                save(f, allow_pickle=False, **dict(arrays))
            except ValueError as exc:
                if "allow_pickle" in str(exc) or "Object arrays" in str(exc):
                    raise InputError(
                        f"cannot write {key!r}: an array has dtype object, which the store "
                        "refuses (no pickles); convert it to a numeric or string dtype"
                    ) from exc
                raise
        assert f.sha256 is not None
        return f.sha256

    def put_file(self, local_path: str | os.PathLike[str], key: str) -> str:
        """Copy a local file into the store atomically; return its sha256."""
        local_path = os.fspath(local_path)
        try:
            src = open(local_path, "rb")
        except FileNotFoundError as exc:
            raise InputError(f"cannot store {local_path!r}: no such local file") from exc
        except OSError as exc:  # a folder, no permission
            raise InputError(f"cannot store {local_path!r}: {exc.strerror or exc}") from exc
        with src, self.open_write(key) as f:
            shutil.copyfileobj(src, f, _CHUNK)
        assert f.sha256 is not None
        return f.sha256

    def put_tree(
        self, local_dir: str | os.PathLike[str], prefix: str, *, prune: bool = True
    ) -> dict[str, str]:
        """Copy every file under a local folder to ``prefix/...`` (each file atomically).

        Returns ``{key: sha256}``. Hidden files (names starting with '.') are skipped. With
        ``prune`` (the default) the folder then holds exactly this tree: objects under
        ``prefix`` that the tree lacks (a photo since removed, a file an earlier version wrote)
        are deleted, after every new file is in place, so readers that list the folder never
        see leftovers. Hidden objects (other writers' temporaries) are left alone.
        """
        root = Path(local_dir)
        if not root.is_dir():
            raise InputError(f"cannot store folder {os.fspath(local_dir)!r}: not a directory")
        prefix = _check_key(prefix)
        files = {}
        for path in sorted(root.rglob("*")):
            rel = path.relative_to(root).as_posix()
            if path.is_file() and not any(p.startswith(".") for p in rel.split("/")):
                try:  # every name first: a bad one stops the copy before it replaced anything
                    files[_check_key(f"{prefix}/{rel}")] = path
                except ConfigError as exc:
                    raise InputError(f"cannot store {os.fspath(path)!r}: {exc}") from None
        out = {key: self.put_file(path, key) for key, path in files.items()}
        if prune:
            for key in self.list(prefix):
                if key not in out and key != prefix:
                    self.delete(key)
        return out

    # ---- reading --------------------------------------------------------------------------

    def get_bytes(self, key: str) -> bytes:
        """Bytes stored under ``key``; InputError if there is none."""
        key = _check_key(key)
        with self._io("read", key, reading=True):
            return self.fs.cat_file(self._full(key))

    def get_json(self, key: str) -> Any:
        """Parsed JSON stored under ``key``."""
        data = self.get_bytes(key)
        try:
            return json.loads(data)
        except ValueError as exc:
            raise InputError(f"{self.url(key)} is not valid JSON ({exc})") from exc

    def get_npz(self, key: str) -> dict[str, np.ndarray]:
        """Arrays stored with :meth:`put_npz`, fully loaded (``allow_pickle=False``)."""
        data = self.get_bytes(key)
        try:
            with np.load(io.BytesIO(data), allow_pickle=False) as npz:
                return {name: npz[name] for name in npz.files}
        except Exception as exc:  # a damaged zip raises BadZipFile, zlib.error, TokenError, ...
            raise InputError(
                f"{self.url(key)} is not a readable pickle-free .npz ({type(exc).__name__}: {exc})"
            ) from exc

    def get_file(self, key: str, local_path: str | os.PathLike[str]) -> Path:
        """Copy ``key`` to a local file (written via a temporary sibling); return its path."""
        key = _check_key(key)
        dest = Path(local_path)
        dest.parent.mkdir(parents=True, exist_ok=True)
        tmp = dest.with_name(f"{TMP_PREFIX}{uuid.uuid4().hex}-{dest.name}")
        try:
            with self._io("read", key, reading=True):
                self.fs.get_file(self._full(key), str(tmp))
            os.replace(tmp, dest)
        finally:
            with contextlib.suppress(FileNotFoundError):
                tmp.unlink()
        return dest

    @contextlib.contextmanager
    def open_local(self, key: str) -> Iterator[Path]:
        """A local path holding ``key``'s content, for tools that need real files.

        On a local store this is the stored file (or folder) itself: treat it as read-only. On a
        remote store the object, or every object under the prefix ``key``, is downloaded into a
        temporary folder that is deleted when the block exits.
        """
        key = _check_key(key)
        full = self._full(key)
        if self._local:
            if not os.path.exists(full):
                raise InputError(f"cannot open {self.url(key)}: no such object or folder")
            yield Path(full)
            return
        with tempfile.TemporaryDirectory(prefix="cropcraft-") as tmpdir:
            name = key.rsplit("/", 1)[-1]
            target = Path(tmpdir) / name
            if self.isfile(key):
                self.get_file(key, target)
            else:
                keys = self.list(key)
                if not keys:
                    raise InputError(f"cannot open {self.url(key)}: no such object or folder")
                for k in keys:
                    self.get_file(k, target / k[len(key) + 1 :])
            yield target

    def sha256(self, key: str) -> str:
        """sha256 of the stored object, streamed in 1 MiB chunks."""
        key = _check_key(key)
        digest = hashlib.sha256()
        with self._io("hash", key, reading=True), self.fs.open(self._full(key), "rb") as f:
            for chunk in iter(lambda: f.read(_CHUNK), b""):
                digest.update(chunk)
        return digest.hexdigest()

    def hashes(self, prefix: str) -> dict[str, str]:
        """{key: sha256} of every object under the folder ``prefix`` (:meth:`list`'s keys)."""
        return {k: self.sha256(k) for k in self.list(prefix)}

    # ---- listing and deleting ---------------------------------------------------------------

    def exists(self, key: str) -> bool:
        """True if an object (or a non-empty folder) exists at ``key``."""
        key = _check_key(key)
        full = self._full(key)
        self._invalidate(full)
        with self._io("check", key, reading=True):
            return bool(self.fs.exists(full))

    def isfile(self, key: str) -> bool:
        """True if an object (not a folder) exists at ``key``."""
        key = _check_key(key)
        full = self._full(key)
        self._invalidate(full)
        with self._io("check", key, reading=True):
            return bool(self.fs.isfile(full))

    def list(self, prefix: str = "") -> list[str]:
        """Sorted keys of every object under the folder ``prefix`` (recursive).

        ``prefix`` is a folder key (``"site/soybean"`` does not match ``"site/soybean2"``);
        ``""`` lists the whole store. Temporary and other reserved dot-objects are never listed.
        """
        prefix = _check_key(prefix, allow_empty=True)
        full = self._full(prefix)
        self._invalidate(full)
        with self._io("list", prefix, reading=True):
            try:
                if not self.fs.isdir(full):
                    return [prefix] if prefix and self.fs.isfile(full) else []
                paths = self.fs.find(full)
            except FileNotFoundError:
                return []
        keys = []
        for path in paths:
            rel = self._rel(path)
            if rel is None or (prefix and not rel.startswith(prefix + "/")):
                continue
            if any(part.startswith(".") for part in rel.split("/")):
                continue
            keys.append(rel)
        return sorted(keys)

    def _children(self, prefix: str, *, folders: bool = False) -> list[str]:
        """Names of the immediate children (objects or folders) of a folder key; ``folders``:
        the sub-folders only, the objects beside them left out (a ``notes.txt`` or
        ``Thumbs.db`` beside a site's date folders is no date, and listing it as a folder
        failed the whole season: session 94's folders audit)."""
        full = self._full(prefix)
        self._invalidate(full)
        with self._io("list", prefix, reading=True):
            try:
                entries = self.fs.ls(full, detail=True)
            except (FileNotFoundError, NotADirectoryError):  # an object stands there
                return []
        names = {
            str(e["name"]).rstrip("/").rsplit("/", 1)[-1]
            for e in entries
            if not folders or e.get("type") == "directory"
        }
        return sorted(n for n in names if n and not n.startswith("."))

    def delete(self, key: str, *, recursive: bool = False) -> None:
        """Delete an object (or, with ``recursive=True``, everything under a folder key).

        Deleting a missing key is not an error.
        """
        if self.before_write is not None:
            self.before_write()
        key = _check_key(key)
        full = self._full(key)
        with self._io("delete", key, reading=False):
            try:
                if recursive and self.fs.isdir(full):
                    self.fs.rm(full, recursive=True)
                else:
                    self.fs.rm_file(full)
            except FileNotFoundError:
                pass
        self._invalidate(full)

    # ---- compare-and-swap of small objects ------------------------------------------------
    #
    # Object storage has no locks that outlive a process; S3 (and MinIO, Ceph, moto) has
    # conditional writes: a PUT with ``If-None-Match: *`` creates only where nothing is, one with
    # ``If-Match: <ETag>`` replaces only the version that was read. Read-modify-write of a small
    # object (a manifest, a lease) then loses no update among processes on any number of
    # machines: a writer whose version was replaced meanwhile reads again and retries.

    @property
    def conditional(self) -> bool:
        """True where :meth:`_write_if` is exact across processes and machines (S3); a local
        store serialises with ``flock`` instead; elsewhere (``memory://``, ``gs://``) writes of
        one object are serialised within this process only."""
        return self.protocol in _S3_PROTOCOLS

    def _s3_key(self, key: str) -> tuple[str, str]:
        bucket, path, _ = self.fs.split_path(self._full(key))
        return bucket, path

    def _read_tagged(self, key: str) -> tuple[bytes | None, str | None, float | None]:
        """``(bytes, version tag, age in seconds)`` of a small object, or ``(None, None, None)``
        where there is none. On S3 the tag is the ETag and the age the server's own clock
        (its ``Date`` less the object's ``Last-Modified``), read in one GET; elsewhere the tag
        is the content's sha256 and the age from the local clock. Reserved (dot-named) keys
        are allowed: the store's own objects."""
        key = _check_key(key, reserved=True)
        with self._io("read", key, reading=False):
            if not self.conditional:
                try:
                    data = self.fs.cat_file(self._full(key))
                except FileNotFoundError:
                    return None, None, None
                try:
                    age = time.time() - self.fs.modified(self._full(key)).timestamp()
                except (NotImplementedError, FileNotFoundError, OSError):
                    age = None
                return data, sha256_bytes(data), age
            from fsspec.asyn import sync

            bucket, path = self._s3_key(key)

            async def get() -> tuple[bytes | None, str | None, float | None]:
                try:
                    resp = await self.fs._call_s3("get_object", Bucket=bucket, Key=path)
                except FileNotFoundError:
                    return None, None, None
                body = resp["Body"]
                try:
                    data = await body.read()
                finally:
                    body.close()
                return data, resp["ETag"], _server_age(resp)

            return sync(self.fs.loop, get)

    def _write_if(self, key: str, data: bytes, tag: str | None) -> str | None:
        """Write ``data`` under ``key`` only if it still holds version ``tag`` (None: only if
        there is no object). Returns the new version's tag, or None where another writer got
        there first. Exact on S3 (one conditional PUT, atomic for readers); elsewhere call it
        under a lock that serialises the writers (``put_bytes`` after a tag check)."""
        key = _check_key(key, reserved=True)
        if not self.conditional:
            current, current_tag, _ = self._read_tagged(key)
            if current_tag != tag:
                return None
            if reserved_name(key):
                with self._io("write", key, reading=False):
                    if self._local:
                        os.makedirs(os.path.dirname(self._full(key)), exist_ok=True)
                    self.fs.pipe_file(self._full(key), bytes(data))
                self._invalidate(self._full(key))
            else:
                self.put_bytes(key, data)
            return sha256_bytes(data)
        bucket, path = self._s3_key(key)
        cond = {"IfMatch": tag} if tag is not None else {"IfNoneMatch": "*"}
        try:
            with self._io("write", key, reading=False):
                try:
                    resp = self.fs.call_s3(
                        "put_object", Bucket=bucket, Key=path, Body=bytes(data), **cond
                    )
                except OSError as exc:
                    if _lost_race(exc):
                        return None
                    raise
        finally:
            self._invalidate(self._full(key))
        return resp["ETag"]

    def _delete_if(self, key: str, tag: str) -> bool:
        """Delete ``key`` only if it still holds version ``tag``; False where it does not (or
        is gone). S3: a read, a compare and a delete (a conditional DELETE is not offered by
        every S3-compatible server), so call it only where no other writer may replace the
        object between the two (a lease its holder renews)."""
        _, current_tag, _ = self._read_tagged(key)
        if current_tag != tag:
            return False
        full = self._full(_check_key(key, reserved=True))
        with self._io("delete", key, reading=False), contextlib.suppress(FileNotFoundError):
            self.fs.rm_file(full)
        self._invalidate(full)
        return True

    def _require_conditional(self, key: str) -> None:
        """Refuse, once per process and bucket, an S3 server that ignores conditional writes.

        S3-compatible servers that predate conditional writes (MinIO before 2024, for one) do
        not fail a PUT with ``If-None-Match: *`` or ``If-Match``: they write it.
        Then two runs could both hold a scene's lease and manifest updates could be lost, with
        nothing said. So before its first lease or manifest change a process writes a probe
        object beside ``key`` three times -- created where there is none, again where it now
        is (must fail), over a version it does not hold (must fail) -- and removes it; a server
        that writes either of the last two is refused with a :class:`StoreError` naming it.
        Any other store is left to :meth:`_warn_unguarded`.
        """
        if not self.conditional:
            self._warn_unguarded()
            return
        bucket, _ = self._s3_key(_check_key(key, reserved=True))
        cache_key = (str(_s3_endpoint(self._storage_options) or "aws"), bucket)
        with _CONDITIONAL_LOCK:
            if cache_key not in _CONDITIONAL_CHECKED:
                _CONDITIONAL_CHECKED[cache_key] = self._probe_conditional(key)
            problem = _CONDITIONAL_CHECKED[cache_key]
        if problem:
            raise StoreError(problem)

    def _warn_unguarded(self) -> None:
        """Warn, once per process and store, that a store with neither conditional writes nor
        a local disk's ``flock`` (``gs://``, any fsspec store but S3 and ``memory://``, which
        no other process sees) serialises the lease and the manifest within this process only:
        two workers running one scene there may both hold its lease."""
        if self._local or self.protocol == "memory":
            return
        with _CONDITIONAL_LOCK:
            if (self.protocol, self.root) in _UNGUARDED_WARNED:
                return
            _UNGUARDED_WARNED.add((self.protocol, self.root))
        log.warning(
            "%s: this store has no conditional writes, so a scene's lease and its manifest "
            "updates are exclusive within this process only: two workers running one scene at "
            "once would interleave its artefacts. Run each scene on one worker at a time, or "
            "use S3 (or a local disk)",
            self.root,
        )

    def _probe_conditional(self, key: str) -> str | None:
        """:meth:`_require_conditional`'s probe: None where the server honours both
        conditions, else the refusal's message; a store error (the network, permissions)
        propagates and is not remembered."""
        parent, _, _ = key.rpartition("/")
        probe = f"{parent}/" * bool(parent) + f".conditional-probe-{uuid.uuid4().hex}"
        where = self.url(probe)
        ignored: list[str] = []
        try:
            tag = self._write_if(probe, b"1\n", None)
            if tag is None:
                return (
                    f"{where}: the S3 server refused to create a new object with "
                    "'If-None-Match: *' as if it existed; its conditional writes cannot be "
                    "trusted for the scene lease and manifest updates"
                )
            if self._write_if(probe, b"2\n", None) is not None:
                ignored.append("'If-None-Match: *' (it replaced an existing object)")
            stale = '"00000000000000000000000000000000"'
            if self._write_if(probe, b"3\n", stale) is not None:
                ignored.append("'If-Match' (it replaced a version the writer did not hold)")
        except StoreError as exc:
            raise StoreError(
                f"{where}: probing the S3 server's conditional writes (If-None-Match / If-Match "
                f"on PUT, which the scene lease and manifest updates need) failed: {exc}"
            ) from exc
        finally:
            with contextlib.suppress(Exception):
                self.fs.rm_file(self._full(probe))
            self._invalidate(self._full(probe))
        if not ignored:
            return None
        return (
            f"{where}: this S3 server ignores conditional writes: a PUT with "
            f"{' and one with '.join(ignored)} succeeded where it must fail. Without them two "
            "runs of one scene could both go ahead and manifest updates could be lost, so "
            "CropCraft does not run on it: use a server release with S3 conditional writes "
            "(AWS S3 and current MinIO have them), or a local store"
        )

    def sweep_tmp(self, prefix: str = "", older_than_s: float | None = 3600.0) -> list[str]:
        """Remove temporary objects left by killed writers, older than ``older_than_s``; with
        ``None`` every one under ``prefix``, and on S3 the multipart uploads a killed writer
        of a large object left unfinished (invisible to listings, billed until aborted).

        Returns the (relative) paths removed. Safe to run while writers are active as long as no
        single write takes longer than ``older_than_s``; ``None`` only by the holder of the
        scene's lease before its own writes (no other run writes there then: a killed run's
        leftover was kept an hour, and a rerun within it kept it for good once the scene
        finished, since nothing runs a finished scene's flow again: session 94's store audit).
        """
        prefix = _check_key(prefix, allow_empty=True)
        full = self._full(prefix)
        self._invalidate(full)
        removed = []
        now = time.time()
        with self._io("sweep", prefix, reading=False):
            try:
                paths = self.fs.find(full)
            except FileNotFoundError:
                paths = []
            for path in paths:
                if not path.rsplit("/", 1)[-1].startswith(TMP_PREFIX):
                    continue
                if older_than_s is not None:
                    try:
                        age = now - self.fs.modified(path).timestamp()
                    except (NotImplementedError, FileNotFoundError):
                        continue
                    if age < older_than_s:
                        continue
                self._rm_quiet(path)
                removed.append(self._rel(path) or path)
            if older_than_s is None and self.protocol in _S3_PROTOCOLS:
                removed += self._abort_uploads(prefix)
        return removed

    def _abort_uploads(self, prefix: str) -> list[str]:
        """Abort the unfinished multipart uploads of temporary objects under ``prefix`` (S3);
        the keys they were for."""
        bucket, path = self._s3_key(prefix)  # "" is the root
        listed = self.fs.call_s3(
            "list_multipart_uploads", Bucket=bucket, Prefix=path.rstrip("/") + "/" if path else ""
        )
        out = []
        for up in listed.get("Uploads") or []:
            if not str(up["Key"]).rsplit("/", 1)[-1].startswith(TMP_PREFIX):
                continue
            with contextlib.suppress(FileNotFoundError):
                self.fs.call_s3(
                    "abort_multipart_upload", Bucket=bucket, Key=up["Key"], UploadId=up["UploadId"]
                )
            out.append(self._rel(f"{bucket}/{up['Key']}") or up["Key"])
        return out

    # ---- reachability -----------------------------------------------------------------------

    def _folders_to_make(self) -> list[str]:
        """A local root's folders that do not exist yet (deepest first), which
        :meth:`check_reachable` creates; none on object storage."""
        if not self._local:
            return []
        made, path = [], os.path.abspath(self._root_path)
        while path and not os.path.exists(path):
            made.append(path)
            parent = os.path.dirname(path)
            if parent == path:
                break
            path = parent
        return made

    def check_reachable(self, timeout_s: float = 5.0) -> None:
        """Fail fast with :class:`StoreError` unless the root can be listed, written and read.

        Writes and deletes a small probe object under the root. For S3 a separate client with
        ``timeout_s`` connect/read timeouts and a single retry is used, so a dead endpoint fails
        in about ``timeout_s`` instead of botocore's default minute. Buckets are never created.
        """
        fs = self.fs
        if self.protocol in _S3_PROTOCOLS:
            opts = dict(self._storage_options)
            config_kwargs = dict(opts.get("config_kwargs") or {})
            config_kwargs.update(
                connect_timeout=timeout_s,
                read_timeout=timeout_s,
                retries={"total_max_attempts": 2, "mode": "standard"},
            )
            opts["config_kwargs"] = config_kwargs
            fs = fsspec.filesystem(self.protocol, skip_instance_cache=True, **opts)
            fs.retries = 1  # s3fs' own retry loop around botocore's
        probe = self._full(f"{TMP_PREFIX}probe-{uuid.uuid4().hex}")
        payload = b"cropcraft-probe"
        start = time.monotonic()
        try:
            if self._local:
                os.makedirs(self._root_path, exist_ok=True)
            fs.pipe_file(probe, payload)
            back = fs.cat_file(probe)
            fs.rm_file(probe)
            if back != payload:
                raise OSError("probe object read back differs from what was written")
        except _backend_errors() as exc:
            hint = (
                "the bucket does not exist (create it, or fix the bucket name)"
                if isinstance(exc, FileNotFoundError)
                else disk_hint(exc)
                or (
                    "check the folder's write permission"
                    if self._local
                    else "check the endpoint, network, credentials and write permission"
                )
            )
            raise StoreError(
                f"scene store {self.root} is not reachable or not writable "
                f"({type(exc).__name__}: {redact(str(exc))}); {hint}"
            ) from exc
        log.debug("store %s reachable in %.3f s", self.root, time.monotonic() - start)

    # ---- manifests ------------------------------------------------------------------------

    def load_manifest(self, scene: SceneKey) -> Manifest:
        """The scene's manifest; InputError if the scene has none (run ingest first)."""
        key = manifest_key(scene)
        return self._parse_manifest(key, self.get_bytes(key))

    def _parse_manifest(self, key: str, data: bytes, scene: SceneKey | None = None) -> Manifest:
        """The manifest in ``data`` (read from ``key``); with ``scene``, it describes that
        scene whatever its fields say (a scene folder copied or moved under another date
        keeps its manifest: an update must not go to, or name, the scene it came from)."""
        try:
            manifest = Manifest.model_validate(json.loads(data))
        except ValueError as exc:  # JSON's and pydantic's errors both
            raise InputError(f"{self.url(key)} is not a valid manifest: {exc}") from exc
        if scene is not None and manifest.scene != scene:
            manifest.site, manifest.crop, manifest.date = scene.site, scene.crop, scene.date
        return manifest

    @staticmethod
    def _manifest_bytes(manifest: Manifest) -> bytes:
        """``manifest`` stamped ``updated`` now, as :meth:`put_json` writes it."""
        manifest.updated = _now()
        if manifest.created is None:
            manifest.created = manifest.updated
        return _json_bytes(manifest_key(manifest.scene), manifest.model_dump(mode="json"))

    def save_manifest(self, manifest: Manifest) -> str:
        """Write a manifest atomically (``updated`` set to now); return its sha256. Replaces
        whatever is there: to change one, use :meth:`update_stage` (no lost updates)."""
        return self.put_bytes(manifest_key(manifest.scene), self._manifest_bytes(manifest))

    #: Attempts of one manifest change against writers in other processes (S3), each after a
    #: random pause of up to ``0.05 * 1.5**attempt`` s: ~25 s in all before giving up.
    _CAS_ATTEMPTS = 16

    def _change_manifest(
        self, scene: SceneKey, change: Callable[[bytes | None], Manifest | None]
    ) -> Manifest | None:
        """Read-modify-write of one scene's manifest with no lost update: ``change(current
        bytes or None)`` returns the new manifest, or None to leave it as it is (then None is
        returned). Within a process a thread lock serialises the writers; across processes a
        local store holds an ``flock``, and S3 replaces only the version that was read (a
        conditional PUT) and runs ``change`` again on the newer one."""
        key = manifest_key(scene)
        with self._manifest_lock(scene):
            self._require_conditional(key)
            if not self.conditional:
                current = self.get_bytes(key) if self.isfile(key) else None
                manifest = change(current)
                if manifest is not None:  # to the key read and locked
                    self.put_bytes(key, self._manifest_bytes(manifest))
                return manifest
            rng = np.random.default_rng()
            for attempt in range(self._CAS_ATTEMPTS):
                current, tag, _ = self._read_tagged(key)
                manifest = change(current)
                if manifest is None:
                    return None
                if self._write_if(key, self._manifest_bytes(manifest), tag) is not None:
                    return manifest
                time.sleep(float(rng.uniform(0.0, 0.05 * 1.5**attempt)))
            raise StoreError(
                f"cannot update {self.url(key)}: other writers replaced it on each of "
                f"{self._CAS_ATTEMPTS} attempts; is something rewriting it in a loop?"
            )

    def init_manifest(
        self,
        scene: SceneKey,
        inputs: Mapping[str, str],
        config: Any,
        *,
        version: str | None = None,
        sources: Mapping[str, str | None] | None = None,
    ) -> Manifest:
        """Create (or refresh) a scene's manifest from its inputs and resolved config;
        ``sources``: where the inputs were read (:attr:`Manifest.sources`).

        ``config`` is stored as canonical JSON data with its :func:`config_hash`. If a manifest
        already exists with the same inputs and config hash, its stage records are kept;
        otherwise they are reset, since every downstream artefact is stale.
        """
        data = json.loads(canonical_json(config))
        if not isinstance(data, dict):
            raise InputError(f"scene config for {scene} must be a mapping, got {type(config)}")
        chash = config_hash(data)
        key = manifest_key(scene)
        # no manifest, but artefacts (it was deleted): start ``written`` from what is there, as
        # for a damaged one, so no cached record is served over files it did not write (the
        # inbox's photos are inputs, not artefacts: a first run reads nothing more)
        lost = None if self.isfile(key) else self._scene_objects(scene, skip=("images",))

        def change(current: bytes | None) -> Manifest:
            recovered: dict[str, str] | None = None
            old = None
            if current is None and lost:
                recovered = lost
            if current is not None:
                try:
                    old = self._parse_manifest(key, current)
                except InputError:
                    recovered = self._set_aside_manifest(scene, current)
            manifest = Manifest(
                site=scene.site,
                crop=scene.crop,
                date=scene.date,
                inputs=dict(inputs),
                config=data,
                config_hash=chash,
                code_version=version or code_version(),
                sources=dict(sources or {}),
            )
            if old is not None:
                manifest.created = old.created
                manifest.written = old.written  # the store's files do not change with the config
                manifest.writing = old.writing  # nor do the writes of a run that died
                if old.inputs == manifest.inputs and old.config_hash == chash:
                    manifest.stages = old.stages
            elif recovered is not None:
                manifest.written = recovered
            return manifest

        return self._change_manifest(scene, change)

    def _set_aside_manifest(self, scene: SceneKey, damaged: bytes) -> dict[str, str]:
        """A scene's manifest is there but unreadable (damaged, or written by a newer version):
        keep a copy beside it (``manifest.unreadable-<UTC time>.json``) and return the sha256 of
        every object of the scene now, the ``written`` that its replacement starts from (what
        the lost one would say, unless someone changed the files by hand): without it, cached
        stage records of other settings would be served over files since overwritten."""
        key = manifest_key(scene)
        stamp = _now().strftime("%Y%m%dT%H%M%S%fZ")
        aside = f"{scene.prefix}/manifest.unreadable-{stamp}.json"
        self.put_bytes(aside, damaged)
        log.warning("%s is unreadable: kept as %s, replaced", self.url(key), self.url(aside))
        return self._scene_objects(scene)

    def _scene_objects(self, scene: SceneKey, skip: tuple[str, ...] = ()) -> dict[str, str]:
        """{key: sha256} of every object of ``scene`` but its manifests and the folders in
        ``skip``."""
        passed = tuple(f"{scene.prefix}/{p}" for p in ("manifest", *(f"{s}/" for s in skip)))
        keys = [k for k in self.list(scene.prefix) if not k.startswith(passed)]
        return {k: self.sha256(k) for k in keys}  # the skipped folders are not read

    @contextlib.contextmanager
    def _manifest_lock(self, scene: SceneKey) -> Iterator[None]:
        """Serialise read-modify-write of one manifest: a thread lock always, plus an
        ``flock`` on ``{scene}/.manifest.lock`` on a local store (processes on one machine)."""
        ident = f"{self.root}/{manifest_key(scene)}"
        with _manifest_locks_guard:
            lock = _manifest_locks.setdefault(ident, threading.Lock())
        with lock:
            if not self._local:
                yield
                return
            try:
                import fcntl
            except ImportError:  # pragma: no cover - Windows
                yield
                return
            folder = self._full(scene_prefix(scene))
            os.makedirs(folder, exist_ok=True)
            with open(os.path.join(folder, ".manifest.lock"), "a+b") as fh:
                fcntl.flock(fh.fileno(), fcntl.LOCK_EX)
                try:
                    yield
                finally:
                    fcntl.flock(fh.fileno(), fcntl.LOCK_UN)

    def update_stage(
        self,
        scene: SceneKey,
        stage: str,
        *,
        status: StageStatus | None = None,
        config_hash: str | None = None,
        inputs: Mapping[str, str] | None = None,
        artefacts: Mapping[str, str] | None = None,
        error: str | BaseException | None = None,
        seconds: float | None = None,
        environment: Mapping[str, str] | None = None,
        writing: Mapping[str, str | None] | None = None,
    ) -> Manifest:
        """Read-modify-write one stage record of a scene's manifest, replaced atomically.

        * ``status="running"`` starts a new attempt: ``started`` = now; ``artefacts``,
          ``finished``, ``seconds`` and ``error`` are cleared.
        * ``status="done"`` or ``"failed"`` sets ``finished`` = now and ``seconds`` (from
          ``started`` unless given); ``error`` is redacted and cut to one line; ``done``
          clears an earlier attempt's error.
        * ``writing``: {attempt name: store folder} entries to set in
          :attr:`Manifest.writing` (an attempt about to write there), or to remove (None: the
          attempt is recorded).
        * ``artefacts`` and ``inputs`` are merged into the record; ``config_hash`` replaces it.
        * ``environment`` (the computing process's :func:`environment_versions`) replaces it.

        No update is lost to another writer, in this process or any other (a local store's
        ``flock``, S3's conditional writes: :meth:`_change_manifest`). Returns the new manifest.
        """
        _check_name(stage, "stage")
        if status is not None and status not in STAGE_STATUSES:
            raise ConfigError(
                f"invalid status {status!r} for stage {stage!r}: one of {STAGE_STATUSES}"
            )
        key = manifest_key(scene)

        def change(current: bytes | None) -> Manifest:
            if current is None:
                raise InputError(
                    f"cannot update {self.url(key)}: no such object; the scene's run writes it "
                    "first (init_manifest)"
                )
            manifest = self._parse_manifest(key, current, scene)
            rec = manifest.stages.get(stage) or StageRecord()
            now = _now()
            took = seconds  # per attempt: a retried change starts from the caller's value
            if status == "running":  # a new attempt: forget the previous one
                rec = StageRecord(status="running", started=now)
            elif status in ("done", "failed"):
                rec.status = status
                rec.finished = now
                if status == "done":
                    rec.error = None
                if took is None and rec.started is not None:
                    took = (now - rec.started).total_seconds()
            elif status is not None:
                rec.status = status
            if config_hash is not None:
                rec.config_hash = config_hash
            if inputs:
                rec.inputs.update({_check_key(k): str(v) for k, v in inputs.items()})
            if artefacts:
                rec.artefacts.update({_check_key(k): str(v) for k, v in artefacts.items()})
                manifest.written.update({_check_key(k): str(v) for k, v in artefacts.items()})
            if took is not None:
                rec.seconds = float(took)
            if environment is not None:
                rec.environment = {str(k): str(v) for k, v in environment.items()}
            if error is not None:
                why = error
                if isinstance(error, BaseException):
                    why = f"{type(error).__name__}: {error}"
                rec.error = redact(" ".join(str(why).split()))[:2000]
            manifest.stages[stage] = rec
            for name, folder in (writing or {}).items():
                if folder is None:
                    manifest.writing.pop(name, None)
                else:
                    manifest.writing[name] = _check_key(folder)
            return manifest

        return self._change_manifest(scene, change)

    def note_sources(
        self,
        scene: SceneKey,
        sources: Mapping[str, str | None],
        *,
        inputs: Mapping[str, str],
        config_hash: str,
    ) -> bool:
        """Set the manifest's ``sources`` only where it still holds ``inputs`` and
        ``config_hash`` (checked and written as one change, so a run of other settings that
        starts meanwhile is not stamped with these); True where it was set."""
        key = manifest_key(scene)

        def change(current: bytes | None) -> Manifest | None:
            if current is None:
                return None
            manifest = self._parse_manifest(key, current, scene)
            if manifest.inputs != dict(inputs) or manifest.config_hash != config_hash:
                return None
            if manifest.sources == dict(sources):
                return None
            manifest.sources = dict(sources)
            return manifest

        return self._change_manifest(scene, change) is not None

    def settle_writing(self, scene: SceneKey) -> dict[str, str]:
        """Account for the attempts :attr:`Manifest.writing` still lists (their runs died
        between writing and recording): hash every object in their folders into ``written``
        and clear the entries. Returns {key: sha256} of the objects whose hash changed there.
        Call it holding the scene's lease, before any cached record is judged; a scene without
        a manifest has nothing to settle."""
        key = manifest_key(scene)
        try:
            pending = dict(self.load_manifest(scene).writing)
        except InputError:
            return {}
        if not pending:
            return {}
        folders = sorted(set(pending.values()))
        found = {k: h for folder in folders for k, h in self.hashes(folder).items()}
        changed: dict[str, str] = {}

        def change(current: bytes | None) -> Manifest:
            if current is None:
                raise InputError(f"cannot update {self.url(key)}: no such object")
            manifest = self._parse_manifest(key, current, scene)
            changed.clear()
            changed.update({k: h for k, h in found.items() if manifest.written.get(k) != h})
            manifest.written.update(changed)
            for name, folder in pending.items():
                if manifest.writing.get(name) == folder:
                    del manifest.writing[name]
            return manifest

        self._change_manifest(scene, change)
        return dict(changed)

    def stage_is_current(
        self,
        scene: SceneKey,
        stage: str,
        *,
        config_hash: str | None = None,
        inputs: Mapping[str, str] | None = None,
        verify: bool = False,
    ) -> bool:
        """True if ``stage`` is done with this config hash and these upstream hashes, and its
        artefacts exist (with ``verify=True``: and still hash to what the manifest records).

        A rerun uses this to skip a stage; anything missing or different means run it again.
        """
        try:
            rec = self.load_manifest(scene).stages.get(stage)
        except InputError:
            return False
        if rec is None or rec.status != "done":
            return False
        if config_hash is not None and rec.config_hash != config_hash:
            return False
        if inputs is not None and dict(inputs) != rec.inputs:
            return False
        for key, digest in rec.artefacts.items():
            if not self.isfile(key):
                return False
            if verify and self.sha256(key) != digest:
                return False
        return True

    # ---- season helpers ---------------------------------------------------------------------

    def list_dates(self, site: str, crop: str, *, with_runs: bool = False) -> list[str]:
        """Sorted ISO dates of ``site``/``crop`` that have at least one object in ``images/``
        (their inbox), and with ``with_runs`` also those with a run manifest (a scene run from
        photos kept elsewhere, ``cropcraft run --images URI``)."""
        _check_name(site, "site")
        if crop not in CROPS:
            raise ConfigError(f"unknown crop {crop!r}: choose one of {', '.join(sorted(CROPS))}")
        prefix = f"{site}/{crop}"
        dates = []
        for name in self._children(prefix, folders=True):
            if not _is_date(name):
                continue
            if self._children(f"{prefix}/{name}/{IMAGES_STAGE}") or (
                with_runs and self.isfile(f"{prefix}/{name}/{MANIFEST_NAME}")
            ):
                dates.append(name)
        return dates

    def _photos_below(self, prefix: str) -> str | None:
        """The folder (relative to ``prefix``, "" for itself) of the first photo at most
        :data:`PHOTO_SEARCH_DEPTH` levels below ``prefix``, hidden files and folders left out;
        None where there is none."""
        from cropcraft_core.sfm.ingest import is_visible_photo

        full = self._full(prefix)
        self._invalidate(full)
        with self._io("list", prefix, reading=True):
            try:
                paths = self.fs.find(full, maxdepth=PHOTO_SEARCH_DEPTH)
            except (FileNotFoundError, NotADirectoryError):
                return None
        found = []
        for path in paths:
            rel = self._rel(path)
            if rel is None or not rel.startswith(prefix + "/"):
                continue
            inner = rel[len(prefix) + 1 :]
            if is_visible_photo(inner):
                found.append(inner.rpartition("/")[0])
        return min(found, key=lambda f: (f.count("/"), f)) if found else None

    def misnamed_dates(self, site: str, crop: str) -> list[str]:
        """Folders of ``site``/``crop`` holding photos (in an ``images/`` inbox, or anywhere
        :data:`PHOTO_SEARCH_DEPTH` levels down: ``20240707/*.jpg``) whose names are not ISO dates
        (``2024-7-02``, ``20240703``, ``2024-02-30``): the season cannot run them, and says so
        rather than skip them unseen. The season summary's own folder is none of them."""
        prefix = f"{site}/{crop}"
        return [
            name
            for name in self._children(prefix, folders=True)
            if not _is_date(name)
            and name != SEASON_FOLDER
            and (
                self._children(f"{prefix}/{name}/{IMAGES_STAGE}")
                or self._photos_below(f"{prefix}/{name}") is not None
            )
        ]

    def photos_out_of_place(self, site: str, crop: str) -> list[str]:
        """Where a dated folder of ``site``/``crop`` holds photos outside its ``images/``
        inbox, and has no inbox (nor a run from elsewhere): the date (its photos in the date's
        folder itself) or the folder below it that holds them (``2024-07-14/Images``,
        ``2024-07-10/DCIM/100MEDIA``: an inbox in another case, or a camera card copied whole).
        The season cannot see them as a scene, and says so rather than skip them unseen."""
        prefix = f"{site}/{crop}"
        out = []
        for name in self._children(prefix, folders=True):
            if not _is_date(name) or self._children(f"{prefix}/{name}/{IMAGES_STAGE}"):
                continue
            if self.isfile(f"{prefix}/{name}/{MANIFEST_NAME}"):
                continue
            where = self._photos_below(f"{prefix}/{name}")
            if where is not None:
                out.append(f"{name}/{where}" if where else name)
        return out

    def sites_like(self, site: str) -> list[str]:
        """Sites in the store spelled as ``site`` up to case (``PlotA`` for ``plota``), itself
        left out: a season of a mistyped site found nothing, said only "is it the store?"."""
        return [
            n for n in self._children("", folders=True) if n.lower() == site.lower() and n != site
        ]

    def discover(self, site: str, crop: str, *, with_runs: bool = False) -> list[DiscoveredScene]:
        """Every dated scene of ``site``/``crop`` with images (and with ``with_runs`` every one
        with a run manifest, see :meth:`list_dates`), with its stage statuses."""
        found = []
        for date in self.list_dates(site, crop, with_runs=with_runs):
            scene = SceneKey(site, crop, date)
            n_images = len(self.list(stage_prefix(scene, IMAGES_STAGE)))
            try:
                manifest = self.load_manifest(scene)
            except InputError:
                found.append(DiscoveredScene(scene, n_images, False, {}))
                continue
            stages = {name: rec.status for name, rec in sorted(manifest.stages.items())}
            found.append(
                DiscoveredScene(
                    scene, n_images, True, stages, dict(manifest.inputs), dict(manifest.sources)
                )
            )
        return found
