"""Mesh files: PLY (read and write), OBJ and GLB (write).

PLY is the lossless interchange format of a ``CanopyMesh``: binary little-endian, vertex positions
as ``double`` (the mesh is float64; a float32 file would move a vertex 100 m from the origin by up
to 4 µm and break exact round trips and re-use of vertices across tools; it costs 12 extra bytes
per vertex, about 20 % of a canopy file), and per face ``organ`` (uchar ``Organ``), ``plant`` (int)
and ``node`` (int) next to the usual ``vertex_indices`` list. ``float32=True`` writes ``float``
positions for tools that cannot read doubles.

``read_ply``/``read_geometry`` read our files and generic PLY files (ASCII or binary of either
byte order; Open3D, MeshLab, CloudCompare, Blender): faces without labels become LEAF of plant 0,
node 0; polygons are fan-triangulated; a file without a face element is a point cloud
(``PointCloud``).

OBJ gets one group per organ (``g leaf`` / ``g petiole`` / ``g stem``) and, optionally, a ``.mtl``
with one diffuse colour per organ; plant and node ids are not stored. GLB (binary glTF 2.0, own
writer, no dependency) has one mesh node per organ with a double-sided PBR material of the organ
colour; glTF positions are float32 and glTF is y-up, so the z-up vertex data sits under a root node
rotated -90° about x (viewers show the canopy upright; the raw buffers keep our coordinates).

All writers go through ``atomic_path`` (no half-written files) and check the mesh first (finite
vertices, face indices in range, known organ labels) with ``GeometryError``.
"""

from __future__ import annotations

import json
import os
import re
import struct
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from cropcraft_core.errors import ConfigError, GeometryError, InputError
from cropcraft_core.export.atomic import atomic_path, atomic_write_text
from cropcraft_core.geometry.mesh import ORGAN_NAMES, CanopyMesh, Organ

__all__ = [
    "ORGAN_COLORS",
    "PointCloud",
    "read_geometry",
    "read_ply",
    "write_glb",
    "write_obj",
    "write_ply",
]

PathLike = str | os.PathLike[str]

#: Default display colour (linear RGB in [0, 1]) of each organ, shared by OBJ, GLB and Helios.
ORGAN_COLORS: dict[Organ, tuple[float, float, float]] = {
    Organ.LEAF: (0.18, 0.55, 0.14),
    Organ.PETIOLE: (0.55, 0.70, 0.25),
    Organ.STEM: (0.45, 0.55, 0.20),
}


@dataclass(frozen=True, eq=False)
class PointCloud:
    """Points read from a file without faces.

    points: (n, 3) float64 in the file's units.  colors: (n, 3) float64 in [0, 1] or None.
    normals: (n, 3) float64 or None.
    """

    points: np.ndarray
    colors: np.ndarray | None = None
    normals: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.points)


# --------------------------------------------------------------------------- checks / colours


def _check_mesh(mesh: CanopyMesh) -> None:
    """Raise ``GeometryError`` unless ``mesh`` can be written: finite, in range, known organs.

    Degenerate faces are allowed (``CanopyMesh.validate`` is stricter); they are written as is.
    """
    if not isinstance(mesh, CanopyMesh):
        raise GeometryError(f"expected a CanopyMesh, got {type(mesh).__name__}")
    if not np.all(np.isfinite(mesh.vertices)):
        raise GeometryError("cannot export a mesh with non-finite (NaN/inf) vertices")
    if mesh.n_faces and (mesh.faces.min() < 0 or mesh.faces.max() >= len(mesh.vertices)):
        raise GeometryError(
            f"cannot export a mesh whose faces index outside its {len(mesh.vertices)} vertices"
        )
    for name in ("plant", "node"):  # PLY stores them as int32, Helios as integers
        ids = np.asarray(getattr(mesh, name))
        if ids.shape != (mesh.n_faces,) or not np.issubdtype(ids.dtype, np.integer):
            raise GeometryError(
                f"cannot export face {name} ids of dtype {ids.dtype}, shape {ids.shape}: "
                f"one integer per face ({mesh.n_faces}) is needed"
            )
        if ids.size and (ids.min() < np.iinfo(np.int32).min or ids.max() > np.iinfo(np.int32).max):
            raise GeometryError(f"cannot export face {name} ids outside the 32-bit range")
    if not np.isin(mesh.organ, [int(o) for o in Organ]).all():
        bad = sorted(set(np.unique(mesh.organ).tolist()) - {int(o) for o in Organ})
        raise GeometryError(f"cannot export faces with unknown organ labels {bad}")


