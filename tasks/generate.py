"""Stage ``generate``: the fitted procedural canopy (organ-labelled mesh) of the plot."""

from __future__ import annotations

from typing import Any

from tasks.common import Timer, artefact, key_of, make_record, open_store, stage_task, workdir
from tasks.fit_seed import layout_of


def canopy_from_recipe(recipe: dict[str, Any]):
    """Rebuild the canopy a ``generate`` recipe describes (deterministic: same plants, same
    mesh)."""
    from cropcraft_core.config import CanopyLayout
    from cropcraft_core.procedural import generate_canopy

    layout = CanopyLayout(**recipe["layout"])
    return generate_canopy(recipe["crop"], recipe["params"], layout, seed=int(recipe["seed"]))


@stage_task("generate")
def generate(
    store_root: str,
    scene: str,
    config: dict[str, Any],
    upstream: dict[str, Any],
    lease: str | None = None,
) -> dict[str, Any]:
    """:func:`cropcraft_core.procedural.generate_canopy` with the fitted parameters; stores the
    recipe (``canopy.json``: crop, params, seed, layout; later stages rebuild the identical
    canopy from it) and the plot's mesh (``canopy.ply``, per-face organ / plant / node).

    config: ``seed`` (canopy seed), ``layout`` (planting overrides).
    """
    from cropcraft_core.export import write_ply
    from cropcraft_core.procedural import generate_canopy

    store = open_store(store_root, scene=scene, lease=lease, what="generate")
    crop = scene.split("/")[1]
    fit = store.get_json(key_of(upstream["aggregate"], "fit"))
    with Timer() as t, workdir("generate") as tmp:
        layout = layout_of(crop, config)
        seed = int(config.get("seed", 0))
        canopy = generate_canopy(crop, fit["params"], layout, seed=seed)
        recipe = {"crop": crop, "params": canopy.params, "seed": seed, "layout": layout.to_dict()}
        hashes = {}
        rkey = artefact(scene, "generate", "canopy.json")
        hashes[rkey] = store.put_json(rkey, recipe)
        write_ply(tmp / "canopy.ply", canopy.plot_mesh())
        mkey = artefact(scene, "generate", "canopy.ply")
        hashes[mkey] = store.put_file(tmp / "canopy.ply", mkey)
    return make_record(
        "generate",
        scene,
        {"recipe": rkey, "mesh": mkey},
        hashes,
        {"n_plants": int(canopy.n_plants), "n_faces": int(canopy.plot_mesh().n_faces)},
        t.seconds,
    )
