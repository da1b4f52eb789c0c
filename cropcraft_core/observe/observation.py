"""The observation a scene fit matches: a row-camera depth map, its foreground mask, optional RGB,
the row camera and the histogram statistics, persistable as npz + json.

Masks (supplementary "Mask and Histogram Details"):

* :func:`observation_mask` — for the NeRF render. With height above the ground
  ``h = render_height - depth`` (ground at height 0 in the row frame; the camera looks straight
  down from ``render_height``) and lateral offset ``|y|`` from the row line (the unprojected
  pixel's camera-frame y, metres), a pixel is background if

  - soybean: (a* < −8 and h > render_height − 0.25 m) or h < 0.1 m or |y| ≥ 0.5 m;
  - maize: (a* < −8 and L* > 40 and h > render_height − 2 m) or h < 0.1 m or |y| ≥ 3 m;

  or if its depth is not finite and positive. The "z-coordinate" of the supplementary is read as
  height above the ground, as the phrase "0.25 m short of the render height" suggests; L*, a* are
  OpenCV's CIELAB of the RGB render (L* ∈ [0, 100], a* ∈ about [−127, 127]). Without RGB the
  colour clause is skipped (never true). All thresholds are preset fields.
* :func:`predicted_mask` — for the procedural render, which has no background: finite depth.
  Given the camera and preset it also applies the geometric clauses (h ≥ 0.1 m, |y| below the
  lateral limit), so that both sides are cut by the same box. The paper uses finite depth
  alone; :meth:`Observation.predicted_stats` cuts a prediction by the box whenever the
  observation's own mask was (``Observation.box_mask``: every observation of a reconstruction
  or a geometry), because otherwise the low leaves that the observation drops are counted on
  the predicted side only, and the fit tilts the leaves to hide them (measured on the demo
  scene: leaf-angle mean 24.0° without the cut, 19.0° with it, 16.1° from a clean render of
  the true canopy, truth 15.2°). A synthetic observation rendered without background
  (``fit.observe_canopy``, the paper's synthetic protocol) has no box, nor do its predictions.

Persistence: ``obs.save("dir/")`` writes ``dir/observation.npz`` (arrays ``depth``, ``mask`` and
``rgb`` if any) and ``dir/observation.json`` (crop, camera, preset, statistics, meta);
``obs.save("x.npz")`` or ``obs.save(fileobj)`` writes one npz with the JSON record stored as the
string array ``record``. :meth:`Observation.load` reads either.
"""

from __future__ import annotations

import functools
import json
import os
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, BinaryIO

import cv2
import numpy as np

from cropcraft_core.errors import ConfigError, InputError, OutputError
from cropcraft_core.geometry.camera import PinholeCamera
from cropcraft_core.observe.histograms import (
    HistogramStats,
    blur_depth,
    check_depth,
    check_mask,
    compute_stats,
    lateral_factor,
    mean_stats,
)
from cropcraft_core.observe.loss import LossBreakdown, loss
from cropcraft_core.observe.presets import CROPS, ObservePreset, preset, resolve_depth_range

FORMAT = "cropcraft-observation"
VERSION = 1
NPZ_NAME = "observation.npz"
JSON_NAME = "observation.json"


# --------------------------------------------------------------------------- masks
def _valid(depth: np.ndarray) -> np.ndarray:
    with np.errstate(invalid="ignore"):
        return np.isfinite(depth) & (depth > 0)


def _height_and_lateral(
    depth: np.ndarray, camera: PinholeCamera, p: ObservePreset
) -> tuple[np.ndarray, np.ndarray]:
    """(H, W) height above the ground and (H, W) |y| from the row line, metres (NaN where the
    depth is NaN)."""
    h = p.render_height - depth
    y = np.abs(lateral_factor(camera))[:, None] * depth
    return h, y