def _organ_colors(
    colors: Mapping[Organ | int | str, tuple[float, float, float]] | None,
) -> dict[Organ, tuple[float, float, float]]:
    """Per-organ RGB in [0, 1]: ``ORGAN_COLORS`` updated by ``colors`` (keys Organ, int or name)."""
    out = dict(ORGAN_COLORS)
    by_name = {name: organ for organ, name in ORGAN_NAMES.items()}
    for key, rgb in (colors or {}).items():
        try:
            organ = by_name[key] if isinstance(key, str) else Organ(int(key))
        except (KeyError, ValueError):
            raise ConfigError(
                f"unknown organ {key!r} in colours; use one of {sorted(by_name)}"
            ) from None
        c = np.asarray(rgb, dtype=np.float64)
        if c.shape != (3,) or not np.all((c >= 0) & (c <= 1)):
            raise ConfigError(
                f"colour of {ORGAN_NAMES[organ]} must be 3 floats in [0, 1], got {rgb}"
            )
        out[organ] = (float(c[0]), float(c[1]), float(c[2]))
    return out


# --------------------------------------------------------------------------- PLY writing


def write_ply(path: PathLike, mesh: CanopyMesh, *, float32: bool = False) -> Path:
    """Write ``mesh`` as binary little-endian PLY with per-face organ/plant/node; return the path.

    Vertex properties x, y, z (``double``, or ``float`` with ``float32``), metres, z up. Face
    properties: ``vertex_indices`` (list uchar int), ``organ`` (uchar), ``plant`` (int),
    ``node`` (int).
    """
    _check_mesh(mesh)
    if float32 and len(mesh.vertices):
        reach = float(np.abs(mesh.vertices).max())
        if reach > FLOAT32_REACH_M:  # read_ply refuses it: written so, the leaves are lost
            raise GeometryError(
                f"{path}: coordinates reach {reach:,.0f}, beyond what 32-bit floats resolve "
                f"(FLOAT32_REACH_M = {FLOAT32_REACH_M:,.0f}): write doubles, or subtract an "
                "offset near the plot first"
            )
    vtype, vdt = ("float", "<f4") if float32 else ("double", "<f8")
    n, m = len(mesh.vertices), mesh.n_faces
    header = (
        "ply\n"
        "format binary_little_endian 1.0\n"
        "comment CropCraft canopy mesh; units metres, z up\n"
        "comment organ: 0=leaf 1=petiole 2=stem\n"
        f"element vertex {n}\n"
        f"property {vtype} x\nproperty {vtype} y\nproperty {vtype} z\n"
        f"element face {m}\n"
        "property list uchar int vertex_indices\n"
        "property uchar organ\nproperty int plant\nproperty int node\n"
        "end_header\n"
    ).encode("ascii")
    verts = np.ascontiguousarray(mesh.vertices, dtype=vdt)
    face_dt = np.dtype(
        [("n", "u1"), ("v", "<i4", (3,)), ("organ", "u1"), ("plant", "<i4"), ("node", "<i4")]
    )
    rec = np.empty(m, dtype=face_dt)
    rec["n"] = 3
    rec["v"] = mesh.faces
    rec["organ"] = mesh.organ
    rec["plant"] = mesh.plant
    rec["node"] = mesh.node
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        f.write(header)
        f.write(verts.tobytes())
        f.write(rec.tobytes())
    return Path(path)


# --------------------------------------------------------------------------- PLY reading

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}  # fmt: skip


@dataclass
class _Prop:
    name: str
    dtype: str  # numpy type code without byte order, e.g. "f8"
    count_dtype: str | None = None  # list properties: type of the length prefix


@dataclass
class _Element:
    name: str
    count: int
    props: list[_Prop]


