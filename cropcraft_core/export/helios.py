"""Helios (plant simulator) XML export.

Follows what Helios's ``Context::loadXML`` actually reads (checked against Helios
``core/src/Context_fileIO.cpp`` / ``Context_primitive.cpp`` and the ``pyhelios3d`` loader):

* root ``<helios>``; the file name must end in ``.xml`` (Helios accepts ``.xml`` / ``.XML`` only);
* one ``<triangle>`` per face whose geometry is ONLY its ``<transform>``: 16 floats, a row-major
  4×4 matrix T mapping Helios's unit triangle (0,0,0), (0,1,0), (1,1,0) onto the face, so
  column 0 = v2 − v1, column 1 = v1 − v0, translation (elements 3, 7, 11) = v0 and column 2 is any
  vector off the face plane; we write the unit face normal there, which keeps T invertible for
  every non-degenerate face (Helios's own writer uses (1,1,1) − v2, which can lie in the plane).
  ``<vertex>`` tags would be ignored; Helios stores floats, so 9 significant digits are written
  (float32 round-trips exactly);
* ``<color>r g b</color>`` and per-primitive data ``<data_string label="object_label">`` (``leaf``,
  ``petiole``, ``shoot`` for stems, as in Helios's plant models), ``<data_int label="plantID">``
  and ``<data_int label="nodeID">``;
* no ``<objID>``: the current loader rejects primitives whose objID has no object block.

Face order is kept: primitive i of the file (i-th UUID ``loadXML`` returns) is face i of the mesh
(after the optional ``plant_ids`` selection).
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Mapping
from pathlib import Path

import numpy as np

from cropcraft_core.errors import ConfigError, GeometryError
from cropcraft_core.export.atomic import atomic_path
from cropcraft_core.export.meshio import _check_mesh, _organ_colors
from cropcraft_core.geometry.mesh import CanopyMesh, Organ

__all__ = ["HELIOS_LABELS", "helios_transforms", "write_helios_xml"]

#: ``object_label`` written for each organ (Helios's plant-architecture vocabulary).
HELIOS_LABELS: dict[Organ, str] = {
    Organ.LEAF: "leaf",
    Organ.PETIOLE: "petiole",
    Organ.STEM: "shoot",
}

_CHUNK = 20_000  # triangles formatted per string operation (bounds memory, ~6 MB of text)


def helios_transforms(triangles: np.ndarray) -> np.ndarray:
    """Helios transformation matrices of triangles.

    triangles: (m, 3, 3) float corner coordinates v0, v1, v2.  Returns (m, 4, 4) float64 T with
    T @ (0,0,0,1) = v0, T @ (0,1,0,1) = v1, T @ (1,1,0,1) = v2 and column 2 the unit normal
    (+z for degenerate faces).
    """
    t = np.asarray(triangles, dtype=np.float64)
    v0, v1, v2 = t[:, 0], t[:, 1], t[:, 2]
    n = np.cross(v1 - v0, v2 - v0)
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    n = np.divide(n, norm, out=np.tile([0.0, 0.0, 1.0], (len(t), 1)), where=norm > 0)
    T = np.zeros((len(t), 4, 4))
    T[:, :3, 0] = v2 - v1
    T[:, :3, 1] = v1 - v0
    T[:, :3, 2] = n
    T[:, :3, 3] = v0
    T[:, 3, 3] = 1.0
    return T


def write_helios_xml(
    path: str | os.PathLike[str],
    mesh: CanopyMesh,
    plant_ids: Iterable[int] | None = None,
    colors: Mapping[Organ | int | str, tuple[float, float, float]] | np.ndarray | None = None,
) -> Path:
    """Write ``mesh`` as a Helios XML file of labelled triangles; return the path.

    plant_ids: export only the faces of these plants (``ConfigError`` if one is not in the mesh);
    None exports all.  colors: per-organ RGB in [0, 1] (keys ``Organ``, int or organ name;
    missing organs keep ``ORGAN_COLORS``) or an (m, 3) float array of per-face RGB in [0, 1].
    Raises ``ConfigError`` for a name not ending in ``.xml``, ``GeometryError`` for a mesh that
    cannot be written, ``OutputError`` if the file cannot be written.
    """
    out = Path(path)
    if out.suffix not in (".xml", ".XML"):
        raise ConfigError(f"Helios file name must end in .xml (Helios refuses others): {out}")
    _check_mesh(mesh)
    face_rgb: np.ndarray | None = None
    if isinstance(colors, np.ndarray):
        face_rgb = np.asarray(colors, dtype=np.float64)
        if face_rgb.shape != (mesh.n_faces, 3) or not np.all((face_rgb >= 0) & (face_rgb <= 1)):
            raise ConfigError(
                f"per-face colours must be ({mesh.n_faces}, 3) floats in [0, 1], "
                f"got shape {face_rgb.shape}"
            )
        organ_rgb = None
    else:
        organ_rgb = _organ_colors(colors)
    if plant_ids is not None:
        wanted = np.unique(np.fromiter((int(p) for p in plant_ids), dtype=np.int64))
        missing = np.setdiff1d(wanted, mesh.plant)
        if missing.size:
            raise ConfigError(f"plant ids {missing.tolist()} are not in the mesh")
        keep = np.isin(mesh.plant, wanted)
        if face_rgb is not None:
            face_rgb = face_rgb[keep]
        mesh = mesh.select(keep)
        if mesh.n_faces == 0:
            raise GeometryError("the selected plants have no faces to export")

    m = mesh.n_faces
    T = helios_transforms(mesh.triangles()) if m else np.zeros((0, 4, 4))
    floats = T[:, :3, :].reshape(m, 12)  # rows 0-2 of each matrix; row 3 is the constant 0 0 0 1
    f9 = " ".join(["%.9g"] * 12)
    head = "<triangle>\n\t<transform>" + f9 + " 0 0 0 1</transform>\n"
    tail = '\t<data_int label="plantID">%d</data_int>\n\t<data_int label="nodeID">%d</data_int>\n'
    tail += "</triangle>\n"
    if face_rgb is None:
        assert organ_rgb is not None
        blocks = np.empty(max(int(o) for o in Organ) + 1, dtype=object)
        for organ in Organ:
            r, g, b = organ_rgb[organ]
            blocks[int(organ)] = (
                f"\t<color>{r:.4g} {g:.4g} {b:.4g}</color>\n"
                f'\t<data_string label="object_label">{HELIOS_LABELS[organ]}</data_string>\n'
            )
        template = head + "%s" + tail
        cols = [floats, blocks[mesh.organ.astype(np.intp)][:, None]]
    else:
        labels = np.array([HELIOS_LABELS[o] for o in Organ], dtype=object)
        template = (
            head + "\t<color>%.4g %.4g %.4g</color>\n"
            '\t<data_string label="object_label">%s</data_string>\n' + tail
        )
        cols = [floats, face_rgb, labels[mesh.organ.astype(np.intp)][:, None]]
    cols += [mesh.plant[:, None], mesh.node[:, None]]
    width = sum(c.shape[1] for c in cols)

    with atomic_path(out) as tmp, open(tmp, "w", encoding="ascii", newline="\n") as f:
        f.write('<?xml version="1.0"?>\n<helios>\n')
        f.write(f"<!-- CropCraft canopy: {m} triangles, metres, z up -->\n")
        for s in range(0, m, _CHUNK):
            k = min(_CHUNK, m - s)
            table = np.empty((k, width), dtype=object)
            j = 0
            for c in cols:
                table[:, j : j + c.shape[1]] = c[s : s + k]
                j += c.shape[1]
            f.write((template * k) % tuple(table.ravel().tolist()))
        f.write("</helios>\n")
    return out
