"""How well the reconstructed surfaces agree with the photos, at the photos' own cameras.

No truth is needed: a photo is the one record of the plot a user has. For a few of the posed
photos, the surfaces are rendered from the photo's camera and compared pixel by pixel over the
plot (pixels whose ray meets the fitted ground plane inside the scene box):

* the photo's plant pixels by the row fit's colour rule (CIELAB a* below ``plant_a_below``:
  green), which cannot tell height, so green weeds, moss or greenish shadows on the soil count
  as plant;
* the reconstruction's surface at that pixel: none (a hole), low (within ``min_height`` of the
  ground) or raised.

Two shares, both of the photos' plant pixels, summarise it:

* ``unreconstructed``: the photo shows plant and the reconstruction has no surface at all
  there: leaves lost by the stereo or the fusion (typically low leaves seen through gaps);
* ``extra``: the reconstruction has a raised surface where the photo shows soil colour: leaf
  edges fattened past the leaf, skirts, floaters;

and ``net = extra − unreconstructed``. On five synthetic soybean canopies (true poses, the
flow's defaults; ``benchmarks/RESULTS.md#consistency``) ``net`` over 12 of their 50 photos read
+0.01 / −0.21 / −0.37 / +0.11 / −0.14 where the reconstruction's share of the LAI error (the
pipeline's error less a perfect reconstruction's from the same row camera) was +9 / −20 / −33
/ +11 / −6 points: cover lost or added in the photos' views pulls the fitted LAI low or high.
It says nothing of the method's own error from one row camera, which can cancel it or add to
it (the canopy at −0.21 read +4 % through the whole pipeline), nor of every error of the
reconstruction: on a sixth canopy net read +0.01 while the reconstruction moved its LAI +71
points (a small error that made two basins of the loss tie). A warning means cover lost or
added; its absence does not clear the reconstruction.
:data:`NET_WARN` holds, per crop, the share past which the scene's summary and report warn.
Maize has none: on one drone scene (true poses, the points backend) net read +0.16 (extra
0.17: splatted leaf edges over the soil between the thin leaves) while the reconstruction's
share of its LAI error was −14 points, so there the sign does not say which way the LAI moves.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence

import numpy as np

from cropcraft_core.errors import InputError
from cropcraft_core.geometry.camera import PinholeCamera
from cropcraft_core.surfaces.base import SurfacesError

#: Per crop, |net| at or above which a run warns that its reconstruction's cover disagrees with
#: its photos (soybean: on the five canopies above, the two at −0.21 and −0.37 lost 20 and 33
#: points of LAI through the reconstruction; the one at −0.14, 6 points); None: no warning
#: (maize, module docstring), the shares are still reported.
NET_WARN: dict[str, float | None] = {"soybean": 0.15, "maize": None}

#: Photos compared by default (evenly spaced over the posed photos; on the five canopies 12 of
#: 50 read ``net`` within 0.02 of all 50's, in about 2 s against 6 s).
MAX_VIEWS = 12

#: Height above the fitted ground (m) from which a reconstructed surface counts as raised.
MIN_HEIGHT_M = 0.02

Render = Callable[[PinholeCamera], tuple[np.ndarray, np.ndarray]]


@dataclasses.dataclass(frozen=True)
class PhotoConsistency:
    """The comparison's result (module docstring). Shares of the plot's pixels are in [0, 1];
    ``extra`` is over the photos' plant and can exceed 1 (a reconstruction twice the plant)."""

    views: tuple[int, ...]
    """Indices of the photos compared."""
    plot_pixels: int
    """Pixels compared (their ray meets the ground inside the scene box), over all views."""
    photo_plant: float
    """Share of the plot's pixels that the photos show as plant."""
    surface_raised: float
    """Share of the plot's pixels with a raised reconstructed surface."""
    holes: float
    """Share of the plot's pixels with no reconstructed surface."""
    unreconstructed: float | None
    """Photo plant without any reconstructed surface, over the photo plant (None: no plant)."""
    extra: float | None
    """Raised surface over photo soil, over the photo plant (None: no plant)."""
    per_view: tuple[dict, ...] = ()
    """Per view: ``index``, ``plot_pixels``, ``photo_plant``, ``unreconstructed``, ``extra``."""

    @property
    def net(self) -> float | None:
        """``extra − unreconstructed``: the reconstruction's cover against the photos'."""
        if self.extra is None or self.unreconstructed is None:
            return None
        return self.extra - self.unreconstructed

    def warning(self, limit: float | None = NET_WARN["soybean"]) -> str | None:
        """:func:`consistency_warning` of this result."""
        return consistency_warning(self.unreconstructed, self.extra, limit)

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["views"] = list(self.views)
        d["per_view"] = list(self.per_view)
        d["net"] = self.net
        return d


