"""The visible-surfaces stage (the paper's NeRF stage): interface, configuration, factory.

A surface backend is fitted to posed photos (``fit``) and then answers two questions:

* ``point_cloud(n_max)``: a coloured point cloud of the visible surfaces (row fitting input);
* ``render(camera)``: z-depth and RGB images for any pinhole camera (the row camera's observation).

``save(dir)`` persists the fitted surface so a later stage can render from it without refitting;
``load_surfaces(dir)`` reads it back whatever the backend.

Backends (``SurfacesConfig.backend``):

* ``tsdf`` (default, CPU): plane-sweep multi-view stereo per view over its best neighbours,
  cross-view depth consistency filtering, Open3D TSDF fusion with colour, mesh extraction,
  ray casting for new views (``cropcraft_core.surfaces.tsdf``).
* ``points`` (CPU; maize's default in the scene flow, :data:`CROP_SURFACES`): the same stereo,
  its points filtered by visibility and splatted (``cropcraft_core.surfaces.points``).
* ``nerfacto``: nerfstudio's Nerfacto as in the paper; needs nerfstudio and a CUDA GPU
  (``cropcraft_core.surfaces.nerfacto``).
* ``truth``: the true mesh plus the ground plane, for tests and benchmarks
  (``cropcraft_core.surfaces.mesh_truth``).

World frame: metres, z up. Cameras: ``PinholeCamera`` (OpenCV axes, pixel centres at +0.5). Depth
is z-depth along the optical axis, NaN where a ray meets nothing.
"""

from __future__ import annotations

import json
import os
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np

from cropcraft_core.errors import ConfigError, CropCraftError, InputError
from cropcraft_core.geometry.camera import PinholeCamera

#: Backend names ``make_backend`` knows.
BACKENDS = ("tsdf", "points", "nerfacto", "truth")

#: The scene box per crop in the levelled frame of :func:`cropcraft_core.sfm.level_poses` (z up,
#: ground z = 0 at the plot centre, metres; m): the plot with a margin for a provisional scale
#: off by up to ~30 % and for the tallest plants (soybean ~1 m; maize 3.2 m). Maize's reaches
#: 3.5 below that ground too: from a drone over a closed maize canopy SfM may find no soil, and
#: levelling's ground (the sparse points' lowest) then lies on the leaves. On a 2.2 m canopy
#: (LAI 3.3) every sparse point was 0.93 m up or more; a box from −0.3 cut the soil out of the
#: reconstruction (height 21.9 % off, LAI −68 %); with this box height 2.1 % off, LAI −14.3 %.
#: Its 128 horizontal sweep planes are 5.9 cm apart instead of 3 cm (refined by a parabola): on
#: a canopy whose soil SfM did see (same SfM model, 10 × 300) LAI −2.5 % against −9.5 %,
#: depth-histogram L1 0.170 against 0.153, the surfaces' time unchanged (284 s, 265 s).
#: Soybean's reaches 1.2 below for the same reason: walking round a 1.1 m canopy (LAI 3.7) SfM
#: found nothing lower than 0.55 m, the box from −0.15 left 23 ground-coloured points and the
#: row fit failed (*no ground found*); with this box it ran (row 0.44° / 2.6 cm / 0.96 %). On
#: the default canopy (same SfM model) holes 9.0 → 10.8–11.3 %, depth-histogram L1 against
#: the reconstructed surfaces 0.091–0.095 → 0.099–0.108, surfaces' time unchanged (~100 s).
#: It is 1.5 wide each way (was 1.3): the provisional scale over a 1.2 m canopy is ~1.5 units
#: per metre, and the row camera's footprint then reached 1.36 (same holes, 11.2 %, and L1).
SCENE_BOX = {
    "soybean": ((-1.5, -1.5, -1.2), (1.5, 1.5, 1.2)),
    "maize": ((-3.0, -3.0, -3.5), (3.0, 3.0, 4.0)),
}


#: Surfaces settings per crop over ``SurfacesConfig``'s defaults (the scene flow and ``bench
#: pipeline`` apply them under the user's own). Maize is photographed from a drone (~13 m), where
#: a stereo point's source footprint is 1.5 cm wide: the fused surface and footprint-sized splats
#: both close the soil gaps between the plants, and the fit reads the extra cover as more, flatter
#: leaf. Points with their discs capped at their spacing in the row view, each dropped where more
#: than a tenth as many views see past it as agree with it (a stereo edge reaching over the soil
#: is seen past from above), keep the gaps: on two 60-photo maize drone scenes (true poses,
#: 10 × 300) LAI −10.3 % and −12.0 % against the fused surface's +58.8 % and +46.9 %
#: (``benchmarks/RESULTS.md``, *Maize through the photo pipeline*). Soybean, photographed
#: walking round the plot, keeps the fused surface, its stereo planes spanning only the heights
#: the scene occupies (``sweep_heights``; *The sweep's height range*): on two dense synthetic
#: canopies (true poses) the row view's loss against the true mesh fell from 0.229 to 0.027 and
#: from 0.047 to 0.018; maize's drone stereo has not been measured with it. Soybean's stereo
#: keeps depths down to an NCC of 0.25 (``min_ncc``; *The NCC threshold through SfM*): through
#: SfM at 10 × 500, LAI −41.8 → −34.3 % (SC, LAI 3.66), −5.7 → −7.1 % (SB), +32.9 → +29.8 %
#: (SA), the demo +3.1 % (+3.3 and +13.8 % on two runs at 0.4), with fewer holes on every
#: canopy; maize's was not measured. Soybean's points (no cap) were its default for one commit
#: in session 77: through SfM over canopies of LAI 1.26 / 2.32 / 0.58 they read LAI −5.3 /
#: −7.7 / −49.9 % against the fused surface's −1.3 / −17.5 / −49.2 %, but the demo (metric
#: poses) read +21.6 % against −0.3 % on the same host (*#sparse-77*). Soybean's stereo matches
#: the photos at full size (``mvs_scale`` 1.0, not 0.75) over 96 planes (not 128), since session
#: 83 (*#scale-83*): over three draws of 30 seeds each the guarded answer's mean |LAI error| fell
#: on all three canopies of the session-78 rule (the demo 7.4 → 4.6 %, a sparse LAI-0.58 canopy
#: through SfM 33.1 → 27.0 %, the default canopy through SfM 6.3 → 5.9 %), and photos →
#: observation through SfM read 444–475 s on the slowest host measured (2 cores), inside #4's
#: 480 s; 128 planes at full size read better on the sparse canopy (21.6 %) but took ~610 s.
#: Since session 84 (*#colour-consistency-84*) soybean's neighbours agree with a depth only where
#: they also see its colour (``consistency_a_tol`` 10 a* units): over two draws of ten seeds the
#: guarded answer's mean |LAI error| read 10.6 % on the sparse canopy (28.7 % without), 11.1 % on
#: the default canopy through SfM (3.7 %) and 7.9 % on the demo (3.9 %): 9.9 % over the three
#: against 12.1 %, the two denser canopies worse (their leaves read ~10 % long: the method's own
#: reading from that canopy's row camera, its true mesh +7.4 %, *#lean-85*), the consistency
#: pass ~5 s longer; a third draw on the sparse canopy read −1.3 % (*#draw3-85*).
CROP_SURFACES: dict[str, dict[str, Any]] = {
    "soybean": {
        "sweep_heights": "auto",
        "min_ncc": 0.25,
        "mvs_scale": 1.0,
        "n_depths": 96,
        "consistency_a_tol": 10.0,
    },
    "maize": {"backend": "points", "splat_density": 1.0, "visibility_ratio": 0.1},
}