def _parse_header(data: bytes, path: Path) -> tuple[str, list[_Element], int]:
    """(format, elements, byte offset of the body) of a PLY file's bytes."""
    if not data.startswith(b"ply"):
        raise InputError(f"{path} is not a PLY file (it does not start with 'ply')")
    m = re.search(rb"(?:^|\n)end_header[ \t]*\r?\n", data[: 1 << 20])  # a line of its own
    if m is None:
        raise InputError(f"{path}: PLY header has no 'end_header' line")
    try:
        lines = data[: m.start()].decode("ascii").splitlines()
    except UnicodeDecodeError:
        raise InputError(f"{path}: PLY header is not ASCII text") from None
    fmt: str | None = None
    elements: list[_Element] = []
    for lineno, raw in enumerate(lines[1:], start=2):
        tok = raw.split()
        if not tok or tok[0] in ("comment", "obj_info"):
            continue
        try:
            if tok[0] == "format":
                fmt = tok[1]
                if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
                    raise InputError(f"{path}: unknown PLY format {fmt!r}")
            elif tok[0] == "element":
                count = int(tok[2])
                if count < 0:
                    raise ValueError("negative count")
                elements.append(_Element(tok[1], count, []))
            elif tok[0] == "property":
                if not elements:
                    raise ValueError("property before any element")
                if tok[1] == "list":
                    prop = _Prop(tok[4], _PLY_TYPES[tok[3]], _PLY_TYPES[tok[2]])
                else:
                    prop = _Prop(tok[2], _PLY_TYPES[tok[1]])
                elements[-1].props.append(prop)
            else:
                raise ValueError(f"unknown keyword {tok[0]!r}")
        except (IndexError, KeyError, ValueError) as e:
            raise InputError(f"{path}: malformed PLY header line {lineno} {raw!r} ({e})") from None
    if fmt is None:
        raise InputError(f"{path}: PLY header has no 'format' line")
    return fmt, elements, m.end()


def _record_dtype(el: _Element, bo: str, list_lens: list[int]) -> np.dtype:
    """Fixed-size record dtype of ``el`` assuming the given length for each list property."""
    fields: list[tuple] = []
    it = iter(list_lens)
    for i, p in enumerate(el.props):
        if p.count_dtype is None:
            fields.append((f"p{i}", bo + p.dtype))
        else:
            fields.append((f"n{i}", bo + p.count_dtype))
            fields.append((f"p{i}", bo + p.dtype, (next(it),)))
    return np.dtype(fields)


def _read_binary_element(
    data: bytes, offset: int, el: _Element, bo: str, path: Path
) -> tuple[dict[str, np.ndarray | list[np.ndarray]], int]:
    """Read one binary element at ``offset``; return {property: values} and the next offset.

    Scalar properties give (count,) arrays; a list property gives a (count, k) array when every
    record's list has the same length k, else a list of 1-d arrays.
    """

    def truncated() -> InputError:
        return InputError(f"{path}: PLY data ends inside element '{el.name}' (file truncated?)")

    list_idx = [i for i, p in enumerate(el.props) if p.count_dtype is not None]
    if el.count == 0:
        return {p.name: np.zeros((0, 3) if p.count_dtype else 0) for p in el.props}, offset
    # Lengths of the first record's lists, then assume every record looks alike.
    lens: list[int] = []
    pos = offset
    for p in el.props:
        if p.count_dtype is None:
            pos += np.dtype(p.dtype).itemsize
        else:
            cdt = np.dtype(bo + p.count_dtype)
            if pos + cdt.itemsize > len(data):
                raise truncated()
            k = _list_length(np.frombuffer(data, cdt, 1, pos)[0], el, path)
            lens.append(k)
            pos += cdt.itemsize + k * np.dtype(p.dtype).itemsize
            if pos > len(data):
                raise truncated()
    dt = _record_dtype(el, bo, lens)
    end = offset + el.count * dt.itemsize
    uniform = False
    if end <= len(data):
        rec = np.frombuffer(data, dt, el.count, offset)
        uniform = all(np.all(rec[f"n{i}"] == k) for i, k in zip(list_idx, lens, strict=True))
    elif not list_idx:
        raise truncated()
    if uniform or not list_idx:
        return {p.name: rec[f"p{i}"] for i, p in enumerate(el.props)}, end
    # Mixed list lengths (polygon soup): record by record.
    out: dict[str, list] = {p.name: [] for p in el.props}
    pos = offset
    for _ in range(el.count):
        for p in el.props:
            if p.count_dtype is None:
                dtp = np.dtype(bo + p.dtype)
                if pos + dtp.itemsize > len(data):
                    raise truncated()
                out[p.name].append(np.frombuffer(data, dtp, 1, pos)[0])
                pos += dtp.itemsize
            else:
                cdt, vdt = np.dtype(bo + p.count_dtype), np.dtype(bo + p.dtype)
                if pos + cdt.itemsize > len(data):
                    raise truncated()
                k = _list_length(np.frombuffer(data, cdt, 1, pos)[0], el, path)
                pos += cdt.itemsize
                if pos + k * vdt.itemsize > len(data):
                    raise truncated()
                out[p.name].append(np.frombuffer(data, vdt, k, pos))
                pos += k * vdt.itemsize
    res: dict[str, np.ndarray | list[np.ndarray]] = {}
    for p in el.props:
        res[p.name] = out[p.name] if p.count_dtype else np.asarray(out[p.name])
    return res, pos


