"""Camera poses: structure from motion with pycolmap, and COLMAP / nerfstudio import and export.

Every pose in CropCraft is a ``PinholeCamera`` (OpenCV axes: x right, y down, z forward; pixel
centres at +0.5, the same convention as COLMAP; ``cam_to_world`` (4, 4)). A ``Poses`` record is the
ordered list of ``(image name, PinholeCamera)``; lens distortion, where an importer or SfM found
any, is kept beside it in ``Poses.distortion`` (the pinhole part is in the camera; the lens as
:func:`cropcraft_core.geometry.lens.lens` records it, which later stages undistort the photos by).

Conventions of the file formats handled here:

* COLMAP text model (``cameras.txt``, ``images.txt``, ``points3D.txt``): ``images.txt`` holds the
  world-to-camera rotation as a unit quaternion ``QW QX QY QZ`` (Hamilton, scalar first) and the
  world-to-camera translation ``TX TY TZ``; camera axes are OpenCV's.
* nerfstudio ``transforms.json``: ``frames[].transform_matrix`` is camera-to-world with OpenGL
  camera axes (x right, y up, z back), i.e. ``c2w_gl = c2w_cv @ diag(1, -1, -1, 1)``; intrinsics
  ``fl_x, fl_y, cx, cy, w, h`` at the top level or per frame, distortion ``k1 k2 k3 k4 p1 p2``
  of ``camera_model`` OPENCV or OPENCV_FISHEYE.

``run_sfm`` runs pycolmap on the CPU: SIFT features, exhaustive matching for up to
``EXHAUSTIVE_MAX_IMAGES`` images (beyond: sequential matching with a quadratic overlap first,
completed by exhaustive matching when too few images register), incremental mapping, and keeps
the model with the most registered images. Poses from SfM are in SfM's own
arbitrary similarity frame; ``umeyama`` aligns them to a metric frame.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from typing import Any

import numpy as np

from cropcraft_core.errors import CropCraftError, InputError, OutputError
from cropcraft_core.geometry.camera import PinholeCamera
from cropcraft_core.geometry.lens import (
    COLMAP_MODELS,
    FISHEYE,
    NERFSTUDIO_MODELS,
    RADIAL_TANGENTIAL,
    lens,
)
from cropcraft_core.sfm.ingest import IMAGE_EXTENSIONS  # what ingest writes and run_sfm reads

#: Up to this many images ``matcher='auto'`` matches every pair; beyond, sequential matching
#: first, then the pairs that close the order's loop (``loop_pairs``), completed by exhaustive
#: matching when those register too few images.
EXHAUSTIVE_MAX_IMAGES = 20
#: Fewer registered images than this fraction make ``run_sfm`` fail.
MIN_REGISTERED_FRACTION = 0.5

_GL_FROM_CV = np.diag([1.0, -1.0, -1.0, 1.0])  # flips camera y and z (its own inverse)


class SfmError(CropCraftError, RuntimeError):
    """Structure from motion failed: no model, or too few images registered."""


# --------------------------------------------------------------------------- records


@dataclass(frozen=True, eq=False)
class Poses:
    """An ordered list of ``(image name, PinholeCamera)``, metres where the frame is metric.

    ``distortion`` maps an image name to its lens (``{"model": "radial_tangential", "k1": ...}``,
    :func:`cropcraft_core.geometry.lens.lens`); images without distortion are absent from it.
    """

    views: tuple[tuple[str, PinholeCamera], ...]
    distortion: dict[str, dict[str, Any]] = field(default_factory=dict)

    def __post_init__(self) -> None:
        views = tuple((str(n), c) for n, c in self.views)
        names = [n for n, _ in views]
        if len(set(names)) != len(names):
            dup = sorted({n for n in names if names.count(n) > 1})
            raise InputError(f"poses name the same image more than once: {', '.join(dup[:5])}")
        for n, c in views:
            if not isinstance(c, PinholeCamera):
                raise InputError(f"pose of {n!r} is not a PinholeCamera")
        object.__setattr__(self, "views", views)

    def __len__(self) -> int:
        return len(self.views)

    def __iter__(self) -> Iterator[tuple[str, PinholeCamera]]:
        return iter(self.views)

    @property
    def names(self) -> list[str]:
        return [n for n, _ in self.views]

    @property
    def cameras(self) -> list[PinholeCamera]:
        return [c for _, c in self.views]

    def camera(self, name: str) -> PinholeCamera:
        for n, c in self.views:
            if n == name:
                return c
        raise InputError(f"no pose for image {name!r}")

    def centers(self) -> np.ndarray:
        """(n, 3) float64 camera centres in the poses' world frame."""
        return np.array([c.center for _, c in self.views]).reshape(-1, 3)

    def transformed(self, scale: float, rotation: np.ndarray, translation: np.ndarray) -> Poses:
        """The poses moved by the similarity x ↦ scale · R x + t (e.g. from ``umeyama``): camera
        centres map like points, orientations rotate by R, intrinsics stay."""
        r = np.asarray(rotation, float)
        t = np.asarray(translation, float)
        out = []
        for n, c in self.views:
            m = np.eye(4)
            m[:3, :3] = r @ c.cam_to_world[:3, :3]
            m[:3, 3] = scale * r @ c.cam_to_world[:3, 3] + t
            out.append((n, PinholeCamera(c.width, c.height, c.fx, c.fy, c.cx, c.cy, m)))
        return Poses(tuple(out), dict(self.distortion))

    def to_dict(self) -> dict:
        return {
            "views": [{"name": n, "camera": c.to_dict()} for n, c in self.views],
            "distortion": self.distortion,
        }

    @classmethod
    def from_dict(cls, d: dict) -> Poses:
        try:
            views = tuple((v["name"], PinholeCamera.from_dict(v["camera"])) for v in d["views"])
        except (KeyError, TypeError) as e:
            raise InputError(f"poses record is malformed: {e}") from None
        return cls(views, dict(d.get("distortion", {})))