#: The paper's nerfacto settings per crop over ``SurfacesConfig``'s (its implementation details):
#: soybean nerfstudio's defaults, maize near/far planes 0.05/6.0 (nerfstudio's frame; the far
#: plane given wins over ``nerf_far_margin``), MLP width 128, 'vertical' orientation. The scene
#: flow applies them under the user's settings where the backend is nerfacto.
NERF_PAPER: dict[str, dict[str, Any]] = {
    "soybean": {},
    "maize": {"near_plane": 0.05, "far_plane": 6.0, "hidden_dim": 128, "orientation": "vertical"},
}


def resolve_bbox(bbox: Any, crop: str) -> np.ndarray | None:
    """``"auto"`` → the crop's :data:`SCENE_BOX`; None → None; else a checked (2, 3) box."""
    if bbox is None:
        return None
    if isinstance(bbox, str):
        if bbox != "auto":
            raise ConfigError(
                f"surfaces bbox must be 'auto', null or [[x,y,z],[x,y,z]], got {bbox!r}"
            )
        if crop not in SCENE_BOX:
            raise ConfigError(f"no scene box for crop {crop!r}: one of {', '.join(SCENE_BOX)}")
        return np.array(SCENE_BOX[crop], dtype=np.float64)
    box = _box(bbox)
    if box is None:
        raise ConfigError(f"surfaces bbox must be [min corner, max corner], got {bbox!r}")
    return box


def _box(bbox: Any) -> np.ndarray | None:
    """``bbox`` as a finite (2, 3) [min corner, max corner] with min < max, else None."""
    try:
        box = np.asarray(bbox, dtype=np.float64)
    except (TypeError, ValueError):
        return None
    if box.shape != (2, 3) or not np.all(np.isfinite(box)) or np.any(box[1] <= box[0]):
        return None
    return box


#: File every saved surface folder holds: backend name, config, cameras, backend metadata.
META_FILE = "surfaces.json"

#: ``progress(stage: str, fraction: float)``: called with fractions in [0, 1] during ``fit``.
Progress = Callable[[str, float], None]


class SurfacesError(CropCraftError, RuntimeError):
    """The surfaces stage cannot run (missing backend dependency, no GPU, fit failed)."""


#: nerfstudio-data's ``--orientation-method`` choices.
NERF_ORIENTATIONS = ("pca", "up", "vertical", "none")