def _read_ascii_elements(
    body: bytes, elements: list[_Element], path: Path
) -> dict[str, dict[str, np.ndarray | list[np.ndarray]]]:
    """Read every element of an ASCII PLY body (whitespace-separated tokens)."""
    tokens = body.split()
    pos = 0
    result: dict[str, dict[str, np.ndarray | list[np.ndarray]]] = {}

    def num(tok: list[bytes], what: str) -> np.ndarray:
        try:
            return np.array(tok, dtype=np.float64) if tok else np.zeros(0)
        except ValueError:
            raise InputError(f"{path}: non-numeric value in PLY element '{what}'") from None

    for el in elements:
        has_list = any(p.count_dtype for p in el.props)
        if not has_list:
            k = len(el.props)
            vals = num(tokens[pos : pos + el.count * k], el.name)
            if vals.size != el.count * k:
                raise InputError(f"{path}: PLY data ends inside element '{el.name}'")
            vals = vals.reshape(el.count, k)
            pos += el.count * k
            res = {p.name: vals[:, i] for i, p in enumerate(el.props)}
            result[el.name] = _declared_types(res, el, path)
            continue
        # Records with lists: try "every record like the first", else go record by record.
        res: dict[str, np.ndarray | list[np.ndarray]] | None = None
        if el.count:
            rec_len, q, lens = 0, pos, []
            try:
                for p in el.props:
                    if p.count_dtype is None:
                        rec_len += 1
                        q += 1
                    else:
                        k = _list_length(int(tokens[q]), el, path)
                        lens.append(k)
                        rec_len += 1 + k
                        q += 1 + k
            except InputError:
                raise
            except (IndexError, ValueError):
                raise InputError(f"{path}: malformed PLY element '{el.name}'") from None
            block = tokens[pos : pos + el.count * rec_len]
            if len(block) == el.count * rec_len:
                vals = num(block, el.name).reshape(el.count, rec_len)
                col, ok, res = 0, True, {}
                it = iter(lens)
                for p in el.props:
                    if p.count_dtype is None:
                        res[p.name] = vals[:, col]
                        col += 1
                    else:
                        k = next(it)
                        ok &= bool(np.all(vals[:, col] == k))
                        res[p.name] = vals[:, col + 1 : col + 1 + k]
                        col += 1 + k
                if ok:
                    pos += el.count * rec_len
                else:
                    res = None
        else:
            res = {p.name: np.zeros((0, 3) if p.count_dtype else 0) for p in el.props}
        if res is None:
            out: dict[str, list] = {p.name: [] for p in el.props}
            try:
                for _ in range(el.count):
                    for p in el.props:
                        if p.count_dtype is None:
                            out[p.name].append(float(tokens[pos]))
                            pos += 1
                        else:
                            k = _list_length(int(tokens[pos]), el, path)
                            out[p.name].append(num(tokens[pos + 1 : pos + 1 + k], el.name))
                            if len(out[p.name][-1]) != k:
                                raise IndexError
                            pos += 1 + k
            except InputError:
                raise
            except (IndexError, ValueError):
                raise InputError(f"{path}: PLY data ends inside element '{el.name}'") from None
            res = {
                p.name: (out[p.name] if p.count_dtype else np.asarray(out[p.name]))
                for p in el.props
            }
        result[el.name] = _declared_types(res, el, path)
    return result


