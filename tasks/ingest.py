"""Stage ``ingest``: photos at a folder/URL → checked, normalised images in the scene store."""

from __future__ import annotations

from typing import Any

from tasks.common import (
    Timer,
    artefact,
    core,
    make_record,
    open_store,
    stage_log,
    stage_task,
    workdir,
)


@stage_task("ingest")
def ingest(
    store_root: str,
    scene: str,
    config: dict[str, Any],
    upstream: dict[str, Any],
    images: str,
    lease: str | None = None,
) -> dict[str, Any]:
    """Run :func:`cropcraft_core.sfm.ingest_images` on ``images`` and store the result under
    ``{scene}/ingest/`` (``images/*.png`` and ``manifest.json``).

    config: ``max_size`` (longer image side, pixels, or None), ``min_images``.
    upstream: ``{"inputs": fingerprint of the photos}`` (cache identity only).
    """
    ingest_images = core("ingest", "cropcraft_core.sfm", "ingest_images")
    store = open_store(store_root, scene=scene, lease=lease, what="ingest")
    with Timer() as t, workdir("ingest") as tmp:
        manifest = ingest_images(
            images,
            tmp / "images",
            max_size=config.get("max_size"),
            min_images=int(config.get("min_images", 3)),
        )
        hashes = store.put_tree(tmp / "images", artefact(scene, "ingest", "images"))
        if manifest.in_subfolders:
            stage_log().warning(
                "ingest: %d photo(s) in subfolders of %s are not read: %s",
                len(manifest.in_subfolders), images, ", ".join(manifest.in_subfolders[:8]),
            )  # fmt: skip
    manifest_key = artefact(scene, "ingest", "images/manifest.json")
    # later stages key on the images and the manifest's content, not on where the photos were
    # read from: the same photos re-read (new mtimes, a copied inbox) leave SfM and on cached
    identity = {**hashes, manifest_key: manifest.identity()}
    return make_record(
        "ingest",
        scene,
        {"images": artefact(scene, "ingest", "images"), "manifest": manifest_key},
        hashes,
        {
            "n_images": len(manifest),
            "duplicates": len(manifest.duplicates),
            # each dropped copy, as "copy (= the photo kept)", for the run's summary
            **({"duplicate_names": copies} if (copies := _copies(manifest)) else {}),
            "ignored": len(manifest.ignored),
            # photos in subfolders, which ingest does not read: named, not lost quietly
            **({"in_subfolders": manifest.in_subfolders} if manifest.in_subfolders else {}),
            "n_focal_exif": sum(im.focal_px is not None for im in manifest.images),
            "size_px": [manifest.images[0].width, manifest.images[0].height],
        },
        t.seconds,
        identity=identity,
    )


def _copies(manifest: Any) -> list[str]:
    """The photos ingest dropped as exact copies of another, as ``"copy (= kept)"``."""
    return [f"{d['source']} (= {d['duplicate_of']})" for d in manifest.duplicates]