@dataclass(frozen=True)
class SurfacesConfig:
    """Settings of the visible-surfaces stage. Unused fields are ignored by other backends."""

    backend: str = "tsdf"
    """'tsdf' (CPU multi-view stereo + TSDF fusion, the default), 'points' (the same stereo,
    its points filtered by visibility and splatted, no fusion), 'nerfacto' (nerfstudio, CUDA)
    or 'truth' (the true mesh, for tests and benchmarks). The settings marked tsdf that shape
    the stereo (neighbours to consistency_a_tol) apply to points too."""
    voxel_size: float = 0.0075
    """tsdf: TSDF voxel edge (m)."""
    trunc_voxels: float = 3.5
    """tsdf: truncation distance of the signed distance, in voxels. It sets how far a fused
    leaf's skirt reaches past its edge, and how much disagreement between the views' depths a
    thin leaf survives. With exact poses (two dense synthetic soybean scenes) the observation's
    mask area was 6–10 % too large with 4, within 2 % with 3, 13 % short with 2. With SfM poses
    (what the pipeline has; three SfM models of two scenes), 3 lost the top leaves' edges:
    mask area 6–9 % short, the nearest depth bin short by a fifth; 3.5 gave −2.6 / −0.3 /
    −1.2 %, 4 gave +2.6 / +4.0 / +3.6 %."""
    depth_range: tuple[float, float] | None = None
    """(near, far) z-depth searched by stereo and fused (m). None: per view, from the bounding
    box's corners (or (0.2, 8.0) without a box)."""
    neighbours: int = 4
    """tsdf: source views matched against each reference view (2–8)."""
    best_sources: int = 0
    """tsdf: a plane's matching score at a pixel is the mean NCC of this many best-scoring
    sources (fewer is more robust to a source that cannot see the pixel, noisier where all
    can); 0: half of the sources, rounded up."""
    mvs_scale: float = 0.75
    """tsdf: image scale for stereo (0.75: 640×480 photos are matched at 480×360). Measured on
    two dense synthetic soybean scenes (true poses; ``bench pipeline --poses truth``): the
    observation's depth-histogram L1 against the true mesh fell from 0.15 and 0.20 (0.5, with a
    4-voxel truncation) to 0.09 and 0.12 (0.75 with 3 voxels), for ~1.4× the stereo time; the
    matching window covers less of the leaf edges, so leaves fatten less. 1.0 (three draws of
    30 seeds each, through SfM, soybean's rule): mean |LAI error| 12.3 % against 15.6 % over
    the demo, the default canopy and a sparse one (D, LAI 0.58: 21.6 against 33.1 %; the demo
    3.6 points worse), but 1.76x the surfaces stage's seconds (462 s against 262 s alone on a
    slow host, photos to observation ~645 s against the issue's 480): not the default
    (benchmarks/RESULTS.md, *#scale-81*)."""
    mvs_max_side: int | None = 1024
    """tsdf: the longest side a photo is matched at, in pixels (its scale then below
    ``mvs_scale``). Stereo's cost volumes are ~3 x 4 bytes x ``n_depths`` a pixel: a phone's
    4000 x 3000 photo at 0.75 would take ~10 GiB a view; at 1024 x 768, 1.2 GiB. 640 x 480 photos
    (480 x 360 at 0.75) are not affected. None: no limit."""
    n_depths: int = 128
    """tsdf: depth hypotheses per view, uniform in inverse depth."""
    window: int = 5
    """tsdf: side of the NCC matching window (pixels at ``mvs_scale``, odd). A 5-pixel window
    on a leaf a few pixels wide matches the soil around it: on a sparse synthetic canopy (LAI
    0.58) an eighth of every photo's plant pixels hold the soil's depth, which carves the leaf
    out. 3 cuts those depths by a third (0.127 → 0.081 of the plant pixels) and the row view's
    lost leaves from 32.5 to 26.1 % (its L1 0.207 → 0.091; the default canopy's 0.285 → 0.197,
    with more holes), but fits (10 × 500, through SfM) read LAI −44.4 % against −49.2 % on
    the sparse canopy and +9.5 % against −1.3 % on the default one (benchmarks/RESULTS.md,
    *#window-78*): not adopted."""
    shiftable_windows: bool = False
    """tsdf: score a pixel by the best of the ``window``-sized windows that contain it (per
    source, a max filter of the centred windows' NCC), not only the window centred on it: a
    pixel of a low leaf seen through a gap can match on a window inside the gap rather than one
    that straddles the nearer leaf's edge. Measured with true poses (``bench pipeline``,
    soybean): on the closed canopy SC (LAI 3.66) the row view's holes fell from 10.7 to 6.5 %
    and the L1 from 0.363 to 0.292, but on the default canopy (LAI 1.26) the leaves fatten: mask
    area 0.62 → 0.68 against the truth's 0.61, L1 0.132 → 0.177, and fits (10 × 300) read
    the fattened leaves as bigger ones: SC +14.5 % (−18.2 % without), the default canopy
    +47.0 % (+6.6 %) (RESULTS, *Shiftable windows*). Off by default."""
    sweep: str = "horizontal"
    """tsdf: plane hypotheses: 'horizontal' (world planes z = h over the bounding box's height
    range, uniform in height: ground and near-horizontal leaves seen obliquely match on their own
    plane, and the smoothing favours flat surfaces; needs a bounding box, else fronto-parallel)
    or 'fronto' (fronto-parallel planes uniform in inverse depth over the view's depth range)."""
    sweep_heights: str = "box"
    """tsdf: the heights the horizontal planes span: 'box' (the bounding box's) or 'auto' (from
    just below the soil to just above the canopy, found by a coarse first stereo pass over the
    box's heights: ``tsdf.occupied_heights``, about a tenth more stereo time; soybean's
    default, ``CROP_SURFACES``)."""
    soil_a_min: float = 2.0
    """tsdf: ``sweep_heights='auto'`` finds the ground where points with CIELAB a* at least
    this (reddish-brown, not green) pile up: the row fit's soil rule (``rowfit`` presets'
    ``plant_a_below``; soybean 2)."""
    colour: bool = True
    """tsdf: match on RGB (the mean of the per-channel NCCs) rather than on grey."""
    sgm_p1: float = 0.05
    """tsdf: semi-global matching penalty for a one-plane step between neighbouring pixels."""
    sgm_p2: float = 0.3
    """tsdf: semi-global matching penalty for a larger jump (0: no smoothing)."""
    min_ncc: float = 0.4
    """tsdf: a depth is kept where its aggregated NCC matching score reaches this (−1 … 1)."""
    min_consistent: int = 1
    """tsdf: a depth is kept where at least this many other views' depth maps agree with it."""
    consistency_rel: float = 0.01
    """tsdf: relative z-depth tolerance of that agreement (0.01 = 1 %)."""
    consistency_a_tol: float | None = None
    """tsdf: where set, a view agrees with a depth only if its pixel there also has the colour
    of the depth's own pixel: CIELAB a* (green to red, the axis the row fit splits plant from
    soil by; brightness does not enter it) within this many units. A window on a thin leaf's
    edge can match the soil beside it, which the neighbours see too: geometry alone keeps that
    depth, and it carves the leaf out of the fused surface. None: geometry only."""
    weight_threshold: float = 1.0
    """tsdf: the extracted surface keeps a marching-cubes cell only where all 8 of its voxels have
    a fused weight *above* this (Open3D's rule): 1.0 = every voxel fused from two or more depth
    maps."""
    fill_one_view: bool = True
    """tsdf: where that surface leaves a ray empty, render the surface whose voxels each have at
    least one depth map (a second mesh, ``fill_faces``). Measured with true poses on three
    synthetic soybean canopies, the row camera at full resolution, fits of 10 seeds × 300
    evaluations (without → with the fill): row view without surface 11.6 → 7.7 % / 23.2 →
    16.4 % / 21.7 → 12.8 %, LAI read −5.4 → +9.1 % / −30.1 → −9.8 % / −46.4 → −25.5 % at true
    LAI 1.26 (default) / 2.32 / 3.66, depth-histogram L1 0.097 → 0.090 / 0.328 → 0.263 / 0.340
    → 0.321. What it adds is mostly coverage, not accurate depth: of its pixels above 0.1 m only
    14 % (LAI 1.26) and 24 % (LAI 3.66) lie within 2 cm of the true surface; most are the one-view
    skirts of leaf edges reaching into the gaps, in front of the low leaves there. Rendering the
    one-view surface everywhere instead (a weight threshold of 0) read +36 % and −13 % on the
    first and last canopies: its skirts also cover what the two-view surface shows."""
    carve_free_space: bool = False
    """tsdf: every depth map is fused into every voxel block that any depth map allocated, not
    only into the blocks near its own surfaces, so a view that sees past a surface another
    view put there (a leaf edge fattened by the matching window, reaching over the soil or a
    lower leaf) fuses free space into it (Open3D's kernel clips the signed distance in front of
    the surface at the truncation) and outvoted, it is carved away. Voxels hidden behind a
    view's surface by more than the truncation are left alone."""
    visibility_rel: float = 0.01
    """points: relative z-depth tolerance of the visibility check: another view agrees with a
    stereo point within it, and sees past the point beyond it."""
    visibility_ratio: float = 0.25
    """points: a stereo point is dropped where the views seeing past it outnumber this times the
    views agreeing with it (maize: 0.1, ``CROP_SURFACES``)."""
    splat_radius: float = 0.71
    """points: each point's disc radius in units of its pixel's side at its depth (0.71: the
    disc circumscribing the pixel's footprint)."""
    splat_density: float | None = None
    """points: cap each disc, in the rendered view, at this coverage / √(π ρ) pixels, ρ the
    points per pixel around it (``splat_density_window``): discs as large as the points' own
    spacing in that view rather than their source pixels' footprints (None: no cap)."""
    splat_density_window: int = 9
    """points: side (pixels) of the square in which ``splat_density`` counts the points."""
    splat_blend: float = 0.02
    """points: a rendered pixel averages the fragments within this relative depth of its
    nearest."""
    splat_close: int = 5
    """points: side of the neighbourhood closing the empty pixels between splats (≤ 1: off)."""
    nerf_iterations: int = 20000
    """nerfacto: training iterations (the paper: 20K)."""
    nerf_args: tuple[str, ...] = ()
    """nerfacto: further ``ns-train`` options, placed before the dataparser's, e.g.
    ``("--pipeline.model.camera-optimizer.mode", "off")`` for exactly known poses."""
    nerf_max_seconds: float | None = None
    """nerfacto: a deadline for training (s): past it training stops and the last checkpoint
    (saved every ``nerfacto.SAVE_EVERY`` steps) is used; the iterations reached are in
    ``timings['nerf_iterations_done']``. None: train all ``nerf_iterations``."""
    near_plane: float | None = None
    """nerfacto: near plane in nerfstudio's scaled frame (the paper's maize: 0.05; None: the
    nerfstudio default)."""
    far_plane: float | None = None
    """nerfacto: far plane in nerfstudio's own scaled frame (the paper's maize: 6.0). Where set
    it wins over ``nerf_far_margin``, and nerfstudio scales the poses itself."""
    nerf_far_margin: float | None = 1.5
    """nerfacto: the far plane at this margin times the farthest any camera is from the scene
    box (its corners), so ``fit`` needs a bounding box; CropCraft then fixes nerfstudio's scale
    (``nerfacto.pose_scale``) so that the plane is known in its frame. With nerfstudio's far
    plane (1000) nerfacto explained the default synthetic canopy's photos by a far backdrop
    (surfaces 14× too far); with a far plane at 1.1 or 1.5 times the scene's extent the views'
    median depth is right within 0.4 % and 91–92 % of the point cloud lies within 2 cm of a true
    surface (H200, 1,000 iterations: benchmarks/RESULTS.md#nerfacto-scene). 1.5 leaves a real
    scene's surroundings more room behind the plot. None: nerfstudio's far plane."""
    hidden_dim: int | None = None
    """nerfacto: MLP width (the paper's maize: 128; None: the nerfstudio default)."""
    orientation: str = "up"
    """nerfacto: nerfstudio-data ``--orientation-method`` (default 'up'; the paper's maize:
    'vertical')."""
    workdir: str | None = None
    """nerfacto: folder for its dataset, checkpoints and exports (None: a temporary folder)."""
    truth_mesh: str | None = None
    """truth: PLY of the true canopy mesh (used when ``make_backend`` gets no mesh)."""
    seed: int = 0
    """Seed of every random choice (point subsampling, nerfstudio's ``--machine.seed``)."""

    def __post_init__(self) -> None:
        if self.backend not in BACKENDS:
            raise ConfigError(
                f"unknown surfaces backend {self.backend!r}: choose one of {', '.join(BACKENDS)}"
            )
        for f in fields(self):  # each setting of the kind of its default (--set passes text)
            v, default = getattr(self, f.name), f.default
            if v is None and "None" in str(f.type):
                continue
            if isinstance(default, bool):
                ok, kind = isinstance(v, bool), "true or false"
            elif isinstance(default, int):
                ok = isinstance(v, int | np.integer) and not isinstance(v, bool)
                kind = "a whole number"
            elif isinstance(default, float):
                ok = isinstance(v, int | float) and not isinstance(v, bool) and np.isfinite(v)
                kind = "a finite number"
            else:
                ok, kind = True, ""
            if not ok:
                raise ConfigError(f"surfaces {f.name} must be {kind}, got {v!r}")
        if self.seed < 0:
            raise ConfigError(f"surfaces seed must be ≥ 0, got {self.seed}")
        if self.weight_threshold < 0:
            raise ConfigError(f"surfaces weight_threshold must be ≥ 0, got {self.weight_threshold}")
        for name in (
            "voxel_size", "trunc_voxels", "mvs_scale", "consistency_rel", "visibility_rel",
            "splat_radius", "splat_density", "consistency_a_tol",
        ):  # fmt: skip
            v = getattr(self, name)
            optional = name in ("splat_density", "consistency_a_tol")
            if optional and v is None:
                continue
            # bool is an int to isinstance; the optional ones have no default kind to refuse it
            number = isinstance(v, int | float) and not isinstance(v, bool)
            if not (number and np.isfinite(v) and v > 0):
                null = " or null" if optional else ""
                raise ConfigError(f"surfaces {name} must be a positive number{null}, got {v!r}")
        if self.mvs_max_side is not None and self.mvs_max_side < 32:
            raise ConfigError(
                f"surfaces mvs_max_side must be at least 32 pixels or null, got {self.mvs_max_side}"
            )
        if not 2 <= int(self.neighbours) <= 8:
            raise ConfigError(f"surfaces neighbours must be in [2, 8], got {self.neighbours}")
        if int(self.n_depths) < 8:
            raise ConfigError(f"surfaces n_depths must be ≥ 8, got {self.n_depths}")
        if self.sweep not in ("horizontal", "fronto"):
            raise ConfigError(
                f"surfaces sweep must be 'horizontal' or 'fronto', got {self.sweep!r}"
            )
        if self.sweep_heights not in ("auto", "box"):
            raise ConfigError(
                f"surfaces sweep_heights must be 'auto' or 'box', got {self.sweep_heights!r}"
            )
        if not (0 <= float(self.sgm_p1) <= float(self.sgm_p2) or float(self.sgm_p2) == 0):
            raise ConfigError(
                f"surfaces sgm penalties need 0 ≤ sgm_p1 ≤ sgm_p2, got {self.sgm_p1}, {self.sgm_p2}"
            )
        if not (float(self.visibility_ratio) >= 0 and float(self.splat_blend) >= 0):
            raise ConfigError(
                "surfaces visibility_ratio and splat_blend must be ≥ 0, got "
                f"{self.visibility_ratio}, {self.splat_blend}"
            )
        for name, least in (("window", 3), ("splat_density_window", 1)):
            v = int(getattr(self, name))
            if v < least or v % 2 == 0:
                raise ConfigError(f"surfaces {name} must be odd and ≥ {least}, got {v}")
        if not -1.0 <= self.min_ncc < 1.0:
            raise ConfigError(f"surfaces min_ncc must be in [-1, 1), got {self.min_ncc}")
        if int(self.best_sources) < 0:
            raise ConfigError(f"surfaces best_sources must be ≥ 0, got {self.best_sources}")
        if int(self.min_consistent) < 0:
            raise ConfigError(f"surfaces min_consistent must be ≥ 0, got {self.min_consistent}")
        if self.depth_range is not None:
            try:
                near, far = (float(x) for x in self.depth_range)
            except (TypeError, ValueError):
                raise ConfigError(
                    f"surfaces depth_range must be [near, far] in metres, got {self.depth_range!r}"
                ) from None
            if not (0 < near < far and np.isfinite(far)):
                raise ConfigError(f"surfaces depth_range must be 0 < near < far, got {near, far}")
            object.__setattr__(self, "depth_range", (near, far))
        if int(self.nerf_iterations) < 1:
            raise ConfigError(f"nerf_iterations must be ≥ 1, got {self.nerf_iterations}")
        if not isinstance(self.nerf_args, list | tuple):
            raise ConfigError(f"nerf_args must be a list of options, not {self.nerf_args!r}")
        object.__setattr__(self, "nerf_args", tuple(str(x) for x in self.nerf_args))

        def number(name: str, v: Any, ok: Callable[[float], bool], says: str) -> None:
            """An optional nerfacto number: None, or a finite number for which ``ok`` holds
            (refused here, not in ns-train on the GPU worker after the photos were sent)."""
            real = isinstance(v, int | float) and not isinstance(v, bool) and np.isfinite(v)
            if v is not None and not (real and ok(v)):
                raise ConfigError(f"surfaces {name} must be null or {says}, got {v!r}")

        number("nerf_max_seconds", self.nerf_max_seconds, lambda v: v > 0, "a number > 0")
        number("nerf_far_margin", self.nerf_far_margin, lambda v: v >= 1, "a number ≥ 1")
        number("near_plane", self.near_plane, lambda v: v >= 0, "a number ≥ 0")
        number("far_plane", self.far_plane, lambda v: v > 0, "a number > 0")
        if self.near_plane is not None and self.far_plane is not None:
            if not self.near_plane < self.far_plane:
                raise ConfigError(
                    f"surfaces near_plane {self.near_plane} must be below far_plane "
                    f"{self.far_plane}"
                )
        hd = self.hidden_dim
        if hd is not None and not (isinstance(hd, int) and not isinstance(hd, bool) and hd > 0):
            raise ConfigError(f"surfaces hidden_dim must be null or a whole number > 0, got {hd!r}")
        if self.orientation not in NERF_ORIENTATIONS:
            raise ConfigError(
                f"surfaces orientation must be one of {', '.join(NERF_ORIENTATIONS)} "
                f"(nerfstudio's --orientation-method), got {self.orientation!r}"
            )

    @classmethod
    def for_crop(cls, crop: str, **overrides: Any) -> SurfacesConfig:
        """The paper's settings per crop: soybean = nerfstudio defaults; maize = near/far planes
        0.05/6.0, MLP width 128, orientation 'vertical'. ``overrides`` win."""
        if crop not in NERF_PAPER:
            raise ConfigError(f"unknown crop {crop!r}: choose soybean or maize")
        return cls(**{**NERF_PAPER[crop], **overrides})

    def to_dict(self) -> dict:
        d = asdict(self)
        if d["depth_range"] is not None:
            d["depth_range"] = list(d["depth_range"])
        return d

    @classmethod
    def from_dict(cls, d: dict) -> SurfacesConfig:
        known = {f.name for f in fields(cls)}
        unknown = set(d) - known
        if unknown:
            raise ConfigError(f"unknown surfaces settings: {', '.join(sorted(unknown))}")
        d = dict(d)
        if d.get("depth_range") is not None:
            d["depth_range"] = tuple(d["depth_range"])
        return cls(**d)