@dataclass(frozen=True, eq=False)
class SfmResult:
    """What ``run_sfm`` found.

    poses: registered images only, in SfM's arbitrary similarity frame.
    registered_fraction: registered / input images.  mean_reprojection_error_px: over all
    observations of the kept model.  points: (n, 3) float64 sparse points (same frame).
    colors: (n, 3) uint8 their RGB colours.  unregistered: names of images left out.
    camera_model / camera_params: the COLMAP camera of the first registered image (distortion is
    also in ``poses.distortion``).  seconds: wall time per stage.  model_dir: the kept model as a
    COLMAP text model.  matcher: the matching passes run, ``+``-joined in order ("exhaustive",
    "sequential", "sequential+loop", "sequential+loop+unplaced", "sequential+exhaustive",
    ...).  focal_priors: the focal length (px) each image's camera started from, for those
    that had a prior.
    """

    poses: Poses
    registered_fraction: float
    mean_reprojection_error_px: float
    points: np.ndarray
    colors: np.ndarray
    n_images: int
    unregistered: list[str]
    matcher: str
    camera_model: str
    camera_params: list[float]
    seconds: dict[str, float]
    model_dir: Path | None = None
    focal_priors: dict[str, float] = field(default_factory=dict)

    @property
    def n_registered(self) -> int:
        return len(self.poses)

    def summary(self) -> dict:
        """JSON-ready figures (no arrays)."""
        return {
            "n_images": self.n_images,
            "n_registered": self.n_registered,
            "registered_fraction": self.registered_fraction,
            "mean_reprojection_error_px": self.mean_reprojection_error_px,
            "n_points": int(len(self.points)),
            "unregistered": list(self.unregistered),
            "matcher": self.matcher,
            "camera_model": self.camera_model,
            "camera_params": list(self.camera_params),
            "seconds": dict(self.seconds),
            "model_dir": None if self.model_dir is None else str(self.model_dir),
            "focal_prior_px": sorted({round(f, 2) for f in self.focal_priors.values()}),
            "n_focal_prior": len(self.focal_priors),
        }


# --------------------------------------------------------------------------- rotations