def rgb_to_lab(rgb: Any, shape: tuple[int, int]) -> np.ndarray:
    """(H, W, 3) RGB (uint8 0–255 or float 0–1) → (H, W, 3) float32 CIELAB (L*, a*, b*)."""
    c = np.asarray(rgb)
    if c.shape != (*shape, 3):
        raise InputError(f"rgb must have shape {(*shape, 3)} (H, W, 3), got {c.shape}")
    if c.dtype == np.uint8:
        f = c.astype(np.float32) / 255.0
    elif np.issubdtype(c.dtype, np.floating):
        f = c.astype(np.float32)
        if not np.all(np.isfinite(f)) or f.min() < 0 or f.max() > 1:
            raise InputError("float rgb must be finite and within [0, 1] (or pass uint8 0–255)")
    else:
        raise InputError(f"rgb must be uint8 or float, got dtype {c.dtype}")
    return cv2.cvtColor(f, cv2.COLOR_RGB2Lab)


def observation_mask(
    depth: np.ndarray,
    rgb: np.ndarray | None,
    camera: PinholeCamera,
    preset: ObservePreset,
) -> np.ndarray:
    """Foreground mask of an observed (NeRF) render by the supplementary's colour and box rules
    (module docstring).

    depth: (H, W) z-depth in metres, ``camera.height × camera.width``.
    rgb: (H, W, 3) uint8 or float [0, 1] RGB render, or ``None`` (colour clause skipped).
    Returns (H, W) bool, true for foreground (plant).
    """
    d = check_depth(depth, camera).astype(np.float64, copy=False)
    p = preset
    valid = _valid(d)
    with np.errstate(invalid="ignore"):
        h, y = _height_and_lateral(d, camera, p)
        bg = ~valid | (h < p.mask_min_height) | (y >= p.mask_max_lateral)
        if rgb is not None:
            lab = rgb_to_lab(rgb, d.shape)
            colour = lab[..., 1] < p.mask_a_max
            if p.mask_l_min is not None:
                colour &= lab[..., 0] > p.mask_l_min
            bg |= colour & (h > p.render_height - p.mask_top_band)
    return ~bg


def predicted_mask(
    depth: np.ndarray,
    camera: PinholeCamera | None = None,
    preset: ObservePreset | None = None,
) -> np.ndarray:
    """Foreground mask of a procedural render (no background rendered): (H, W) bool, true where
    the depth is finite and positive. With ``camera`` and ``preset`` also require height
    ``>= mask_min_height`` and ``|y| < mask_max_lateral`` (the observation's box clauses)."""
    d = np.asarray(depth)
    if d.ndim != 2:
        raise InputError(f"depth must be a 2-D (H, W) array, got shape {d.shape}")
    m = _valid(d)
    if (camera is None) != (preset is None):
        raise ConfigError("predicted_mask needs both camera and preset, or neither")
    if camera is not None and preset is not None:
        d = check_depth(d, camera).astype(np.float64, copy=False)
        with np.errstate(invalid="ignore"):
            h, y = _height_and_lateral(d, camera, preset)
            m &= (h >= preset.mask_min_height) & (y < preset.mask_max_lateral)
    return m


#: Share of the row camera's view without a fully supported reconstructed surface
#: (``SurfaceBackend.render_supported``) above which a scene's traits are flagged as likely
#: underestimated (:func:`coverage_warning`). In a field every ray from above meets a leaf or
#: the soil, so such a pixel is one the reconstruction lost or only guessed at (tsdf: filled from
#: single depth maps), and the fit reads lost pixels as gaps. Measured on synthetic soybean (CPU
#: surfaces, true poses, 10 seeds × 300 evaluations): the default canopy (LAI 1.26) leaves
#: 11.5–14.3 % of the view without a two-view surface, and its LAI is within target (−5 %
#: without the one-view fill, +9 % with it); a denser one (LAI 2.32) 23 % (−30 % / −10 %); a
#: 1.1 m tall one (LAI 3.66) 22 % (−46 % / −26 %). The threshold sits between the two groups;
#: with the fill (the default) it also flags the LAI-2.32 canopy, read within target.
NO_SURFACE_WARN = 0.18


def no_surface_fraction(depth: np.ndarray) -> float:
    """Share of the pixels of an (H, W) depth map rendered from reconstructed surfaces that show
    no surface (non-finite depth)."""
    d = np.asarray(depth)
    return float(np.mean(~np.isfinite(d))) if d.size else 0.0