def _list_length(value: Any, el: _Element, path: Path) -> int:
    """A list property's length prefix, refused when negative (a damaged file)."""
    k = int(value)
    if k < 0:
        raise InputError(f"{path}: negative list length {k} in PLY element '{el.name}'")
    return k


def _declared_types(
    res: dict[str, np.ndarray | list[np.ndarray]], el: _Element, path: Path
) -> dict[str, np.ndarray | list[np.ndarray]]:
    """An ASCII element's integer properties (read as float64) in their declared types, as a
    binary file gives them: colours keep their scale (uchar / 255, ushort / 65535)."""
    for p in el.props:
        if p.count_dtype is not None or np.dtype(p.dtype).kind not in "iu":
            continue
        v = np.asarray(res[p.name], dtype=np.float64)
        info = np.iinfo(p.dtype)
        if v.size and not (
            np.all(v == np.round(v)) and v.min() >= info.min and v.max() <= info.max
        ):
            raise InputError(
                f"{path}: PLY property '{p.name}' of element '{el.name}' is declared "
                f"{np.dtype(p.dtype).name} but holds other values"
            )
        res[p.name] = v.astype(p.dtype)
    return res


def _read_ply_elements(path: Path) -> dict[str, dict[str, np.ndarray | list[np.ndarray]]]:
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise InputError(f"PLY file {path} does not exist") from None
    except OSError as e:
        raise InputError(f"cannot read PLY file {path}: {e}") from e
    fmt, elements, body = _parse_header(data, path)
    if fmt == "ascii":
        return _read_ascii_elements(data[body:], elements, path)
    bo = "<" if fmt == "binary_little_endian" else ">"
    result = {}
    offset = body
    for el in elements:
        result[el.name], offset = _read_binary_element(data, offset, el, bo, path)
    return result