def check_inputs(
    images: Sequence[np.ndarray], cameras: Sequence[PinholeCamera], bbox: Any
) -> tuple[list[np.ndarray], list[PinholeCamera], np.ndarray | None]:
    """Validate ``fit``'s arguments: images (H, W, 3) uint8 matching their camera's size, at least
    two views, bbox None or (2, 3) (min corner, max corner). Returns them as lists / an array."""
    imgs, cams = list(images), list(cameras)
    if len(imgs) != len(cams):
        raise InputError(f"{len(imgs)} images but {len(cams)} cameras")
    if len(cams) < 2:
        raise InputError(f"the surfaces stage needs at least 2 posed images, got {len(cams)}")
    for i, (im, cam) in enumerate(zip(imgs, cams, strict=True)):
        if not isinstance(cam, PinholeCamera):
            raise InputError(f"camera {i} is a {type(cam).__name__}, not a PinholeCamera")
        a = np.asarray(im)
        if a.dtype != np.uint8 or a.ndim != 3 or a.shape[2] != 3:
            raise InputError(f"image {i} must be (H, W, 3) uint8, got {a.dtype} {a.shape}")
        if a.shape[:2] != (cam.height, cam.width):
            raise InputError(
                f"image {i} is {a.shape[1]}×{a.shape[0]} but its camera is {cam.width}×{cam.height}"
            )
        imgs[i] = a
    box = None if bbox is None else _box(bbox)
    if bbox is not None and box is None:
        raise InputError(f"bbox must be (2, 3) [min corner, max corner], got {bbox!r}")
    return imgs, cams, box