def rotation_to_quaternion(r: np.ndarray) -> np.ndarray:
    """(3, 3) rotation matrix → (4,) unit quaternion (w, x, y, z), w ≥ 0 (Shepperd's method)."""
    r = np.asarray(r, dtype=np.float64)
    tr = r[0, 0] + r[1, 1] + r[2, 2]
    if tr > 0:
        s = 2.0 * math.sqrt(1.0 + tr)
        q = [0.25 * s, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s]
    elif r[0, 0] > r[1, 1] and r[0, 0] > r[2, 2]:
        s = 2.0 * math.sqrt(1.0 + r[0, 0] - r[1, 1] - r[2, 2])
        q = [(r[2, 1] - r[1, 2]) / s, 0.25 * s, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s]
    elif r[1, 1] > r[2, 2]:
        s = 2.0 * math.sqrt(1.0 + r[1, 1] - r[0, 0] - r[2, 2])
        q = [(r[0, 2] - r[2, 0]) / s, (r[0, 1] + r[1, 0]) / s, 0.25 * s, (r[1, 2] + r[2, 1]) / s]
    else:
        s = 2.0 * math.sqrt(1.0 + r[2, 2] - r[0, 0] - r[1, 1])
        q = [(r[1, 0] - r[0, 1]) / s, (r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, 0.25 * s]
    q = np.array(q)
    q /= np.linalg.norm(q)
    return -q if q[0] < 0 else q


def quaternion_to_rotation(q: Sequence[float]) -> np.ndarray:
    """(4,) quaternion (w, x, y, z), normalised here → (3, 3) rotation matrix."""
    w, x, y, z = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def _rigid(r: np.ndarray, t: np.ndarray) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = r
    m[:3, 3] = t
    return m


def _invert_rigid(m: np.ndarray) -> np.ndarray:
    r, t = m[:3, :3], m[:3, 3]
    return _rigid(r.T, -r.T @ t)


def umeyama(
    src: np.ndarray, dst: np.ndarray, with_scale: bool = True
) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares similarity dst ≈ s · R @ src + t (Umeyama 1991).

    src, dst: (n, 3) corresponding points, n ≥ 3 not collinear.
    Returns (s, R (3, 3) proper rotation, t (3,)).
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3 or len(src) < 3:
        raise InputError(f"umeyama needs two (n ≥ 3, 3) arrays, got {src.shape} and {dst.shape}")
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    cov = xd.T @ xs / len(src)
    u, d, vt = np.linalg.svd(cov)
    sgn = np.ones(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        sgn[2] = -1.0
    r = u @ np.diag(sgn) @ vt
    var_s = (xs**2).sum() / len(src)
    if var_s <= 0:
        raise InputError("umeyama: source points are all identical")
    s = float((d * sgn).sum() / var_s) if with_scale else 1.0
    t = mu_d - s * r @ mu_s
    return s, r, t


# --------------------------------------------------------------------------- COLMAP text


def _fmt(x: float) -> str:
    return repr(float(x))


def _camera_key(c: PinholeCamera) -> tuple:
    return (c.width, c.height, c.fx, c.fy, c.cx, c.cy)


def export_colmap_text(
    poses: Poses,
    out_dir: str | os.PathLike,
    points: np.ndarray | None = None,
    colors: np.ndarray | None = None,
) -> Path:
    """Write ``poses`` as a COLMAP text model (PINHOLE cameras, one per distinct intrinsics) in
    ``out_dir``: cameras.txt, images.txt (no 2D points), points3D.txt (``points`` (n, 3) with
    ``colors`` (n, 3) uint8, empty tracks; or empty). Floats are written with full precision, so a
    round trip is exact. Distortion is not written (PINHOLE). Returns ``out_dir``."""
    out = Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise OutputError(f"cannot create COLMAP model folder {out}: {e}") from None
    cam_ids: dict[tuple, int] = {}
    for _, c in poses:
        cam_ids.setdefault(_camera_key(c), len(cam_ids) + 1)
    lines = [
        "# Camera list with one line of data per camera:",
        "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]",
        f"# Number of cameras: {len(cam_ids)}",
    ]
    for (w, h, fx, fy, cx, cy), i in cam_ids.items():
        lines.append(f"{i} PINHOLE {w} {h} {_fmt(fx)} {_fmt(fy)} {_fmt(cx)} {_fmt(cy)}")
    _write_text(out / "cameras.txt", "\n".join(lines) + "\n")
    lines = [
        "# Image list with two lines of data per image:",
        "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
        "#   POINTS2D[] as (X, Y, POINT3D_ID)",
        f"# Number of images: {len(poses)}, mean observations per image: 0",
    ]
    for i, (name, c) in enumerate(poses, start=1):
        if any(ch.isspace() for ch in name):
            raise OutputError(f"COLMAP image names cannot hold white space: {name!r}")
        w2c = c.world_to_cam
        q = rotation_to_quaternion(w2c[:3, :3])
        t = w2c[:3, 3]
        vals = " ".join(_fmt(v) for v in (*q, *t))
        lines.append(f"{i} {vals} {cam_ids[_camera_key(c)]} {name}")
        lines.append("")
    _write_text(out / "images.txt", "\n".join(lines) + "\n")
    lines = [
        "# 3D point list with one line of data per point:",
        "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)",
    ]
    if points is not None and len(points):
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        col = (
            np.full((len(p), 3), 128, np.uint8)
            if colors is None
            else np.asarray(colors).reshape(-1, 3).astype(np.uint8)
        )
        lines.append(f"# Number of points: {len(p)}, mean track length: 0")
        for i, (x, rgb) in enumerate(zip(p, col, strict=True), start=1):
            lines.append(f"{i} {_fmt(x[0])} {_fmt(x[1])} {_fmt(x[2])} {rgb[0]} {rgb[1]} {rgb[2]} 0")
    else:
        lines.append("# Number of points: 0, mean track length: 0")
    _write_text(out / "points3D.txt", "\n".join(lines) + "\n")
    return out


def _write_text(path: Path, text: str) -> None:
    tmp = path.with_name(path.name + ".tmp")
    try:
        tmp.write_text(text, encoding="utf-8")
        os.replace(tmp, path)
    except OSError as e:
        raise OutputError(f"cannot write {path}: {e}") from None


def _camera_from_colmap(cam, cam_to_world: np.ndarray) -> tuple[PinholeCamera, dict[str, float]]:
    """pycolmap camera → (PinholeCamera, distortion coefficients by name, empty if none)."""
    pc = PinholeCamera(
        int(cam.width),
        int(cam.height),
        float(cam.focal_length_x),
        float(cam.focal_length_y),
        float(cam.principal_point_x),
        float(cam.principal_point_y),
        cam_to_world,
    )
    model = str(cam.model.name)
    if model not in COLMAP_MODELS:
        raise InputError(
            f"COLMAP camera model {model} is not supported (its lens: one of "
            f"{', '.join(COLMAP_MODELS)}); undistort the photos first (colmap image_undistorter)"
        )
    params = [float(v) for v in cam.params]
    named = set(cam.focal_length_idxs()) | set(cam.principal_point_idxs())
    extra = [i for i in range(len(params)) if i not in named]
    info = cam.params_info.split(", ") if cam.params_info else []
    dist = {info[i] if i < len(info) else f"p{i}": params[i] for i in extra}
    return pc, lens(COLMAP_MODELS[model], dist, f"COLMAP camera {cam.camera_id} ({model})")


def _poses_from_reconstruction(rec) -> Poses:
    views, dist = [], {}
    for image_id in sorted(rec.reg_image_ids()):
        im = rec.image(image_id)
        w2c = np.eye(4)
        w2c[:3, :] = im.cam_from_world().matrix()
        cam, d = _camera_from_colmap(rec.camera(im.camera_id), _invert_rigid(w2c))
        views.append((im.name, cam))
        if d:
            dist[im.name] = d
    views.sort(key=lambda v: v[0])
    return Poses(tuple(views), dist)


def _read_colmap(model_dir: str | os.PathLike) -> tuple[Poses, np.ndarray]:
    """(poses of the registered images, (n, 3) points3D) of a COLMAP model folder."""
    import pycolmap

    d = Path(model_dir)
    found = [p for p in ("cameras.txt", "cameras.bin") if (d / p).is_file()]
    if not found:
        raise InputError(f"{d} holds no COLMAP model (cameras.txt or cameras.bin)")
    try:
        rec = pycolmap.Reconstruction(str(d))
    except Exception as e:  # pycolmap raises ValueError/RuntimeError with its own text
        raise InputError(f"cannot read the COLMAP model in {d}: {e}") from None
    poses = _poses_from_reconstruction(rec)
    if not len(poses):
        raise InputError(f"the COLMAP model in {d} has no registered images")
    ids = list(rec.point3D_ids())
    pts = np.array([rec.point3D(i).xyz for i in ids], dtype=np.float64).reshape(-1, 3)
    return poses, pts


def import_colmap(model_dir: str | os.PathLike) -> Poses:
    """Read a COLMAP model (text or binary: cameras, images, points3D) → ``Poses`` of its
    registered images, sorted by name. Lens distortion goes to ``Poses.distortion``; the
    points are :func:`import_poses`'."""
    return _read_colmap(model_dir)[0]


@dataclass(frozen=True)
class ImportedPoses:
    """Poses another tool made, with what their source says of their frame."""

    poses: Poses
    points: np.ndarray | None
    """(n, 3) sparse points in the poses' frame (a COLMAP model's points3D, a transforms.json's
    ``ply_file_path``), or None."""
    from_sfm: bool
    """Made by structure from motion, so of arbitrary scale and orientation: a COLMAP model, or
    a ``transforms.json`` with ``applied_transform`` (nerfstudio's ``ns-process-data`` writes
    it for COLMAP and Metashape projects) or, from releases before that field, COLMAP's
    ``colmap_im_id`` on its frames (:func:`transforms_from_sfm`). False for any other
    ``transforms.json``: a phone's AR tracking (``ns-process-data polycam`` / ``record3d``,
    ``cropcraft synth``), metres and gravity-aligned."""


def import_poses(path: str | os.PathLike) -> ImportedPoses:
    """Poses from a COLMAP model folder (or a project folder with ``sparse/0``) or a nerfstudio
    ``transforms.json`` (:func:`import_colmap`, :func:`import_transforms_json`), with the sparse
    points where the source has them: a COLMAP model's points3D, or the PLY a
    ``transforms.json`` names in ``ply_file_path`` (``ns-process-data`` writes
    ``sparse_pc.ply`` beside it), when it is there."""
    p = Path(path)
    if p.is_dir():

        def model_in(*folders: Path) -> Path | None:
            return next(
                (d for d in folders for f in ("cameras.txt", "cameras.bin") if (d / f).is_file()),
                None,
            )

        # a COLMAP project (as before), else an ns-process-data output folder (its
        # transforms.json, as nerfstudio reads it, then the COLMAP model it keeps)
        model = model_in(p / "sparse" / "0", p)
        if model is None and (p / "transforms.json").is_file():
            p = p / "transforms.json"
        else:
            model = model or model_in(p / "colmap" / "sparse" / "0")
            if model is None:
                raise InputError(
                    f"{p} holds no COLMAP model (cameras.txt or cameras.bin, in it, in "
                    "sparse/0 or in colmap/sparse/0) and no transforms.json"
                )
            poses, pts = _read_colmap(model)
            return ImportedPoses(poses, pts if len(pts) else None, True)
    doc = _transforms_doc(p)
    points = None
    rel = transforms_ply(doc)
    given = doc.get("ply_file_path") if isinstance(doc, dict) else None
    if rel is None and isinstance(given, str) and Path(given).is_absolute():
        rel = given  # an absolute path, as nerfstudio reads it, where it is on this host
    if rel is not None and (p.parent / rel).is_file():
        from cropcraft_core.export.meshio import PointCloud, read_geometry

        geom = read_geometry(p.parent / rel)  # a point cloud, or a mesh's vertices
        pts = geom.points if isinstance(geom, PointCloud) else geom.vertices
        points = np.asarray(pts, np.float64).reshape(-1, 3) if len(pts) else None
    return ImportedPoses(_transforms_poses(doc, p), points, transforms_from_sfm(doc))


def transforms_from_sfm(doc: dict) -> bool:
    """Whether a ``transforms.json`` holds SfM poses (any scale and orientation) rather than a
    phone's metric AR tracking: ``ns-process-data`` writes ``applied_transform`` for COLMAP and
    Metashape projects, and releases before it wrote that field still gave every COLMAP frame
    its ``colmap_im_id`` (which Polycam's and Record3D's frames never carry); instant-ngp's
    ``colmap2nerf.py`` gives every frame its ``sharpness`` (and scales the poses to "NeRF
    size", 4 / the cameras' mean distance from the point they look at: read as metres, a
    walk's cameras stood 2x too high)."""
    if "applied_transform" in doc:
        return True
    marks = ("colmap_im_id", "sharpness")
    return any(isinstance(f, dict) and any(m in f for m in marks) for f in doc.get("frames") or ())


def transforms_ply(doc: dict) -> str | None:
    """The sparse-point PLY a ``transforms.json`` names (``ply_file_path``), relative to its
    folder; None where it names none, or a path outside that folder."""
    rel = doc.get("ply_file_path") if isinstance(doc, dict) else None
    if not isinstance(rel, str) or not rel.strip():
        return None
    parts = PurePosixPath(rel.replace("\\", "/")).parts
    if not parts or parts[0] == "/" or ".." in parts:
        return None
    return "/".join(x for x in parts if x != ".")


# --------------------------------------------------------------------------- nerfstudio

_NS_DISTORTION = ("k1", "k2", "k3", "k4", "p1", "p2")


def export_transforms_json(
    poses: Poses,
    path: str | os.PathLike,
    image_prefix: str = "images/",
    extra: dict | None = None,
) -> Path:
    """Write ``poses`` as a nerfstudio ``transforms.json`` (camera_model OPENCV, zero distortion
    unless ``poses.distortion`` has it). Intrinsics shared by every view go to the top level,
    otherwise into each frame. ``file_path`` = ``image_prefix + name``. ``extra`` keys are added at
    the top level (nerfstudio ignores unknown keys). Returns the path."""
    if not len(poses):
        raise OutputError("no poses to write")
    keys = {_camera_key(c) for _, c in poses}
    shared = len(keys) == 1 and not poses.distortion

    def intr(c: PinholeCamera, name: str | None) -> dict:
        d = {"fl_x": c.fx, "fl_y": c.fy, "cx": c.cx, "cy": c.cy, "w": c.width, "h": c.height}
        dist = poses.distortion.get(name, {}) if name else {}
        d.update({k: float(dist.get(k, 0.0)) for k in _NS_DISTORTION})  # SfM's k is k1
        return d

    models = {d.get("model") for d in poses.distortion.values() if d}
    if (
        len(models) > 1
        or any(d.get(k) for d in poses.distortion.values() for k in ("k4", "k5", "k6") if d)
        and models == {RADIAL_TANGENTIAL}
    ):
        raise OutputError(
            "these poses' lenses (mixed models, or rational radial-tangential terms k4-k6) "
            "cannot be written as one nerfstudio camera_model"
        )
    doc: dict = {"camera_model": "OPENCV_FISHEYE" if models == {FISHEYE} else "OPENCV"}
    if shared:
        doc.update(intr(poses.cameras[0], None))
    frames = []
    for name, c in poses:
        f = {"file_path": f"{image_prefix}{name}"}
        if not shared:
            f.update(intr(c, name))
        f["transform_matrix"] = (c.cam_to_world @ _GL_FROM_CV).tolist()
        frames.append(f)
    doc["frames"] = frames
    if extra:
        doc.update(extra)
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    _write_text(p, json.dumps(doc, indent=2))
    return p


def import_transforms_json(path: str | os.PathLike) -> Poses:
    """Read a nerfstudio ``transforms.json`` → ``Poses`` in OpenCV camera axes, named by the
    base name of each frame's ``file_path``. Intrinsics per frame override the top level's;
    ``camera_angle_x`` stands in for ``fl_x`` where that is missing. Non-zero distortion
    coefficients go to ``Poses.distortion``."""
    p = Path(path)
    return _transforms_poses(_transforms_doc(p), p)


def _transforms_doc(p: Path) -> dict:
    try:
        doc = json.loads(p.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise InputError(f"cannot read {p}: {e}") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("frames"), list) or not doc["frames"]:
        raise InputError(f"{p} has no frames")
    return doc


def _transforms_poses(doc: dict, p: Path) -> Poses:
    views, dist = [], {}
    for i, f in enumerate(doc["frames"]):
        where = f"{p} frame {i}"
        if not isinstance(f, dict):
            raise InputError(f"{where} is not a mapping of file_path, transform_matrix, ...")
        g = {**doc, **f}
        try:
            w, h = int(g["w"]), int(g["h"])
            if "fl_x" in g:
                fx = float(g["fl_x"])
            else:
                fx = 0.5 * w / math.tan(0.5 * float(g["camera_angle_x"]))
            fy = float(g.get("fl_y", fx))
            cx, cy = float(g.get("cx", w / 2)), float(g.get("cy", h / 2))
            m = np.asarray(f["transform_matrix"], dtype=np.float64)
            name = PurePosixPath(str(f["file_path"]).replace("\\", "/")).name  # Windows too
        except (KeyError, TypeError, ValueError) as e:
            raise InputError(f"{where} is missing or has a malformed {e}") from None
        if not all(math.isfinite(x) for x in (fx, fy, cx, cy)):
            raise InputError(f"{where}: intrinsics must be finite numbers")
        model = g.get("camera_model", "OPENCV")
        if model not in NERFSTUDIO_MODELS:
            raise InputError(
                f"{where}: camera_model {model!r} is not supported "
                f"({', '.join(NERFSTUDIO_MODELS)}); undistort the photos first"
            )
        coeffs = {k: g[k] for k in _NS_DISTORTION if g.get(k) is not None}
        if NERFSTUDIO_MODELS[model] == RADIAL_TANGENTIAL and coeffs.get("k4"):
            raise InputError(
                f"{where}: {model} distortion k4={coeffs['k4']} is read as a polynomial term by "
                "nerfstudio's rays and as OpenCV's rational one by its undistortion; give "
                "undistorted photos or a COLMAP model"
            )
        d = lens(NERFSTUDIO_MODELS[model], coeffs, where)
        if m.shape == (3, 4):
            m = np.vstack([m, [0, 0, 0, 1.0]])
        if m.shape != (4, 4):
            raise InputError(f"{where}: transform_matrix must be 4×4, got {m.shape}")
        try:
            views.append((name, PinholeCamera(w, h, fx, fy, cx, cy, m @ _GL_FROM_CV)))
        except (CropCraftError, ValueError) as e:
            raise InputError(f"{where}: {e}") from None
        if d:
            dist[name] = d
    return Poses(tuple(views), dist)


# --------------------------------------------------------------------------- photos


def pinhole_photos(
    image_dir: str | os.PathLike, poses: Poses, indices: Sequence[int] | None = None
) -> list[np.ndarray]:
    """The posed photos in ``image_dir`` (all, or those at ``indices`` of ``poses``), RGB uint8,
    each undistorted into its pinhole camera (:func:`cropcraft_core.geometry.lens.
    undistort_image`) where ``poses.distortion`` has its lens."""
    from PIL import Image

    from cropcraft_core.geometry.lens import stored_lens, undistort_image

    folder = Path(image_dir)
    views = poses.views
    out = []
    for i in range(len(views)) if indices is None else indices:
        name, cam = views[i]
        with Image.open(folder / name) as im:
            rgb = np.asarray(im.convert("RGB"))
        try:
            out.append(undistort_image(rgb, cam, stored_lens(poses.distortion.get(name), name)))
        except InputError as e:
            raise InputError(f"photo {name}: {e}") from None
    return out


# --------------------------------------------------------------------------- SfM


def list_images(image_dir: str | os.PathLike) -> list[str]:
    """Sorted names of the JPEG/PNG files directly in ``image_dir``."""
    d = Path(image_dir)
    if not d.is_dir():
        raise InputError(f"image folder {d} does not exist")
    return sorted(
        p.name
        for p in d.iterdir()
        if p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS and not p.name.startswith(".")
    )


def _image_size(path: Path) -> tuple[int, int]:
    from PIL import Image

    try:
        with Image.open(path) as im:
            return im.size
    except OSError as e:
        raise InputError(f"cannot read image {path.name}: {e}") from None


def choose_matcher(n_images: int, matcher: str = "auto") -> str:
    """'exhaustive', 'sequential' or 'auto': ``auto`` matches every pair up to
    ``EXHAUSTIVE_MAX_IMAGES`` images (cheap), beyond that each image with its neighbours in name
    order first, then the last images with the first (``loop_pairs``), and every other pair only
    if those register too few images (``run_sfm``)."""
    if matcher not in ("auto", "exhaustive", "sequential"):
        raise InputError(f"unknown matcher {matcher!r}: choose auto, exhaustive or sequential")
    if matcher != "auto":
        return matcher
    return "exhaustive" if n_images <= EXHAUSTIVE_MAX_IMAGES else "auto"


#: SIFT's peak (contrast) threshold: a third of COLMAP's default (0.02 / 3 octave layers).
#: Canopies are low-contrast, repetitive texture; on a synthetic soybean canopy of LAI 2.3 (50
#: photos, 640 × 480) COLMAP's default registered 35 of 50 images even after exhaustive matching
#: (989 points; a mapper accepting 8 inliers: 39), this threshold all 50 from sequential matching
#: alone (3,582 points).
SIFT_PEAK_THRESHOLD = 0.02 / 9


def completion_pairs(n: int, outside: list[int]) -> list[tuple[int, int]] | None:
    """The pairs that match each of ``outside`` (indices of images outside the largest model)
    with every other of ``n`` images, each pair once; None where they would be more than half
    of all pairs (then every pair is matched: the order told little)."""
    out = {(min(a, b), max(a, b)) for a in outside for b in range(n) if b != a}
    if 2 * len(out) > n * (n - 1) // 2:
        return None
    return sorted(out)


def _verified_pairs(db: Path, min_inliers: int) -> set[tuple[str, str]]:
    """The image pairs (names) of a COLMAP database with at least ``min_inliers`` verified
    inlier matches."""
    import pycolmap

    base = pycolmap.Database.open(str(db))
    try:
        name = {im.image_id: im.name for im in base.read_all_images()}
        pair_ids, inliers = base.read_two_view_geometry_num_inliers()
    finally:
        base.close()
    out = set()
    for pid, k in zip(pair_ids, inliers, strict=True):
        if k >= min_inliers:
            a, b = pycolmap.pair_id_to_image_pair(pid)
            out.add((name[a], name[b]))
    return out


def loop_pairs(n: int, overlap: int) -> list[tuple[int, int]]:
    """The pairs that close a loop of ``n`` images in name order: sequential matching's pairs
    (each image with the next ``overlap`` and those ``2**k`` on, COLMAP's quadratic overlap)
    taken round the end of the order, the last images with the first: only steps that pass
    the end. Where such a pair's distance without the wrap is itself a step (``n - d`` in the
    steps, e.g. 16 of 32 images) the sequential pass already made it, and COLMAP's matcher
    skips pairs its database holds. Empty for fewer than ``2 * overlap + 2`` images, where the
    sequential pass's pairs already reach round."""
    if n < 2 * overlap + 2:
        return []
    steps = sorted(set(range(1, overlap + 1)) | {2**k for k in range(overlap) if 2**k < n})
    out = set()
    for a in range(n):
        for d in steps:
            if a + d >= n:  # d < n: b is another image, before a
                out.add(((a + d) % n, a))
    return sorted(out)


#: Photos of one size whose EXIF focal lengths differ by more than this factor were taken
#: through different lenses (a phone's main and telephoto cameras, two phones): one camera
#: each. Within it, one lens (a phone's own focal length written with jitter, a zoom nudged).
LENS_RATIO = 1.1


def _by_lens(group: list[str], focal_priors: dict[str, float] | None) -> list[list[str]]:
    """``group`` (photos of one size) split by lens: runs of their known focal lengths, sorted,
    each step within :data:`LENS_RATIO`. Two phones of the same resolution shared one camera
    that started at the median of both lenses, 25 % off each (session 92's photos audit).
    Photos without a known focal length join the lens where there is one, else form their own
    group (no prior)."""
    known = sorted(
        (float(focal_priors[n]), n) for n in group if focal_priors and focal_priors.get(n)
    )
    if not known:
        return [group]
    lenses: list[list[str]] = [[known[0][1]]]
    for (before, _), (f, name) in zip(known, known[1:], strict=False):
        if f > LENS_RATIO * before:
            lenses.append([])
        lenses[-1].append(name)
    focal_known = {name for _, name in known}
    unknown = [n for n in group if n not in focal_known]
    if unknown:
        if len(lenses) == 1:
            lenses[0].extend(unknown)
        else:
            lenses.append(unknown)
    order = {n: i for i, n in enumerate(group)}
    return [sorted(lens, key=order.__getitem__) for lens in lenses]


def run_sfm(
    image_dir: str | os.PathLike,
    work_dir: str | os.PathLike,
    matcher: str = "auto",
    num_threads: int = 2,
    *,
    camera_model: str = "SIMPLE_RADIAL",
    single_camera: bool = True,
    max_num_features: int = 8192,
    sift_peak_threshold: float = SIFT_PEAK_THRESHOLD,
    sequential_overlap: int = 10,
    guided_matching: bool = False,
    complete_below: float = 0.95,
    focal_length_px: float | None = None,
    focal_priors: Mapping[str, float] | None = None,
    min_images: int = 3,
    min_registered_fraction: float = MIN_REGISTERED_FRACTION,
    seed: int = 0,
    progress: Callable[[str, float], None] | None = None,
) -> SfmResult:
    """Structure from motion on the JPEG/PNG images in ``image_dir`` with pycolmap on the CPU.

    SIFT features (``max_num_features`` per image, detected down to the scale-space contrast
    ``sift_peak_threshold``: see ``SIFT_PEAK_THRESHOLD``), matching by ``choose_matcher``
    (sequential: ``sequential_overlap`` neighbours, quadratic overlap, no loop detection;
    auto: sequential; where fewer than ``complete_below`` of the images registered, the pairs
    that close the name order's loop (``loop_pairs``: a walk round the plot ends where it
    began), and where still too few, each image outside the largest model with every other
    (``completion_pairs``; every pair where those are most of them) — on the 50-view synthetic
    walk the verified pairs are 94 % within three neighbours; names with whitespace, which
    pycolmap's pair list cannot hold, skip the loop pass and complete by every pair), incremental
    mapping after the first pass and after each later one that verified a pair reaching an
    image outside the largest model;
    the model with the most registered images is kept and written as a text model to
    ``work_dir/model``. ``camera_model``: COLMAP model fitted (focal length starts at 1.2 × the
    longer side unless EXIF says otherwise); ``single_camera``: one camera shared by all images
    of a size and lens (photos of two sizes, portrait and landscape shots, get one camera each;
    so do photos of one size whose EXIF focal lengths differ by more than ``LENS_RATIO``).
    ``focal_length_px``: prior focal length (e.g. from a calibration or EXIF), still refined by
    bundle adjustment; without it COLMAP starts at 1.2 × the longer side, which a short capture
    may not recover from. ``focal_priors``: per image name (ingest's ``focal_px``, from EXIF),
    where ``focal_length_px`` is not given: each camera starts at the median of its photos'
    known ones (photos without one share it; a camera none of whose photos has one starts at
    COLMAP's guess). The priors used are in ``SfmResult.focal_priors``.
    ``guided_matching``: re-match each verified pair under its epipolar geometry. Off by
    default: on canopies an epipolar line crosses many look-alike leaf
    features, and the extra matches cost both time and accuracy (measured November 24; pose
    error = RMS of the camera centres against the truth after a similarity): 60 drone photos of
    maize at 960 × 720, matching 747 → 31 s, SfM 953 → 86 s, 0.86 → 0.34 px, 60/60 registered
    either way; three 50-photo soybean walks, pose error 0.76 → 0.12, 0.50 → 0.48 and
    1.53 → 0.48 cm, SfM 70 → 56, 59 → 20 and 49 → 19 s, 50/50 registered each time. The mapper
    accepts weaker evidence than COLMAP's defaults (initial pair ≥ 50 inliers, new image ≥ 15
    inliers at ratio ≥ 0.15).

    ``progress(step, fraction)``, where given: each step's start (0) and end (1) — "features",
    "matching (sequential)" and the other passes, "mapping" — and the mapping's share of the
    images registered so far (at 500 photos SfM ran ~36 min without a line of its own:
    session 94's drone audit).

    Raises ``InputError`` for fewer than ``min_images`` images, an unknown matcher or a
    non-positive ``sift_peak_threshold`` (before ``work_dir`` is touched), ``SfmError`` when no
    model is built or fewer than ``min_registered_fraction`` of the images are registered.
    """
    import pycolmap

    names = list_images(image_dir)
    if len(names) < min_images:
        raise InputError(
            f"{image_dir} holds {len(names)} JPEG/PNG image(s); structure from motion needs at "
            f"least {min_images}"
        )
    mode = choose_matcher(len(names), matcher)
    if not (np.isfinite(sift_peak_threshold) and sift_peak_threshold > 0):
        raise InputError(f"sift_peak_threshold must be positive, got {sift_peak_threshold!r}")
    work = Path(work_dir)
    work.mkdir(parents=True, exist_ok=True)
    db = work / "database.db"
    if db.exists():
        db.unlink()
    sparse = work / "sparse"
    shutil.rmtree(sparse, ignore_errors=True)
    sparse.mkdir()
    pycolmap.set_random_seed(int(seed))
    seconds: dict[str, float] = {}

    def said(step: str, fraction: float) -> None:
        if progress is not None:
            progress(step, fraction)

    said("features", 0.0)
    t0 = time.perf_counter()
    ext = pycolmap.FeatureExtractionOptions()
    ext.num_threads = int(num_threads)
    ext.use_gpu = False
    ext.sift.max_num_features = int(max_num_features)
    ext.sift.peak_threshold = float(sift_peak_threshold)
    if (focal_length_px is not None or focal_priors) and camera_model not in (
        "SIMPLE_RADIAL",
        "SIMPLE_PINHOLE",
        "PINHOLE",
    ):
        raise InputError(f"a focal prior needs a SIMPLE_RADIAL/PINHOLE model, not {camera_model}")
    # one camera per photo size: COLMAP's single camera skips every photo of another size than
    # the first (a phone held upright for some shots: ingest turns them upright), and they
    # read as merely unregistered
    groups: list[tuple[tuple[int, int] | None, list[str]]] = [(None, names)]
    if single_camera:
        by_size: dict[tuple[int, int], list[str]] = {}
        for name in names:
            by_size.setdefault(_image_size(Path(image_dir) / name), []).append(name)
        groups = [
            (size, lens)
            for size, group in by_size.items()
            for lens in _by_lens(group, None if focal_length_px is not None else focal_priors)
        ]

    priors: dict[str, float] = {}

    def reader_for(size: tuple[int, int] | None, group: list[str]) -> Any:
        reader = pycolmap.ImageReaderOptions()
        reader.camera_model = camera_model
        known = [float(focal_priors[n]) for n in group if (focal_priors or {}).get(n)]
        f = float(focal_length_px) if focal_length_px is not None else None
        if f is None and known and (single_camera or len(group) == 1):
            f = float(np.median(known))
        if f is not None:
            w, h = size or _image_size(Path(image_dir) / names[0])
            priors.update(dict.fromkeys(group, f))
            prior = {
                "SIMPLE_RADIAL": [f, w / 2, h / 2, 0.0],
                "SIMPLE_PINHOLE": [f, w / 2, h / 2],
                "PINHOLE": [f, f, w / 2, h / 2],
            }[camera_model]
            reader.camera_params = ",".join(repr(v) for v in prior)
        return reader

    try:
        for size, group in groups:
            pycolmap.extract_features(
                str(db),
                str(image_dir),
                image_names=group,
                camera_mode=pycolmap.CameraMode.SINGLE
                if single_camera
                else pycolmap.CameraMode.AUTO,
                reader_options=reader_for(size, group),
                extraction_options=ext,
                device=pycolmap.Device.cpu,
            )
        seconds["features"] = time.perf_counter() - t0
        said("features", 1.0)

        mopt = pycolmap.FeatureMatchingOptions()
        mopt.num_threads = int(num_threads)
        mopt.use_gpu = False
        mopt.guided_matching = bool(guided_matching)
        popt = pycolmap.IncrementalPipelineOptions()
        popt.num_threads = int(num_threads)
        popt.random_seed = int(seed)
        popt.min_model_size = 3
        # canopies are hard to match (thin leaves, parallax, occlusion): accept weaker but still
        # geometrically verified evidence than COLMAP's defaults (100 / 30 inliers, ratio 0.25)
        popt.mapper.init_min_num_inliers = 50
        popt.mapper.abs_pose_min_num_inliers = 15
        popt.mapper.abs_pose_min_inlier_ratio = 0.15

        def match(kind: str, pairs: list[tuple[int, int]] | None = None) -> None:
            said(f"matching ({kind})", 0.0)
            t0 = time.perf_counter()
            if kind == "exhaustive":
                # pairs already in the database (from a sequential pass) are not matched again
                pycolmap.match_exhaustive(
                    str(db), matching_options=mopt, device=pycolmap.Device.cpu
                )
            elif kind in ("loop", "unplaced"):
                listed = work / f"{kind}_pairs.txt"
                listed.write_text("".join(f"{names[a]} {names[b]}\n" for a, b in pairs or []))
                pair = pycolmap.ImportedPairingOptions()
                pair.match_list_path = str(listed)
                pycolmap.match_image_pairs(
                    str(db), matching_options=mopt, pairing_options=pair, device=pycolmap.Device.cpu
                )
            else:
                pair = pycolmap.SequentialPairingOptions()
                pair.overlap = int(sequential_overlap)
                pair.quadratic_overlap = True
                pair.loop_detection = False
                pycolmap.match_sequential(
                    str(db), matching_options=mopt, pairing_options=pair, device=pycolmap.Device.cpu
                )
            seconds[f"matching_{kind}"] = time.perf_counter() - t0
            said(f"matching ({kind})", 1.0)

        def mapping() -> dict:
            t0 = time.perf_counter()
            shutil.rmtree(sparse, ignore_errors=True)
            sparse.mkdir()
            said("mapping", 0.0)
            placed = [0]

            def next_image() -> None:  # after each image the mapper registers
                placed[0] += 1
                said("mapping", min(0.99, placed[0] / len(names)))

            out = pycolmap.incremental_mapping(
                str(db), str(image_dir), str(sparse), popt,
                next_image_callback=next_image if progress is not None else None,
            )  # fmt: skip
            said("mapping", 1.0)
            seconds["mapping"] = seconds.get("mapping", 0.0) + time.perf_counter() - t0
            return out

        def registered(found: dict) -> int:
            return max((r.num_reg_images() for r in found.values()), default=0)

        def placed(found: dict) -> set[str]:
            best = max(found.values(), key=lambda r: r.num_reg_images(), default=None)
            return set() if best is None else {best.image(i).name for i in best.reg_image_ids()}

        def verified() -> set[tuple[str, str]]:
            return _verified_pairs(db, popt.mapper.abs_pose_min_num_inliers)

        def remap_if_new(before: set[tuple[str, str]], models: dict) -> dict:
            # map again only where the pass verified a pair that reaches an image outside the
            # largest model: frames no pass can place (a drone's take-off and landing shots)
            # cost a whole mapping per pass, ~18 min at 500 photos (session 94's drone audit)
            outside = set(names) - placed(models)
            if any(a in outside or b in outside for a, b in verified() - before):
                return mapping()
            return models

        if mode == "auto":
            # ordered captures (a walk, a drone line) share features with their neighbours in
            # name order: match those first; complete only if that registers too few images
            match("sequential")
            models = mapping()
            mode = "sequential"
            # a walk round the plot ends where it began: the last photos with the first (not
            # for names with whitespace, which pycolmap's space-separated pair list cannot hold)
            spaced = any(ch.isspace() for n in names for ch in n)
            loop = [] if spaced else loop_pairs(len(names), int(sequential_overlap))
            if loop and registered(models) < complete_below * len(names):
                before = verified()
                match("loop", loop)
                models = remap_if_new(before, models)
                mode += "+loop"
            if registered(models) < complete_below * len(names):
                # the images outside the largest model against every other image: every pair
                # of a 500-photo flight was 124,750 pairs, ~3 h here, for the 25 frames of its
                # take-off and landing (session 94's drone audit); every pair where that is
                # most of them, or where names with whitespace cannot be listed
                inside = placed(models)
                rest = completion_pairs(len(names), [i for i, n in enumerate(names)
                                                     if n not in inside])  # fmt: skip
                before = verified()
                if rest == []:  # every image placed: a target above all of them
                    pass
                elif rest is None or spaced:
                    match("exhaustive")
                    mode += "+exhaustive"
                else:
                    match("unplaced", rest)
                    mode += "+unplaced"
                models = remap_if_new(before, models)
        else:
            match(mode)
            models = mapping()
        seconds["matching"] = sum(v for k, v in seconds.items() if k.startswith("matching_"))
    except Exception as e:  # pycolmap raises RuntimeError/ValueError with COLMAP's text
        raise SfmError(f"pycolmap structure from motion on {image_dir} failed: {e}") from e

    if not models:
        raise SfmError(
            f"structure from motion on {len(names)} images in {image_dir} built no model: the "
            "images share too few matching features (too little overlap or texture?)"
        )
    rec = max(models.values(), key=lambda r: r.num_reg_images())
    poses = _poses_from_reconstruction(rec)
    frac = len(poses) / len(names)
    unregistered = sorted(set(names) - set(poses.names))
    if frac < min_registered_fraction:
        sizes = sorted((r.num_reg_images() for r in models.values()), reverse=True)
        if len(sizes) > 1 and sum(sizes) > len(poses):
            # every photo may be registered, in models that share no verified match (a drone's
            # flight lines with too little side overlap): naming the others "not registered"
            # sent users looking for bad photos. Those in no model at all are named, and where
            # they are most, the photos share too few features (session 92's photos audit: 19
            # of 24 in none read "the photos of one part do not overlap the others'")
            placed = set().union(*(_poses_from_reconstruction(r).names for r in models.values()))
            nowhere = [n for n in unregistered if n not in placed]
            listed = f"{', '.join(nowhere[:10])}{' ...' if len(nowhere) > 10 else ''}"
            why = (
                "the images share too few matching features (too little overlap or texture?)"
                if 2 * len(nowhere) > len(names)
                else "the photos of one part do not overlap the others' enough (a drone's "
                "flight lines closer together, or more photos)"
            )
            raise SfmError(
                f"structure from motion on {len(names)} images in {image_dir} built "
                f"{len(sizes)} separate models ({', '.join(map(str, sizes))} images) that share "
                f"no verified matches; the largest holds {100 * frac:.0f} % of them (need "
                f"{100 * min_registered_fraction:.0f} %)"
                + (f", and {len(nowhere)} are in none ({listed})" if nowhere else "")
                + f": {why}"
            )
        raise SfmError(
            f"structure from motion registered only {len(poses)} of {len(names)} images "
            f"({100 * frac:.0f} %, need {100 * min_registered_fraction:.0f} %); not registered: "
            f"{', '.join(unregistered[:10])}{' ...' if len(unregistered) > 10 else ''}"
        )
    ids = list(rec.point3D_ids())
    pts = np.array([rec.point3D(i).xyz for i in ids], dtype=np.float64).reshape(-1, 3)
    cols = np.array([rec.point3D(i).color for i in ids], dtype=np.uint8).reshape(-1, 3)
    model_dir = work / "model"
    model_dir.mkdir(exist_ok=True)
    rec.write_text(str(model_dir))
    first = rec.camera(rec.image(sorted(rec.reg_image_ids())[0]).camera_id)
    return SfmResult(
        poses=poses,
        registered_fraction=float(frac),
        mean_reprojection_error_px=float(rec.compute_mean_reprojection_error()),
        points=pts,
        colors=cols,
        n_images=len(names),
        unregistered=unregistered,
        matcher=mode,
        camera_model=str(first.model.name),
        camera_params=[float(v) for v in first.params],
        seconds=seconds,
        model_dir=model_dir,
        focal_priors=priors,
    )