def coverage_warning(fraction: float, crop: str | None = "soybean") -> str | None:
    """The warning a scene gets when ``fraction`` of its row camera's view has no reconstructed
    surface (above :data:`NO_SURFACE_WARN`), else None; soybean's cites what it measured (no
    such figures for maize)."""
    if not fraction > NO_SURFACE_WARN:
        return None
    measured = ""
    if crop == "soybean":
        measured = " (synthetic soybean, true poses: -10 % at 23 %, -26 % at 22 %)"
    return (
        f"{100 * fraction:.1f} % of the row camera's view has no fully supported reconstructed "
        f"surface (over {100 * NO_SURFACE_WARN:.0f} %): the fit reads lost pixels as gaps, so "
        f"LAI is likely underestimated{measured}"
    )


#: Share of the row camera's view without a reconstructed surface above which a scene is
#: refused (:func:`check_coverage`): the fit would read its LAI from the gaps. A maize walk
#: round a 1.8 m canopy on the tsdf backend left 97.9 % of the view without a surface and
#: read LAI 0.069 for 1.79, finished "done" with a coverage warning (session 96's capture
#: audit). Of 237 stored observations of sessions 90-96 the next highest read 86.7 % (a 13 m
#: maize flight given a 1.4 m camera height); the tests' small scenes read 4-55 %.
NO_SURFACE_REFUSE = 0.9


def check_coverage(fraction: float) -> None:
    """``SurfacesError`` where ``fraction`` of the row camera's view has no reconstructed
    surface, over :data:`NO_SURFACE_REFUSE`."""
    if not fraction > NO_SURFACE_REFUSE:
        return
    from cropcraft_core.surfaces.base import SurfacesError

    raise SurfacesError(
        f"the reconstruction covers only {100 * (1 - fraction):.1f} % of the row camera's view "
        f"({100 * fraction:.1f} % has no surface, over the {100 * NO_SURFACE_REFUSE:.0f} % a "
        "fit can read): its LAI would be read from the gaps. Do the photos see the canopy from "
        "above? (a walk round a crop taller than the camera sees its sides: photograph maize "
        "from a drone)"
    )


def check_row_camera(camera: PinholeCamera, p: ObservePreset) -> None:
    """``ConfigError`` unless ``camera`` is the preset's row camera: looking straight down
    (optical axis = world −z), ``render_height`` above the ground z = 0, vertical field of view
    ``vfov_deg`` (any resolution, e.g. ``camera.scaled(0.5)``)."""
    if not isinstance(camera, PinholeCamera):
        raise ConfigError(f"camera must be a PinholeCamera, got {type(camera).__name__}")
    axis = camera.cam_to_world[:3, 2]
    if not np.allclose(axis, [0.0, 0.0, -1.0], atol=1e-6):
        raise ConfigError(
            f"the row camera must look straight down (optical axis (0, 0, -1)), got {axis.round(6)}"
        )
    z = float(camera.center[2])
    if abs(z - p.render_height) > 1e-6:
        raise ConfigError(
            f"the camera is {z:g} m above the ground but the {p.crop} preset's render height is "
            f"{p.render_height:g} m: build the preset with render_height={z:g} or use "
            "preset.row_camera()"
        )
    if abs(camera.vfov_deg - p.vfov_deg) > 0.05:
        raise ConfigError(
            f"the camera's vertical field of view is {camera.vfov_deg:.3f}° but the preset's is "
            f"{p.vfov_deg:g}°"
        )


# --------------------------------------------------------------------------- observation
def _readonly(a: np.ndarray) -> np.ndarray:
    a = np.array(a, copy=True)
    a.flags.writeable = False
    return a