def depth_limits(
    camera: PinholeCamera, bbox: np.ndarray | None, depth_range: tuple[float, float] | None
) -> tuple[float, float]:
    """(near, far) z-depth for ``camera``: ``depth_range`` if given; else the range of z-depths at
    which a 16 × 12 grid of the camera's pixel rays is inside the bounding box (near ≥ 5 cm);
    else (0.2, 8.0)."""
    if depth_range is not None:
        return float(depth_range[0]), float(depth_range[1])
    if bbox is None:
        return 0.2, 8.0
    small = camera.scaled(16 / camera.width) if camera.width > 16 else camera
    d = small.ray_directions(normalized=False).reshape(-1, 3)  # t = z-depth
    c = camera.center
    with np.errstate(divide="ignore", invalid="ignore"):
        t0 = (bbox[0] - c) / d
        t1 = (bbox[1] - c) / d
    lo = np.where(np.isnan(t0), -np.inf, np.minimum(t0, t1))
    hi = np.where(np.isnan(t1), np.inf, np.maximum(t0, t1))
    inside_axis = (d == 0) & (c >= bbox[0]) & (c <= bbox[1])
    lo = np.where(inside_axis, -np.inf, lo).max(axis=1)
    hi = np.where(inside_axis, np.inf, hi).min(axis=1)
    ok = (hi > lo) & (hi > 0.05)
    if not ok.any():
        raise InputError(
            f"the camera at {np.round(c, 3).tolist()} does not see the bounding box "
            f"{np.round(bbox, 3).tolist()}"
        )
    return max(0.05, float(lo[ok].min())), float(hi[ok].max())


