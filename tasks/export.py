"""Stage ``export``: the files a user takes away (meshes, Helios XML, parameters, metrics,
preview), as in ``cropcraft generate``'s bundle."""

from __future__ import annotations

from typing import Any

from tasks.common import Timer, artefact, key_of, make_record, open_store, stage_task, workdir
from tasks.generate import canopy_from_recipe


@stage_task("export")
def export(
    store_root: str,
    scene: str,
    config: dict[str, Any],
    upstream: dict[str, Any],
    lease: str | None = None,
) -> dict[str, Any]:
    """The bundle of ``cropcraft generate`` and ``cropcraft fit``
    (:func:`cropcraft_core.bundle.write_bundle_files`) for the generated canopy under
    ``{scene}/export/bundle/``: the plot mesh as ``canopy.ply`` / ``.obj`` (+ ``.mtl``) /
    ``.glb`` and ``canopy.helios.xml``, an oblique shaded ``preview.png``, ``params.json``
    (the recipe, ``params_std`` and the answer's fit record as ``fit``) and ``metrics.json``
    (the metrics stage's)."""
    from cropcraft_core.bundle import write_bundle_files

    store = open_store(store_root, scene=scene, lease=lease, what="export")
    recipe = store.get_json(key_of(upstream["generate"], "recipe"))
    values = store.get_json(key_of(upstream["metrics"], "metrics"))
    fit = store.get_json(key_of(upstream["aggregate"], "fit"))
    with Timer() as t, workdir("export") as tmp:
        extra = {"params_std": fit.get("params_std"), "fit": fit}
        write_bundle_files(canopy_from_recipe(recipe), tmp, values, extra)
        prefix = artefact(scene, "export", "bundle")
        hashes = store.put_tree(tmp, prefix)
    arts = {"bundle": prefix, **{k.rsplit("/", 1)[-1]: k for k in hashes}}
    return make_record("export", scene, arts, hashes, {"files": sorted(arts)}, t.seconds)