def consistency_warning(
    unreconstructed: float | None, extra: float | None, limit: float | None
) -> str | None:
    """A sentence for a run's summary and report when the net cover ``extra −
    unreconstructed`` is at least ``limit`` from zero, else None (also when either share or
    ``limit`` is None: :data:`NET_WARN`)."""
    if unreconstructed is None or extra is None or limit is None:
        return None
    net = extra - unreconstructed
    if abs(net) < limit:
        return None
    if net < 0:
        return (
            f"the reconstruction has no surface under {100 * unreconstructed:.1f} % of the "
            f"plant the photos show (net cover {100 * net:+.1f} % against the photos): leaves "
            "are lost, which pulls the fitted LAI low"
        )
    return (
        f"the reconstruction raises surface over soil on {100 * extra:.1f} % of the photos' "
        f"plant area (net cover {100 * net:+.1f} % against the photos): leaf edges are "
        "fattened, which pulls the fitted LAI high"
    )


def describe(unreconstructed: float, extra: float) -> str:
    """The shares in words, for the run's output, the report and the benchmark."""
    return (
        f"no surface under {100 * unreconstructed:.1f} % of the plant they show, raised "
        f"surface over their soil {100 * extra:.1f} % of it (net cover "
        f"{100 * (extra - unreconstructed):+.1f} %)"
    )


def _share(num: int, den: int) -> float | None:
    return None if den == 0 else num / den


def pick_views(n: int, max_views: int = MAX_VIEWS) -> tuple[int, ...]:
    """Up to ``max_views`` indices evenly spaced over ``n`` photos (first and last included)."""
    if n < 1:
        raise InputError("no photos to compare the reconstruction with")
    if max_views < 1:
        raise InputError(f"max_views must be at least 1, got {max_views}")
    return tuple(sorted({int(round(x)) for x in np.linspace(0, n - 1, min(n, max_views))}))