#: Fewer photos than this are named as the likely cause where no two see the scene box: a
#: 3-photo date's poses levelled the plot 1 photo in view (session 90's soybean walk audit).
FEW_PHOTOS = 10


def views_in_box(
    names: Sequence[str], cameras: Sequence[PinholeCamera], bbox: np.ndarray | None
) -> list[int]:
    """The indices of the views whose camera sees some of the scene box (:func:`depth_limits`
    finds depths of it in front of the camera; every camera sees "no box"). A photo looking
    away from the plot (one more drone pass along the field, a walker's glance up it) has no
    depths of the box for the stereo, which :func:`depth_limits` refuses: it is left out by
    its caller. Fewer than two views seeing the box is an ``InputError`` naming the others."""
    keep = []
    for i, cam in enumerate(cameras):
        try:
            if bbox is not None:
                depth_limits(cam, bbox, None)
        except InputError:
            continue
        keep.append(i)
    if len(keep) < 2:
        away = [n for i, n in enumerate(names) if i not in keep]
        few = (
            f"; {len(cameras)} photos are too few to set a plot's frame from (its ground and "
            "scale): a walk around a plot takes ~50"
            if len(cameras) < FEW_PHOTOS
            else ""
        )
        raise InputError(
            f"only {len(keep)} of {len(cameras)} photos see the scene box "
            f"{np.round(bbox, 2).tolist()}: check surfaces.bbox and the poses' frame (photos "
            f"that do not: {', '.join(away[:8])}{', ...' if len(away) > 8 else ''}){few}"
        )
    return keep