def _triangulate(lists: np.ndarray | list[np.ndarray], path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Fan-triangulate polygons: (faces (t, 3) int64, source polygon index (t,))."""
    if isinstance(lists, np.ndarray):
        m, k = lists.shape
        if m and k < 3:
            raise InputError(f"{path}: PLY faces have {k} vertices; at least 3 are needed")
        if k == 3:
            return lists.astype(np.int64), np.arange(m)
        idx = np.arange(1, k - 1)
        tri = np.stack(
            [np.repeat(lists[:, :1], k - 2, axis=1), lists[:, idx], lists[:, idx + 1]], axis=2
        )
        return tri.reshape(-1, 3).astype(np.int64), np.repeat(np.arange(m), k - 2)
    faces, src = [], []
    for j, poly in enumerate(lists):
        if len(poly) < 3:
            raise InputError(
                f"{path}: PLY face {j} has {len(poly)} vertices; at least 3 are needed"
            )
        for i in range(1, len(poly) - 1):
            faces.append((poly[0], poly[i], poly[i + 1]))
            src.append(j)
    return np.asarray(faces, dtype=np.int64).reshape(-1, 3), np.asarray(src, dtype=np.int64)


def _colors(vertex: dict, path: Path) -> np.ndarray | None:
    for names in (
        ("red", "green", "blue"),
        ("r", "g", "b"),
        ("diffuse_red", "diffuse_green", "diffuse_blue"),
    ):
        if all(n in vertex for n in names):
            c = np.stack([np.asarray(vertex[n]) for n in names], axis=1)
            if np.issubdtype(c.dtype, np.floating) and c.size and c.max() <= 1.0:
                return c.astype(np.float64)
            if c.dtype == np.uint16:
                return c.astype(np.float64) / 65535.0
            return c.astype(np.float64) / 255.0
    return None


#: Largest coordinate a PLY may store as 32-bit floats (float32 resolves 8 mm at 100 km,
#: 0.5 m at 4,000 km: a georeferenced plot in float32 has lost its leaves).
FLOAT32_REACH_M = 100_000.0


def read_geometry(path: PathLike, empty_faces_as_points: bool = True) -> CanopyMesh | PointCloud:
    """Read a PLY file: a ``CanopyMesh`` if it has a face element, else a ``PointCloud``; with
    ``empty_faces_as_points`` a face element of no faces (MeshLab's and scanners' point clouds)
    is read as a point cloud too.

    Face labels come from the face properties ``organ``/``plant``/``node`` when present (our
    files); otherwise every face is LEAF, plant 0, node 0. Raises ``InputError`` naming the file
    for a missing, truncated or malformed file, bad indices or unknown organ labels.
    """
    p = Path(path)
    elements = _read_ply_elements(p)
    vertex = elements.get("vertex")
    if vertex is None or not all(k in vertex for k in ("x", "y", "z")):
        raise InputError(f"{p}: PLY file has no vertex element with x, y, z")
    if any(isinstance(vertex[k], list) for k in ("x", "y", "z")):
        raise InputError(f"{p}: PLY vertex coordinates must be scalar properties")
    single = [  # either byte order: a big-endian '>f4' is not np.float32 to ==
        k for k in ("x", "y", "z") if np.asarray(vertex[k]).dtype.newbyteorder("=") == np.float32
    ]
    xyz = np.stack([np.asarray(vertex[k], dtype=np.float64) for k in ("x", "y", "z")], axis=1)
    if single:
        stored = np.abs(xyz[:, [("x", "y", "z").index(k) for k in single]])
        # finite values only: an inf (a scanner's empty return, as NaN is) is not a reach
        reach = float(np.max(stored, where=np.isfinite(stored), initial=0))
        if reach > FLOAT32_REACH_M:
            step = float(np.spacing(np.float32(reach)))
            raise InputError(
                f"{p}: coordinates stored as 32-bit floats reach {reach:,.0f}, where they "
                f"resolve only {step:.3g} (a georeferenced survey?): write them as doubles, "
                "or subtract an offset near the plot first"
            )
    face = elements.get("face")
    no_faces = face is not None and not len(
        face.get("vertex_indices", face.get("vertex_index", [1]))
    )
    if empty_faces_as_points and no_faces:
        face = None  # an empty face element (some scanners write one): a point cloud
    if face is None:
        normals = None
        if all(k in vertex for k in ("nx", "ny", "nz")):
            normals = np.stack([np.asarray(vertex[k], np.float64) for k in ("nx", "ny", "nz")], 1)
        return PointCloud(points=xyz, colors=_colors(vertex, p), normals=normals)
    key = next((k for k in ("vertex_indices", "vertex_index") if k in face), None)
    if key is None:
        raise InputError(f"{p}: PLY face element has no vertex_indices list")
    faces, src = _triangulate(face[key], p)
    if faces.size and (faces.min() < 0 or faces.max() >= len(xyz)):
        raise InputError(f"{p}: PLY faces index outside the {len(xyz)} vertices")
    labels = {}
    for name, default in (("organ", int(Organ.LEAF)), ("plant", 0), ("node", 0)):
        if name in face and not isinstance(face[name], list):
            labels[name] = np.asarray(face[name])[src]
        else:
            labels[name] = np.full(len(faces), default)
    organ = labels["organ"]
    if not np.isin(organ, [int(o) for o in Organ]).all():
        bad = sorted(set(np.unique(organ).tolist()) - {int(o) for o in Organ})
        raise InputError(
            f"{p}: PLY faces carry unknown organ labels {bad} (0 leaf, 1 petiole, 2 stem)"
        )
    return CanopyMesh(
        vertices=xyz,
        faces=faces.astype(np.int32),
        organ=organ.astype(np.uint8),
        plant=labels["plant"].astype(np.int32),
        node=labels["node"].astype(np.int32),
    )


def read_ply(path: PathLike) -> CanopyMesh:
    """Read a PLY mesh as a ``CanopyMesh`` (see ``read_geometry``; an empty face element is a
    mesh of no faces); a point cloud is an error."""
    geom = read_geometry(path, empty_faces_as_points=False)
    if isinstance(geom, PointCloud):
        raise InputError(
            f"{path} is a point cloud ({len(geom)} points, no faces); read it with read_geometry"
        )
    return geom


# --------------------------------------------------------------------------- OBJ


def write_obj(
    path: PathLike,
    mesh: CanopyMesh,
    *,
    mtl: bool = True,
    decimals: int = 6,
    colors: Mapping[Organ | int | str, tuple[float, float, float]] | None = None,
) -> Path:
    """Write ``mesh`` as Wavefront OBJ with one group per organ; return the path.

    Layout: ``v`` lines for all vertices (``decimals`` digits after the point, 6 = 1 µm), then for
    each organ present ``g <organ>`` (+ ``usemtl <organ>``) and its faces (1-based, in the
    mesh's face order). With ``mtl`` a ``<stem>.mtl`` next to the file holds one ``Kd`` colour per
    organ (``ORGAN_COLORS`` updated by ``colors``). Plant and node ids are not stored (use PLY).
    """
    _check_mesh(mesh)
    rgb = _organ_colors(colors)
    out = Path(path)
    if not 0 <= decimals <= 12:
        raise ConfigError(f"decimals must be in 0..12, got {decimals}")
    mtl_path = out.with_suffix(".mtl")
    head = [
        "# CropCraft canopy: units metres, z up; groups by organ",
        f"# {len(mesh.vertices)} vertices, {mesh.n_faces} faces",
    ]
    if mtl:
        head.append(f"mtllib {mtl_path.name}")
    order = np.argsort(mesh.organ, kind="stable")
    organs_sorted = mesh.organ[order]
    with atomic_path(out) as tmp, open(tmp, "w", encoding="ascii", newline="\n") as f:
        # the materials before the OBJ replaces its old self: never an OBJ naming a missing .mtl
        if mtl:
            lines = ["# CropCraft organ materials"]
            for organ, (r, g, b) in rgb.items():
                lines += [
                    f"newmtl {ORGAN_NAMES[organ]}",
                    f"Kd {r:.4f} {g:.4f} {b:.4f}",
                    "Ka 0 0 0",
                    "Ks 0 0 0",
                    "d 1",
                    "illum 1",
                    "",
                ]
            atomic_write_text(mtl_path, "\n".join(lines))
        f.write("\n".join(head) + "\n")
        vfmt = f"v %.{decimals}f %.{decimals}f %.{decimals}f\n"
        chunk = 100_000
        for s in range(0, len(mesh.vertices), chunk):
            v = mesh.vertices[s : s + chunk]
            f.write((vfmt * len(v)) % tuple(v.ravel().tolist()))
        for organ in Organ:
            lo, hi = np.searchsorted(organs_sorted, [int(organ), int(organ) + 1])
            if hi == lo:
                continue
            name = ORGAN_NAMES[organ]
            f.write(f"g {name}\n" + (f"usemtl {name}\n" if mtl else ""))
            for s in range(lo, hi, chunk):
                tri = mesh.faces[order[s : min(s + chunk, hi)]].astype(np.int64) + 1
                f.write(("f %d %d %d\n" * len(tri)) % tuple(tri.ravel().tolist()))
    return out


# --------------------------------------------------------------------------- GLB

_GLB_MAGIC, _GLB_JSON, _GLB_BIN = 0x46546C67, 0x4E4F534A, 0x004E4942
_Y_UP = [-0.7071067811865476, 0.0, 0.0, 0.7071067811865476]  # quaternion xyzw: -90° about x


def write_glb(
    path: PathLike,
    mesh: CanopyMesh,
    *,
    colors: Mapping[Organ | int | str, tuple[float, float, float]] | None = None,
) -> Path:
    """Write ``mesh`` as binary glTF 2.0: one node/mesh/material per organ present; return path.

    Each organ's faces become one triangle primitive with its own compacted float32 POSITION
    accessor (z-up metres) and uint32 indices; the organ nodes hang under a root node ``canopy``
    rotated into glTF's y-up frame. Materials are double-sided, non-metallic, with the organ
    colour (``ORGAN_COLORS`` updated by ``colors``). Plant and node ids are not stored. A
    canopy beyond ``FLOAT32_REACH_M`` (georeferenced) is stored about its rounded centre, given
    in z-up metres as the asset's ``extras.offset_m``.
    """
    _check_mesh(mesh)
    rgb = _organ_colors(colors)
    # float32 positions resolve 8 mm at 100 km: a georeferenced canopy is stored about its
    # centre (a UTM leaf had no area left), recorded in the root node's extras; a translation
    # would bring the loss back in every viewer that composes it in float32
    far = len(mesh.vertices) and float(np.abs(mesh.vertices).max()) > FLOAT32_REACH_M
    offset = np.round(mesh.vertices.mean(axis=0)) if far else np.zeros(3)
    blob = bytearray()
    gltf: dict = {
        "asset": {"version": "2.0", "generator": "CropCraft"},
        "scene": 0,
        "scenes": [{"name": "canopy", "nodes": [0]}],
        "nodes": [{"name": "canopy", "rotation": _Y_UP, "children": []}],
        **({"extras": {"offset_m": offset.astype(float).tolist()}} if far else {}),
        "meshes": [],
        "materials": [],
        "accessors": [],
        "bufferViews": [],
    }

    def add_view(arr: np.ndarray, target: int) -> int:
        gltf["bufferViews"].append(
            {"buffer": 0, "byteOffset": len(blob), "byteLength": arr.nbytes, "target": target}
        )
        blob.extend(arr.tobytes())  # float32/uint32 data keeps every offset 4-byte aligned
        return len(gltf["bufferViews"]) - 1

    for organ in Organ:
        mask = mesh.organ == int(organ)
        if not mask.any():
            continue
        sub = mesh.select(mask)
        pos = np.ascontiguousarray(sub.vertices - offset, dtype="<f4")
        idx = np.ascontiguousarray(sub.faces.ravel(), dtype="<u4")
        gltf["accessors"].append(
            {
                "bufferView": add_view(pos, 34962),
                "componentType": 5126,
                "count": len(pos),
                "type": "VEC3",
                "min": pos.min(axis=0).astype(float).tolist(),
                "max": pos.max(axis=0).astype(float).tolist(),
            }
        )
        gltf["accessors"].append(
            {
                "bufferView": add_view(idx, 34963),
                "componentType": 5125,
                "count": len(idx),
                "type": "SCALAR",
            }
        )
        name = ORGAN_NAMES[organ]
        gltf["materials"].append(
            {
                "name": name,
                "pbrMetallicRoughness": {
                    "baseColorFactor": [*rgb[organ], 1.0],
                    "metallicFactor": 0.0,
                    "roughnessFactor": 0.8,
                },
                "doubleSided": True,
            }
        )
        n_acc, n_mat = len(gltf["accessors"]), len(gltf["materials"])
        gltf["meshes"].append(
            {
                "name": name,
                "primitives": [
                    {
                        "attributes": {"POSITION": n_acc - 2},
                        "indices": n_acc - 1,
                        "material": n_mat - 1,
                        "mode": 4,
                    }
                ],
            }
        )
        gltf["nodes"].append({"name": name, "mesh": len(gltf["meshes"]) - 1})
        gltf["nodes"][0]["children"].append(len(gltf["nodes"]) - 1)
    for key in ("meshes", "materials", "accessors", "bufferViews"):
        if not gltf[key]:
            del gltf[key]
    if not gltf["nodes"][0]["children"]:
        del gltf["nodes"][0]["children"]
    if blob:
        gltf["buffers"] = [{"byteLength": len(blob)}]
    js = json.dumps(gltf, separators=(",", ":")).encode("utf-8")
    js += b" " * (-len(js) % 4)
    blob.extend(b"\0" * (-len(blob) % 4))
    chunks = struct.pack("<II", len(js), _GLB_JSON) + js
    if blob:
        chunks += struct.pack("<II", len(blob), _GLB_BIN) + bytes(blob)
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        f.write(struct.pack("<III", _GLB_MAGIC, 2, 12 + len(chunks)))
        f.write(chunks)
    return Path(path)