@dataclass(frozen=True, eq=False)
class Observation:
    """A row observation and its histogram statistics.

    crop: "soybean" or "maize".
    camera: the row camera (straight down from the preset's render height, x along the row).
    depth: (H, W) float32 or float64 (as given; other dtypes become float64) z-depth in metres,
    a read-only copy; non-finite where nothing is seen.
    mask: (H, W) bool foreground (read-only copy); every masked pixel has a finite positive depth.
    rgb: (H, W, 3) uint8 or float [0, 1] RGB render, or ``None``.
    stats: the :class:`HistogramStats` of (depth, mask); computed (derivative histogram
    included, whatever λ_sobel) when ``None``.
    preset: the :class:`ObservePreset`; ``preset(crop)`` when ``None``. One that fits its depth
    range to the canopy (``depth_top_margin``) is resolved against this observation's
    foreground depths (:func:`~cropcraft_core.observe.presets.resolve_depth_range`): the
    attribute holds the resolved, fixed-range preset.
    meta: JSON-serialisable provenance (scene, source, render-height choice, ...).
    box_mask: whether ``mask`` drops the preset's box (height < ``mask_min_height``, ``|y|`` ≥
    ``mask_max_lateral``), as :func:`observation_mask` does; predictions are then cut by the
    same box (:meth:`predicted_stats`). False for a render without background whose mask is
    its finite depth (``fit.observe_canopy``).

    Raises ``InputError`` for an all-NaN depth map, an empty mask, shape mismatches or masked
    pixels without depth; ``ConfigError`` for an unknown crop, a preset of another crop, a camera
    that is not the preset's row camera, or statistics computed with another preset.
    """

    crop: str
    camera: PinholeCamera
    depth: np.ndarray
    mask: np.ndarray
    rgb: np.ndarray | None = None
    stats: HistogramStats | None = None
    preset: ObservePreset | None = None
    meta: dict = field(default_factory=dict)
    box_mask: bool = True

    def __post_init__(self) -> None:
        if not isinstance(self.crop, str) or self.crop not in CROPS:
            raise ConfigError(f"unknown crop {self.crop!r}: choose one of {', '.join(CROPS)}")
        p = self.preset if self.preset is not None else preset(self.crop)
        if not isinstance(p, ObservePreset):
            raise ConfigError(f"preset must be an ObservePreset, got {type(p).__name__}")
        if p.crop != self.crop:
            raise ConfigError(f"a {p.crop} preset was given for a {self.crop} observation")
        if not isinstance(self.box_mask, bool | np.bool_):
            raise ConfigError(f"box_mask must be True or False, got {self.box_mask!r}")
        check_row_camera(self.camera, p)
        d = check_depth(self.depth, self.camera)
        valid = _valid(d)
        if not valid.any():
            raise InputError("depth map has no finite positive values (all NaN, inf or <= 0)")
        m = check_mask(self.mask, d.shape)
        if not m.any():
            raise InputError(
                "foreground mask is empty: no plant pixels in the observation (check the mask "
                "thresholds, the render height and the row camera)"
            )
        n_bad = int(np.count_nonzero(m & ~valid))
        if n_bad:
            raise InputError(f"mask marks {n_bad} pixel(s) whose depth is not finite and positive")
        p = resolve_depth_range(p, d[m])  # the depth bins over this canopy, where p asks
        rgb = self.rgb
        if rgb is not None:
            rgb_to_lab(rgb, d.shape)  # validates shape, dtype and range
            rgb = _readonly(rgb)
        try:
            meta = json.loads(json.dumps(dict(self.meta), allow_nan=False))
        except (TypeError, ValueError) as e:
            raise InputError(f"meta must be a JSON-serialisable mapping: {e}") from None
        d, m = _readonly(d), _readonly(m)
        stats = self.stats
        if stats is None and p.n_views > 1:
            raise ConfigError(
                f"the preset pools {p.n_views} row cameras (views_along={p.views_along}, "
                f"views_across={p.views_across}) but only the row camera's depth map was given: "
                "build the observation with its pooled statistics (fit.observe_canopy, the "
                "observe stage)"
            )
        if stats is None:  # always with the derivative histogram (computed once, for reports)
            stats = compute_stats(d, self.camera, m, p, sobel=True)
        elif not isinstance(stats, HistogramStats):
            raise InputError(f"stats must be HistogramStats, got {type(stats).__name__}")
        elif stats.spec != p.stats_spec():
            raise ConfigError("stats were computed with a different preset than this observation's")
        for name, value in (
            ("preset", p),
            ("depth", d),
            ("mask", m),
            ("rgb", rgb),
            ("meta", meta),
            ("stats", stats),
            ("box_mask", bool(self.box_mask)),
        ):
            object.__setattr__(self, name, value)

    # ----------------------------------------------------------------- construction
    @classmethod
    def from_depth(
        cls,
        crop: str,
        depth: np.ndarray,
        camera: PinholeCamera | None = None,
        rgb: np.ndarray | None = None,
        mask: np.ndarray | None = None,
        preset: ObservePreset | None = None,
        meta: dict | None = None,
    ) -> Observation:
        """Build an observation from a row-camera depth map (and RGB render).

        ``camera`` defaults to ``preset.row_camera()``; ``preset`` to the crop's paper settings;
        ``mask`` to :func:`observation_mask` (colour clause only when ``rgb`` is given).
        """
        p = preset if preset is not None else _preset_for(crop)
        cam = camera if camera is not None else p.row_camera()
        if mask is None:
            check_row_camera(cam, p)
            mask = observation_mask(depth, rgb, cam, p)
        return cls(crop, cam, depth, mask, rgb=rgb, preset=p, meta=dict(meta or {}))

    @classmethod
    def from_surfaces(
        cls,
        crop: str,
        render: Callable[[PinholeCamera], tuple[np.ndarray, np.ndarray]],
        camera_world: PinholeCamera,
        camera_scene: PinholeCamera,
        scale: float,
        render_height: float,
        *,
        image_scale: float = 1.0,
        preset_overrides: dict | None = None,
        meta: dict | None = None,
        row_spacing: float | None = None,
        no_surface: Callable[[PinholeCamera], float] | None = None,
        max_no_surface: float | None = None,
    ) -> Observation:
        """The observation of fitted visible surfaces through the row camera.

        ``render(camera) -> (depth, rgb)`` renders the surfaces (``SurfaceBackend.render``) in
        their own (scene) frame, where the row camera is ``camera_scene``; ``camera_world`` is
        the same camera in the metric world frame, ``scale`` metres per scene unit (depths are
        converted with it). ``image_scale`` resizes both cameras (e.g. 0.5); the preset is the
        crop's with the row fit's ``render_height``, the camera's size and
        ``preset_overrides``. Where the preset pools several row cameras
        (:func:`observe_views`), each is rendered the same way (``row_spacing``, metres, places
        the neighbouring rows). ``no_surface(camera_scene) -> share`` then measures, for each
        view beside the row camera, the share of its view without a reconstructed surface
        (e.g. :func:`no_surface_fraction` of ``SurfaceBackend.render_supported``), and a view
        over ``max_no_surface`` is left out of the pool (:func:`observe_views`' ``coverage``
        and ``max_outside``; by default the row camera's own share or 18 %, the larger).
        """
        if image_scale != 1.0:
            camera_world = camera_world.scaled(image_scale)
            camera_scene = camera_scene.scaled(image_scale)
        p = preset(
            crop,
            **{
                "render_height": float(render_height),
                "image_width": camera_world.width,
                "image_height": camera_world.height,
                **dict(preset_overrides or {}),
            },
        )
        check_row_camera(camera_world, p)
        k = 1.0 / float(scale)  # scene units per metre

        def view(dx: float, dy: float):
            cam = camera_world.shifted(dx, dy)
            depth, rgb = render(camera_scene.shifted(dx * k, dy * k))
            depth_m = np.asarray(depth, np.float64) * float(scale)
            return cam, depth_m, observation_mask(depth_m, rgb, cam, p), rgb

        coverage = None
        if no_surface is not None:

            def coverage(dx: float, dy: float) -> float:
                return no_surface(camera_scene.shifted(dx * k, dy * k))

        return observe_views(
            crop, p, view, row_spacing, meta=meta, coverage=coverage, max_outside=max_no_surface
        )

    # ----------------------------------------------------------------- comparison
    def predicted_stats(self, depth: np.ndarray, mask: np.ndarray | None = None) -> HistogramStats:
        """Statistics of a procedural render from this observation's camera: (H, W) z-depth,
        NaN where nothing is seen; ``mask`` defaults to :func:`predicted_mask`: finite depth,
        cut by the preset's box when the observation's mask is (``box_mask``) unless the preset
        says otherwise (``mask_predictions=False``, the paper's rule). Where the preset asks
        (``prediction_blur_m``), the depth is blurred (:func:`blur_depth`,
        :attr:`prediction_blur_px`) after the mask is taken and before the statistics."""
        if mask is None:
            cut = self.box_mask and self.preset.mask_predictions
            box = (self.camera, self.preset) if cut else (None, None)
            mask = predicted_mask(depth, *box)
        if self.prediction_blur_px > 0:
            depth = blur_depth(depth, self.prediction_blur_px)
        return compute_stats(depth, self.camera, mask, self.preset)

    @functools.cached_property
    def prediction_blur_px(self) -> float:
        """The preset's ``prediction_blur_m`` in this camera's pixels at the observed canopy's
        median z-depth (0 when the preset asks for no blur)."""
        blur_m = float(self.preset.prediction_blur_m)
        if blur_m == 0:
            return 0.0
        z = float(np.median(self.depth[self.mask]))
        return blur_m * float(self.camera.fy) / z

    def loss_of(self, depth: np.ndarray, mask: np.ndarray | None = None) -> LossBreakdown:
        """The loss of a procedural render (see :meth:`predicted_stats`) against this
        observation."""
        return loss(self.stats, self.predicted_stats(depth, mask), self.preset)

    # ----------------------------------------------------------------- persistence
    def record(self) -> dict[str, Any]:
        """The JSON part of the saved form."""
        return {
            "format": FORMAT,
            "version": VERSION,
            "crop": self.crop,
            "camera": self.camera.to_dict(),
            "preset": self.preset.to_dict(),
            "stats": self.stats.to_dict(),
            "meta": self.meta,
            "has_rgb": self.rgb is not None,
            "box_mask": self.box_mask,
        }

    def _arrays(self) -> dict[str, np.ndarray]:
        arrays = {"depth": self.depth, "mask": self.mask}
        if self.rgb is not None:
            arrays["rgb"] = self.rgb
        return arrays

    def save(self, target: str | os.PathLike | BinaryIO) -> Path | None:
        """Write the observation.

        target: a directory (created; gets ``observation.npz`` with the record inside, as every
        form has it, and ``observation.json``, the record a person reads and may edit, with
        the digest of the arrays it was written beside), a path ending in ``.npz`` (one file,
        JSON record inside), or a binary file object (one npz).
        Returns the path written, ``None`` for a file object. ``OutputError`` if it cannot be
        written.
        """
        record = self.record()
        text = json.dumps(record, indent=1, allow_nan=False)
        if hasattr(target, "write"):
            np.savez_compressed(target, record=np.array(text), **self._arrays())
            return None
        path = Path(target)
        try:
            if path.suffix == ".npz":
                path.parent.mkdir(parents=True, exist_ok=True)
                _atomic_npz(path, {"record": np.array(text), **self._arrays()})
            else:
                path.mkdir(parents=True, exist_ok=True)
                # the record in the npz too, which load reads first: a save stopped between
                # the two files left new arrays beside the old statistics, loaded as one
                arrays = self._arrays()
                _atomic_npz(path / NPZ_NAME, {"record": np.array(text), **arrays})
                beside = {**record, "arrays_sha256": _arrays_digest(arrays)}
                tmp = path / f".{JSON_NAME}.{os.getpid()}.tmp"
                tmp.write_text(json.dumps(beside, indent=1, allow_nan=False) + "\n")
                os.replace(tmp, path / JSON_NAME)
        except OSError as e:
            raise OutputError(f"cannot write observation to {path}: {e}") from None
        return path

    @classmethod
    def load(cls, source: str | os.PathLike | BinaryIO) -> Observation:
        """Read what :meth:`save` wrote (directory, ``.npz`` path or file object). Stored
        statistics are reused when their spec matches the stored preset, else recomputed.
        ``InputError`` if missing or malformed."""
        if hasattr(source, "read"):
            arrays, text = _read_npz(source, "file object")
        else:
            path = Path(source)
            if path.is_dir():
                arrays, inside = _read_npz(path / NPZ_NAME, str(path / NPZ_NAME))
                try:
                    text = (path / JSON_NAME).read_text()
                except OSError as e:
                    raise InputError(f"cannot read {path / JSON_NAME}: {e}") from None
                if inside is not None and _torn(text, arrays):
                    text = inside  # a save stopped between its two files: the npz's own
            elif path.is_file():
                arrays, text = _read_npz(path, str(path))
            else:
                raise InputError(f"no observation at {path}")
        if text is None:
            raise InputError("observation npz has no JSON 'record' entry")
        try:
            rec = json.loads(text)
        except json.JSONDecodeError as e:
            raise InputError(f"observation record is not valid JSON: {e}") from None
        if not isinstance(rec, dict) or rec.get("format") != FORMAT:
            raise InputError(f"not a {FORMAT} record")
        if rec.get("version") != VERSION:
            raise InputError(f"unsupported observation version {rec.get('version')!r}")
        for key in ("crop", "camera", "preset"):
            if key not in rec:
                raise InputError(f"observation record is missing {key!r}")
        for key in ("depth", "mask"):
            if key not in arrays:
                raise InputError(f"observation arrays are missing {key!r}")
        if rec.get("has_rgb") and "rgb" not in arrays:
            raise InputError("observation record says it has rgb but the npz holds none")
        p = ObservePreset.from_dict(rec["preset"])
        camera = PinholeCamera.from_dict(rec["camera"])
        stats = None
        if isinstance(rec.get("stats"), dict):
            stats = HistogramStats.from_dict(rec["stats"])
            if stats.spec != p.stats_spec():
                stats = None
        return cls(
            rec["crop"],
            camera,
            arrays["depth"],
            arrays["mask"],
            rgb=arrays.get("rgb"),
            stats=stats,
            preset=p,
            meta=rec.get("meta") or {},
            # records written before the field existed all came from observation_mask
            box_mask=bool(rec.get("box_mask", True)),
        )

    def equals(self, other: Observation) -> bool:
        """Exact equality of arrays, camera, preset, statistics and meta."""
        return (
            self.crop == other.crop
            and self.camera.to_dict() == other.camera.to_dict()
            and self.preset == other.preset
            and np.array_equal(self.depth, other.depth, equal_nan=True)
            and self.depth.dtype == other.depth.dtype
            and np.array_equal(self.mask, other.mask)
            and (
                (self.rgb is None and other.rgb is None)
                or (
                    self.rgb is not None
                    and other.rgb is not None
                    and self.rgb.dtype == other.rgb.dtype
                    and np.array_equal(self.rgb, other.rgb)
                )
            )
            and self.stats.equals(other.stats)
            and self.meta == other.meta
            and self.box_mask == other.box_mask
        )