class SurfaceBackend(ABC):
    """A fitted model of the visible surfaces of a scene."""

    #: the name ``SurfacesConfig.backend`` selects it by
    name: str = ""

    def __init__(self, config: SurfacesConfig | None = None) -> None:
        self.config = config or SurfacesConfig(backend=self.name or "tsdf")
        self.cameras: list[PinholeCamera] = []
        self.bbox: np.ndarray | None = None
        self.timings: dict[str, float] = {}

    @abstractmethod
    def fit(
        self,
        images: list[np.ndarray],
        cameras: list[PinholeCamera],
        bbox: np.ndarray | None = None,
        progress: Progress | None = None,
    ) -> None:
        """Fit the surfaces to posed photos.

        images: n (H, W, 3) uint8 RGB photos.  cameras: their n ``PinholeCamera`` poses (world
        frame, metres).  bbox: (2, 3) [min corner, max corner] of the region of interest (m), or
        None for no region: the stereo backends then search z-depths of 0.2-8 m in every view
        (``SurfacesConfig.depth_range`` sets others; a drone's 13 m needs one).  progress:
        optional ``progress(stage, fraction)``.
        """

    @abstractmethod
    def render(self, camera: PinholeCamera) -> tuple[np.ndarray, np.ndarray]:
        """(depth (H, W) float32 z-depth in metres, NaN where empty; rgb (H, W, 3) uint8) seen
        by ``camera``."""

    @property
    def edge_blur(self) -> float:
        """The scale (scene units, a Gaussian's standard deviation) over which these surfaces
        soften the leaves' depth near their edges: the observe stage blurs the fit's
        predictions by it (``ObservePreset.prediction_blur_m``, its ``auto`` setting).
        0 here: a backend's softening is taken as none until measured (tsdf's is)."""
        return 0.0

    def render_supported(self, camera: PinholeCamera) -> np.ndarray:
        """(H, W) float32 z-depth of only the surfaces the backend reconstructed with full
        support, NaN elsewhere: what ``render`` shows less whatever it filled in (tsdf: the fill
        from single depth maps). The share of NaN in it is the scene's coverage figure."""
        return self.render(camera)[0]

    @abstractmethod
    def point_cloud(self, n_max: int = 100_000) -> tuple[np.ndarray, np.ndarray]:
        """(points (n, 3) float64 metres, colors (n, 3) float64 in [0, 1]) on the visible
        surfaces inside the bounding box, n ≤ ``n_max`` (a seeded random subset if more)."""

    @abstractmethod
    def _save_payload(self, folder: Path) -> dict:
        """Write the backend's files into ``folder``; return metadata for ``surfaces.json``."""

    @abstractmethod
    def _load_payload(self, folder: Path, meta: dict) -> None:
        """Read back what ``_save_payload`` wrote."""

    @property
    def fitted(self) -> bool:
        return bool(self.cameras)

    def rendered_point_cloud(self, n_max: int = 100_000) -> tuple[np.ndarray, np.ndarray]:
        """``point_cloud`` for backends that only render (the paper samples its NeRF this way):
        every fitted view rendered at quarter size and unprojected, cropped to the bounding box,
        then a seeded subset of at most ``n_max``."""
        self._require_fitted()
        pts, cols = [], []
        for cam in self.cameras:
            small = cam.scaled(0.25)
            depth, rgb = self.render(small)
            ok = np.isfinite(depth)
            pts.append(small.unproject(depth)[ok])
            cols.append(rgb[ok].astype(np.float64) / 255.0)
        p, c = np.concatenate(pts), np.concatenate(cols)
        keep = in_bbox(p, self.bbox)
        return subsample(p[keep], c[keep], n_max, self.config.seed)

    def _require_fitted(self) -> None:
        if not self.fitted:
            raise SurfacesError(f"the {self.name} surfaces are not fitted: call fit() or load()")

    def save(self, folder: str | os.PathLike) -> Path:
        """Persist the fitted surface in ``folder`` (created): ``surfaces.json`` plus the backend's
        files. Returns the folder."""
        self._require_fitted()
        out = Path(folder)
        try:
            out.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise SurfacesError(f"cannot create {out}: {e}") from None
        payload = self._save_payload(out)
        meta = {
            "backend": self.name,
            "config": self.config.to_dict(),
            "cameras": [c.to_dict() for c in self.cameras],
            "bbox": None if self.bbox is None else self.bbox.tolist(),
            "timings_s": self.timings,
            "payload": payload,
            # the files this record was written with: a save over an earlier one that stopped
            # between its files and this record left one save's mesh under the other's cameras
            "files_sha256": _file_hashes(out, _payload_files(payload)),
        }
        tmp = out / f".{META_FILE}.{os.getpid()}.tmp"
        try:
            tmp.write_text(json.dumps(meta, indent=1), encoding="utf-8")
            os.replace(tmp, out / META_FILE)
        except OSError as e:
            tmp.unlink(missing_ok=True)
            raise SurfacesError(f"cannot write {out / META_FILE}: {e}") from None
        return out

    @classmethod
    def load(cls, folder: str | os.PathLike) -> SurfaceBackend:
        """Read a surface that ``save`` wrote (of this backend class)."""
        folder = Path(folder)
        meta = read_meta(folder)
        if meta.get("backend") != cls.name:
            raise InputError(
                f"{folder} holds {meta.get('backend')!r} surfaces, not {cls.name!r}: "
                "use load_surfaces()"
            )
        obj = cls.__new__(cls)
        where = Path(folder) / META_FILE
        try:
            SurfaceBackend.__init__(obj, SurfacesConfig.from_dict(meta["config"]))
            obj.cameras = [PinholeCamera.from_dict(c) for c in meta["cameras"]]
            obj.timings = dict(meta.get("timings_s") or {})
            payload = meta.get("payload") or {}
            if not isinstance(payload, dict):
                raise ValueError(f"payload is {type(payload).__name__}, not a mapping")
        except (CropCraftError, KeyError, TypeError, ValueError, AttributeError) as e:
            raise InputError(f"{where} is damaged: {type(e).__name__} {e}") from None
        obj.bbox = None if meta.get("bbox") is None else _box(meta["bbox"])
        if meta.get("bbox") is not None and obj.bbox is None:
            raise InputError(f"{where} is damaged: bbox {meta['bbox']!r}")
        if not obj.cameras:
            raise InputError(f"{where} is damaged: it holds no cameras")
        named = set(_payload_files(payload))
        recorded = {k: v for k, v in (meta.get("files_sha256") or {}).items() if k in named}
        if recorded != _file_hashes(folder, recorded):
            raise InputError(
                f"{folder}'s surface files are not the ones {META_FILE} records (changed since, or "
                "a save over an earlier one stopped before its record): fit and save them again"
            )
        obj._load_payload(folder, payload)
        return obj


