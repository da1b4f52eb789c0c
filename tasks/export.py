"""Stage ``export``: the files a user takes away (meshes, Helios XML, parameters, metrics,
preview), as in ``cropcraft generate``'s bundle."""

from __future__ import annotations

import json
from typing import Any

from tasks.common import Timer, artefact, key_of, make_record, open_store, stage_task, workdir
from tasks.generate import canopy_from_recipe


@stage_task("export")
def export(
    store_root: str, scene: str, config: dict[str, Any], upstream: dict[str, Any]
) -> dict[str, Any]:
    """Write the generated canopy's plot mesh as ``canopy.ply`` / ``.obj`` (+ ``.mtl``) /
    ``.glb`` and ``canopy.helios.xml`` (``cropcraft_core.export``), an oblique shaded
    ``preview.png`` (``cropcraft_core.render.preview``), ``params.json`` (recipe and fit) and
    ``metrics.json`` (from the metrics stage) under ``{scene}/export/``."""
    from cropcraft_core.export import write_glb, write_helios_xml, write_obj, write_ply
    from cropcraft_core.render.preview import oblique_camera, save_png, shade_rgb

    store = open_store(store_root)
    recipe = store.get_json(key_of(upstream["generate"], "recipe"))
    values = store.get_json(key_of(upstream["metrics"], "metrics"))
    fit = store.get_json(key_of(upstream["aggregate"], "fit"))
    with Timer() as t, workdir("export") as tmp:
        canopy = canopy_from_recipe(recipe)
        plot = canopy.plot_mesh()
        write_ply(tmp / "canopy.ply", plot)
        write_obj(tmp / "canopy.obj", plot)
        write_glb(tmp / "canopy.glb", plot)
        write_helios_xml(tmp / "canopy.helios.xml", plot)
        lay = canopy.layout
        half = 0.5 * max(lay.plot_length, lay.plot_width)
        top = float(canopy.mesh.vertices[:, 2].max()) if canopy.mesh.n_faces else 0.5
        cam = oblique_camera((-half, half, -half, half), height=top)
        save_png(tmp / "preview.png", shade_rgb(canopy.mesh, cam))
        params = {**recipe, "params_std": fit.get("params_std"), "fit": fit.get("config")}
        (tmp / "params.json").write_text(json.dumps(params, indent=2, sort_keys=True) + "\n")
        (tmp / "metrics.json").write_text(json.dumps(values, indent=2, sort_keys=True) + "\n")
        prefix = artefact(scene, "export", "bundle")
        hashes = store.put_tree(tmp, prefix)
    arts = {"bundle": prefix, **{k.rsplit("/", 1)[-1]: k for k in hashes}}
    return make_record("export", scene, arts, hashes, {"files": sorted(arts)}, t.seconds)