#: ``view(dx, dy) -> (camera, depth, mask, rgb)``: the row camera moved ``dx`` metres along
#: the row and ``dy`` across it, what it sees (z-depth in metres), its foreground mask and RGB
#: (or ``None``). :func:`observe_views` calls it once per pooled camera.
ViewRenderer = Callable[[float, float], tuple[PinholeCamera, np.ndarray, np.ndarray, Any]]


def observe_views(
    crop: str,
    p: ObservePreset,
    view: ViewRenderer,
    row_spacing: float | None = None,
    meta: dict | None = None,
    box_mask: bool = True,
    coverage: Callable[[float, float], float] | None = None,
    max_outside: float | None = None,
) -> Observation:
    """The observation of the row camera (``view(0, 0)``), its statistics pooled over the
    preset's cameras (:meth:`ObservePreset.view_offsets`; neighbouring rows ``row_spacing``
    metres apart) as their bin-by-bin mean (:func:`mean_stats`). Every view is binned with the
    row camera's preset (a depth range fitted to the canopy, maize's default, is resolved over
    the row camera's own foreground); the depth map, mask, RGB and camera are the row camera's,
    and ``meta["views"]`` lists the offsets pooled. With the paper's single camera it is
    exactly ``Observation(crop, camera, depth, mask, rgb, preset=p)``.

    ``coverage(dx, dy) -> share``: the share of that camera's view that lies outside what was
    observed (no reconstructed surface, or no geometry under it); a view beside the row camera
    over ``max_outside`` is left out of the pool, since its lost pixels would read as gaps (the
    mean over the rest still estimates the field's). ``max_outside`` defaults to the
    ``observe_rows`` stage's rule: :data:`NO_SURFACE_WARN` or the row camera's own share
    (``coverage(0, 0)``), the larger, so a view no worse covered than the row camera is kept.
    ``meta["views_left_out"]`` lists those left out as ``[dx, dy, share]``,
    ``meta["views_outside"]`` the pooled ones' shares.

    Why: one row camera sees one draw of the canopy, and on some scenes that draw lies far
    from its parameters' average, so the fit follows the draw (benchmarks/RESULTS.md,
    *#views*). A procedural prediction's statistics do not depend on where along a uniform
    canopy, or over which of its rows, the camera stands, so the predictions stay one camera."""
    if coverage is None and max_outside is not None:
        raise ConfigError(
            "max_outside without coverage: a coverage check needs both the measure and its limit"
        )
    cam, depth, mask, rgb = view(0.0, 0.0)
    meta = dict(meta or {})
    if p.n_views == 1:
        return Observation(crop, cam, depth, mask, rgb=rgb, preset=p, meta=meta, box_mask=box_mask)
    offsets = p.view_offsets(row_spacing)
    # the row camera's own observation checks its input and resolves the bins the views share
    own = replace(p, views_along=1, views_across=0)
    first = Observation(crop, cam, depth, mask, rgb=rgb, preset=own, meta=meta, box_mask=box_mask)
    stats, pooled, shares, left = [first.stats], [offsets[0]], [], []
    if coverage is not None and max_outside is None:
        max_outside = max(NO_SURFACE_WARN, float(coverage(0.0, 0.0)))
    for dx, dy in offsets[1:]:
        if coverage is not None:
            share = float(coverage(dx, dy))
            if not share <= max_outside:  # outside what was observed (or unmeasurable)
                left.append([dx, dy, share])
                continue
            shares.append(share)
        cv, dv, mv, _ = view(dx, dy)
        stats.append(
            compute_stats(
                check_depth(dv, cv), cv, check_mask(mv, dv.shape), first.preset, sobel=True
            )
        )
        pooled.append((dx, dy))
    return replace(
        first,
        stats=mean_stats(stats),
        preset=replace(first.preset, views_along=p.views_along, views_across=p.views_across),
        meta={
            **first.meta,
            "views": [list(o) for o in pooled],
            **({} if coverage is None else {"views_outside": shares, "views_left_out": left}),
        },
    )