def photo_consistency(
    render: Render,
    images: Sequence[np.ndarray],
    cameras: Sequence[PinholeCamera],
    ground_normal: Sequence[float],
    ground_offset: float,
    *,
    scale: float = 1.0,
    bbox: np.ndarray | None = None,
    plant_a_below: float = 2.0,
    min_height_m: float = MIN_HEIGHT_M,
    views: Sequence[int] | None = None,
) -> PhotoConsistency:
    """Compare the surfaces' renders (``render(camera) -> (depth, rgb)``, z-depth in the
    surfaces' frame, not finite where there is no surface) with the photos ``images`` (H, W, 3)
    uint8 at their ``cameras``, over the plot (module docstring).

    ground_normal, ground_offset: the fitted ground plane ``n · p + offset = 0`` in the surfaces'
    frame (``RowFit.ground_normal`` / ``ground_offset``; n points to the plants); ``scale``:
    metres per unit of that frame (for ``min_height_m``); ``bbox``: (2, 3) scene box in that
    frame (its x–y extent bounds the plot; None: every pixel whose ray meets the ground);
    ``plant_a_below``: the row fit's colour rule; ``views``: the photos to compare (default
    :func:`pick_views`).
    """
    if len(images) != len(cameras):
        raise InputError(f"{len(images)} photos but {len(cameras)} cameras")
    n = np.asarray(ground_normal, np.float64)
    if n.shape != (3,) or not np.all(np.isfinite(n)) or not np.linalg.norm(n) > 0:
        raise InputError(f"ground_normal must be a finite non-zero 3-vector, got {ground_normal}")
    norm = float(np.linalg.norm(n))
    n, off = n / norm, float(ground_offset) / norm
    if not (np.isfinite(scale) and scale > 0):
        raise InputError(f"scale must be positive, got {scale}")
    box = None if bbox is None else np.asarray(bbox, np.float64)
    if box is not None and box.shape != (2, 3):
        raise InputError(f"bbox must be (2, 3) [min corner, max corner], got shape {box.shape}")
    from cropcraft_core.rowfit.lab import srgb_to_lab

    idx = pick_views(len(images)) if views is None else tuple(int(i) for i in views)
    if len(set(idx)) != len(idx) or any(not 0 <= i < len(images) for i in idx):
        raise InputError(f"views must be distinct photo indices in 0..{len(images) - 1}, got {idx}")
    min_h = float(min_height_m) / float(scale)
    tot = dict.fromkeys(("px", "plant", "raised", "holes", "unrec", "extra"), 0)
    per_view = []
    for i in idx:
        cam, img = cameras[i], np.asarray(images[i])
        if img.shape[:2] != (cam.height, cam.width) or img.ndim != 3:
            raise InputError(f"photo {i} is {img.shape} but its camera is {cam.width}×{cam.height}")
        dirs = cam.ray_directions(normalized=False)
        c = cam.center
        with np.errstate(divide="ignore", invalid="ignore"):
            t = -(c @ n + off) / (dirs @ n)
            g = c + t[..., None] * dirs
        plot = np.isfinite(t) & (t > 0)
        if box is not None:
            plot &= np.all((g[..., :2] >= box[0, :2]) & (g[..., :2] <= box[1, :2]), axis=-1)
        if not plot.any():
            continue
        depth, _ = render(cam)
        depth = np.asarray(depth, np.float64)
        if depth.shape != plot.shape:
            raise SurfacesError(f"the surfaces rendered {depth.shape} for a {plot.shape} photo")
        surf = np.isfinite(depth) & (depth > 0)
        with np.errstate(invalid="ignore"):
            h = (c + dirs * np.where(surf, depth, 0.0)[..., None]) @ n + off
        raised = surf & (h > min_h)
        plant = srgb_to_lab(img)[..., 1] < plant_a_below
        counts = {
            "px": int(plot.sum()),
            "plant": int((plant & plot).sum()),
            "raised": int((raised & plot).sum()),
            "holes": int((~surf & plot).sum()),
            "unrec": int((plant & ~surf & plot).sum()),
            "extra": int((raised & ~plant & plot).sum()),
        }
        for k, v in counts.items():
            tot[k] += v
        per_view.append(
            {
                "index": int(i),
                "plot_pixels": counts["px"],
                "photo_plant": counts["plant"] / counts["px"],
                "unreconstructed": _share(counts["unrec"], counts["plant"]),
                "extra": _share(counts["extra"], counts["plant"]),
            }
        )
    if tot["px"] == 0:
        raise SurfacesError(
            f"none of the {len(idx)} photos compared sees the ground inside the scene box: "
            "the ground plane or the box is off"
        )
    px = tot["px"]
    return PhotoConsistency(
        views=tuple(v["index"] for v in per_view),
        plot_pixels=px,
        photo_plant=tot["plant"] / px,
        surface_raised=tot["raised"] / px,
        holes=tot["holes"] / px,
        unreconstructed=_share(tot["unrec"], tot["plant"]),
        extra=_share(tot["extra"], tot["plant"]),
        per_view=tuple(per_view),
    )
