"""One canopy → the files a user gets: meshes, Helios XML, parameters, metrics and a preview.

Everything is written into a temporary directory inside ``out_dir`` and moved into place only when
all of it succeeded, as one set (:func:`cropcraft_core.export.publish`: a failure part-way puts the
older bundle's files back), so ``out_dir`` never holds a half-written bundle or two canopies' files.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import shutil
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

from cropcraft_core.errors import OutputError
from cropcraft_core.procedural import Canopy, generate_canopy, plot_region

BUNDLE_FILES = (
    "canopy.ply",
    "canopy.obj",
    "canopy.mtl",
    "canopy.glb",
    "canopy.helios.xml",
    "params.json",
    "metrics.json",
    "preview.png",
)


def check_output_dir(out_dir: str | os.PathLike) -> Path:
    """Fail early (before any work) unless ``out_dir`` can be created and written; an empty
    path (an unset shell variable) is refused, not read as the current folder."""
    if not str(os.fspath(out_dir)).strip():
        raise OutputError("the output directory is an empty path: give --out a folder")
    out = Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
        probe = tempfile.NamedTemporaryFile(dir=out, prefix=".probe-", delete=True)
        probe.close()
    except OSError as e:
        raise OutputError(f"cannot write output directory {out}: {e.strerror or e}") from None
    return out


@contextlib.contextmanager
def output_dir(out_dir: str | os.PathLike) -> Iterator[Path]:
    """:func:`check_output_dir` for a command's whole run: where the run fails, the folders it
    created are removed again if they are still empty, so a mistyped option or a bad input
    leaves no empty ``--out`` behind (a folder that held anything before is never touched)."""
    out = Path(out_dir)
    made = [p for p in (out, *out.parents) if not p.exists()]  # deepest first
    checked = check_output_dir(out)
    try:
        yield checked
    except BaseException:
        for p in made:
            try:
                p.rmdir()  # only an empty folder
            except OSError:
                break
        raise


def gap_fraction_canopy(canopy: Canopy) -> Canopy:
    """The same plants with a border wide enough for gap-fraction rays at 68° zenith to stay
    inside the canopy (height · tan 68°, plus a row spacing because rows are discrete), capped at
    8 m. A plot whose wider border would pass ``MAX_PLANTS`` (a 39 m soybean plot) keeps its
    own: only the sensors near its edge see past it, and the reading's
    ``lai_gap_fraction_border_ok`` says so."""
    from cropcraft_core.procedural.canopy import MAX_PLANTS, plants_in_region

    height = float(canopy.mesh.vertices[:, 2].max()) if canopy.mesh.n_faces else 0.0
    border = min(8.0, height * math.tan(math.radians(68.0)) + 0.2 + canopy.layout.row_spacing)
    region = plot_region(canopy.layout, border)
    if all(abs(a) >= abs(b) for a, b in zip(canopy.info["region"], region, strict=True)):
        return canopy
    if plants_in_region(canopy.layout, region) > MAX_PLANTS:
        return canopy
    return generate_canopy(canopy.crop, canopy.params, canopy.layout, canopy.seed, region=region)


def measure_canopy(canopy: Canopy, gap_fraction: bool = True, rng: int | None = None) -> dict:
    """``canopy``'s metrics (:func:`cropcraft_core.metrics.canopy_metrics`), the gap-fraction
    rays cast through :func:`gap_fraction_canopy`'s wider border around the same plants (the
    plot's traits are the same plants' either way; ``n_faces_total`` is ``canopy``'s own).
    rng: the sensors' seed (None: the canopy's), so one canopy reads the same everywhere."""
    from cropcraft_core.metrics import canopy_metrics

    wide = gap_fraction_canopy(canopy) if gap_fraction else None
    return canopy_metrics(canopy, gap_fraction, rng, gap_canopy=wide)


def write_bundle_files(
    canopy: Canopy,
    folder: str | os.PathLike,
    metrics: dict,
    extra: dict | None = None,
    timings: dict[str, float] | None = None,
) -> dict:
    """Write :data:`BUNDLE_FILES` of ``canopy`` into ``folder`` (a staging folder: the files
    are written in place) with ``metrics`` as ``metrics.json`` and ``extra`` joined to
    ``params.json`` (crop, params, seed, layout, plants in the plot and in all); returns the
    metrics as written. ``timings``: seconds already spent (measuring): metrics.json then gets
    a ``timings`` block with the mesh files' and the preview's seconds added. ``cropcraft
    generate`` / ``fit`` and the scene flow's export stage write their bundles through this
    one function."""
    from cropcraft_core.export import write_glb, write_helios_xml, write_obj, write_ply
    from cropcraft_core.render.preview import oblique_camera, save_png, shade_rgb

    folder = Path(folder)
    t = time.perf_counter()
    # The files hold the plot's plants; the planted border (there only so that views and
    # gap-fraction rays see no edge) is rebuilt from params.json's parameters and seed.
    plot = canopy.plot_mesh()
    write_ply(folder / "canopy.ply", plot)
    write_obj(folder / "canopy.obj", plot)
    write_glb(folder / "canopy.glb", plot)
    write_helios_xml(folder / "canopy.helios.xml", plot)
    seconds = {"export_s": time.perf_counter() - t}
    t = time.perf_counter()
    lay = canopy.layout
    half = 0.5 * max(lay.plot_length, lay.plot_width)
    top = float(canopy.mesh.vertices[:, 2].max()) if canopy.mesh.n_faces else 0.5
    cam = oblique_camera((-half, half, -half, half), height=top)
    # the files' plants only: the planted border drew a field 3x the files' plot
    save_png(folder / "preview.png", shade_rgb(plot, cam))
    seconds["preview_s"] = time.perf_counter() - t
    if timings is not None:
        metrics = {**metrics, "timings": {**timings, **seconds}}
    params = {
        "crop": canopy.crop,
        "params": canopy.params,
        "seed": canopy.seed,
        "layout": lay.to_dict(),
        "plants_in_plot": canopy.n_plants,
        "plants_total": len(canopy.plant_in_plot),
        **(extra or {}),
    }
    for name, data in (("params.json", params), ("metrics.json", metrics)):
        text = json.dumps(data, indent=2, sort_keys=True, default=float) + "\n"
        (folder / name).write_text(text)
    return metrics


def write_bundle(
    canopy: Canopy,
    out_dir: str | os.PathLike,
    extra: dict | None = None,
    more_metrics: dict | None = None,
) -> dict:
    """Measure ``canopy`` and write every bundle file into ``out_dir``; returns the metrics.
    ``extra``: more of ``params.json``; ``more_metrics``: more of ``metrics.json`` (its
    ``definitions`` joined to the traits' own), e.g. the seeds' traits
    (:func:`cropcraft_core.metrics.seeds.seed_metrics`)."""
    from cropcraft_core.export import publish
    from cropcraft_core.metrics import join_metrics

    out = check_output_dir(out_dir)
    t = time.perf_counter()
    metrics = measure_canopy(canopy)
    if more_metrics:
        metrics = join_metrics(metrics, more_metrics)
    seconds = time.perf_counter() - t

    tmp = Path(tempfile.mkdtemp(dir=out, prefix=".bundle-"))
    try:
        metrics = write_bundle_files(canopy, tmp, metrics, extra, {"metrics_s": seconds})
        publish(tmp, out, BUNDLE_FILES)  # all files or none: never two canopies' side by side
    except OutputError:  # names its own file
        raise
    except OSError as e:
        raise OutputError(f"cannot write {out}: {e}") from None
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return metrics