def _payload_files(payload: Mapping[str, Any]) -> list[str]:
    """The file names a backend's saved payload record names (its text values)."""
    return [v for v in payload.values() if isinstance(v, str)]


def _file_hashes(folder: Path, names: Iterable[str]) -> dict[str, str]:
    """sha256 of each of the files ``names`` in ``folder`` that is there."""
    import hashlib

    out = {}
    for name in [n for n in names if (folder / n).is_file()]:
        h = hashlib.sha256()
        with open(folder / name, "rb") as f:
            for block in iter(lambda: f.read(1 << 20), b""):
                h.update(block)
        out[name] = h.hexdigest()
    return out


def read_meta(folder: Path) -> dict:
    p = Path(folder) / META_FILE
    try:
        meta = json.loads(p.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputError(f"{folder} holds no saved surfaces ({META_FILE} is missing)") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise InputError(f"cannot read {p}: {e}") from None
    if not isinstance(meta, dict):
        raise InputError(f"{p} is damaged: a {type(meta).__name__}, not a mapping")
    return meta


def make_backend(config: SurfacesConfig | None = None, mesh: Any = None) -> SurfaceBackend:
    """The backend ``config.backend`` names (default: tsdf).

    mesh: for 'truth' only, the true ``CanopyMesh`` (else ``config.truth_mesh`` is read).
    Raises ``ConfigError`` for an unknown backend, ``SurfacesError`` where nerfacto cannot run.
    """
    if config is None:
        config = SurfacesConfig()
    if isinstance(config, str):
        config = SurfacesConfig(backend=config)
    if not isinstance(config, SurfacesConfig):
        raise ConfigError(f"expected a SurfacesConfig, got {type(config).__name__}")
    if config.backend == "tsdf":
        from cropcraft_core.surfaces.tsdf import TsdfSurfaces

        return TsdfSurfaces(config)
    if config.backend == "points":
        from cropcraft_core.surfaces.points import PointSurfaces

        return PointSurfaces(config)
    if config.backend == "nerfacto":
        from cropcraft_core.surfaces.nerfacto import NerfactoSurfaces

        return NerfactoSurfaces(config)
    if config.backend == "truth":
        from cropcraft_core.surfaces.mesh_truth import TruthSurfaces

        return TruthSurfaces(mesh, config=config)
    raise ConfigError(  # unreachable: SurfacesConfig checks the name
        f"unknown surfaces backend {config.backend!r}: choose one of {', '.join(BACKENDS)}"
    )


def prediction_blur_m(backend: SurfaceBackend, scale: float, setting: Any = "auto") -> float:
    """The blur (metres) of a fit's predictions against an observation of ``backend``'s
    surfaces (``ObservePreset.prediction_blur_m``): ``setting`` ``"auto"`` = the backend's own
    :attr:`~SurfaceBackend.edge_blur` (scene units) times ``scale`` (metres per scene unit, the
    row fit's), or a number of metres (0: none, the paper's prediction)."""
    from cropcraft_core.observe import check_prediction_blur

    if check_prediction_blur(setting) == "auto":
        return float(backend.edge_blur) * float(scale)
    return float(setting)


def load_surfaces(folder: str | os.PathLike) -> SurfaceBackend:
    """Load saved surfaces of any backend from ``folder``."""
    meta = read_meta(Path(folder))
    name = meta.get("backend")
    if name == "tsdf":
        from cropcraft_core.surfaces.tsdf import TsdfSurfaces as cls
    elif name == "points":
        from cropcraft_core.surfaces.points import PointSurfaces as cls
    elif name == "nerfacto":
        from cropcraft_core.surfaces.nerfacto import NerfactoSurfaces as cls
    elif name == "truth":
        from cropcraft_core.surfaces.mesh_truth import TruthSurfaces as cls
    else:
        raise InputError(f"{folder} holds surfaces of an unknown backend {name!r}")
    return cls.load(folder)


def subsample(
    points: np.ndarray, colors: np.ndarray, n_max: int, seed: int
) -> tuple[np.ndarray, np.ndarray]:
    """A seeded random subset of at most ``n_max`` rows of points (n, 3) and colors (n, 3), in
    a canonical order (sorted by x, y, z, then colour): the same for any order of the same rows.

    Open3D's TSDF hands its marching-cubes vertices back in its hash map's order, which changes
    from run to run: two fits of the same photos gave the same 487,145 vertices in different
    orders, so a subset by index (and the row fit's seeded RANSAC over it) differed between
    reruns (the rows' scale −0.75 % on one, −1.42 % on the next)."""
    if isinstance(n_max, bool) or not isinstance(n_max, int | np.integer) or n_max < 0:
        raise ConfigError(f"n_max must be a whole number ≥ 0, got {n_max!r}")
    points, colors = np.asarray(points), np.asarray(colors)
    order = np.lexsort((*colors.T[::-1], *points.T[::-1]))  # last key first: x, y, z, colour
    if len(points) > n_max:
        rng = np.random.default_rng(seed)
        order = order[np.sort(rng.choice(len(points), size=n_max, replace=False))]
    return points[order], colors[order]


def in_bbox(points: np.ndarray, bbox: np.ndarray | None) -> np.ndarray:
    """(n,) bool: rows of points (n, 3) inside bbox (2, 3) (all True without a box)."""
    if bbox is None:
        return np.ones(len(points), bool)
    return np.all((points >= bbox[0]) & (points <= bbox[1]), axis=1)