def _preset_for(crop: str) -> ObservePreset:
    return preset(crop)


def _atomic_npz(path: Path, arrays: dict[str, np.ndarray]) -> None:
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as f:
        np.savez_compressed(f, **arrays)
    os.replace(tmp, path)


def _read_npz(src: Any, label: str) -> tuple[dict[str, np.ndarray], str | None]:
    try:
        with np.load(src, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except FileNotFoundError:
        raise InputError(f"no observation file {label}") from None
    except Exception as e:  # a damaged zip raises BadZipFile, zlib.error, TokenError, ...
        raise InputError(
            f"cannot read observation npz {label} (damaged?): {type(e).__name__}: {e}"
        ) from None
    text = arrays.pop("record", None)
    return arrays, (str(text[()]) if text is not None else None)


__all__ = [
    "Observation",
    "check_row_camera",
    "observation_mask",
    "predicted_mask",
    "rgb_to_lab",
]


def _arrays_digest(arrays: dict[str, np.ndarray]) -> str:
    """sha256 of an observation's arrays (names, dtypes, shapes and bytes)."""
    import hashlib

    h = hashlib.sha256()
    for name in sorted(arrays):
        a = np.ascontiguousarray(arrays[name])
        h.update(f"{name}:{a.dtype.str}:{a.shape};".encode())
        h.update(a.tobytes())
    return h.hexdigest()


def _torn(text: str, arrays: dict[str, np.ndarray]) -> bool:
    """Whether a directory's ``observation.json`` was written beside other arrays than its
    npz's (a save stopped between the two files: the new arrays, the old record and
    statistics). A record without a digest (older, or edited without one) is not judged."""
    try:
        digest = json.loads(text).get("arrays_sha256")
    except (ValueError, AttributeError):
        return False  # load names what is wrong with it
    return digest is not None and digest != _arrays_digest(arrays)
