"""Exporters against real readers: our PLY reader, Open3D, (trimesh), and Helios via pyhelios3d."""

from __future__ import annotations

import json
import os
import struct
from pathlib import Path

import numpy as np
import pytest

from cropcraft_core.errors import ConfigError, GeometryError, InputError, OutputError
from cropcraft_core.export import (
    PointCloud,
    atomic_path,
    atomic_write_bytes,
    atomic_write_text,
    helios_transforms,
    read_geometry,
    read_ply,
    write_glb,
    write_helios_xml,
    write_obj,
    write_ply,
)
from cropcraft_core.geometry.mesh import CanopyMesh, Organ

# The known flat leaf: a 0.10 m x 0.05 m rectangle at z = 0.5 m, two triangles, 0.005 m².
LEAF_CORNERS = np.array([[1.0, 2.0, 0.5], [1.1, 2.0, 0.5], [1.1, 2.05, 0.5], [1.0, 2.05, 0.5]])
LEAF_AREA = 0.1 * 0.05


def make_mesh(n_random: int = 300, seed: int = 0) -> CanopyMesh:
    """``n_random`` random non-degenerate triangles (mixed organs/plants/nodes) + the flat leaf.

    The flat leaf comes first (faces 0, 1; plant 7, node 3) and shares its 4 vertices.
    """
    rng = np.random.default_rng(seed)
    centres = rng.uniform([0, 0, 0], [3, 2, 1.2], (n_random, 3))
    tri = centres[:, None, :] + rng.normal(0, 0.03, (n_random, 3, 3))
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    assert area.min() > 1e-6
    vertices = np.concatenate([LEAF_CORNERS, tri.reshape(-1, 3)])
    faces = np.concatenate([[[0, 1, 2], [0, 2, 3]], 4 + np.arange(3 * n_random).reshape(-1, 3)])
    organ = np.concatenate([[Organ.LEAF, Organ.LEAF], rng.integers(0, 3, n_random)])
    return CanopyMesh(
        vertices=vertices,
        faces=faces.astype(np.int32),
        organ=organ.astype(np.uint8),
        plant=np.concatenate([[7, 7], rng.integers(0, 12, n_random)]).astype(np.int32),
        node=np.concatenate([[3, 3], rng.integers(0, 25, n_random)]).astype(np.int32),
    )


@pytest.fixture(scope="module")
def mesh() -> CanopyMesh:
    m = make_mesh()
    m.validate()
    assert set(np.unique(m.organ)) == {0, 1, 2}
    return m


# --------------------------------------------------------------------------- PLY


def test_ply_round_trip_is_exact(tmp_path: Path, mesh: CanopyMesh) -> None:
    path = write_ply(tmp_path / "canopy.ply", mesh)
    header = path.read_bytes()[:600]
    assert header.startswith(b"ply\nformat binary_little_endian 1.0\n")
    for line in (b"property double x", b"property uchar organ", b"property int plant"):
        assert line in header
    back = read_ply(path)
    assert np.array_equal(back.vertices, mesh.vertices)  # float64 on disk: bit-exact
    assert np.array_equal(back.faces, mesh.faces)
    assert np.array_equal(back.organ, mesh.organ)
    assert np.array_equal(back.plant, mesh.plant)
    assert np.array_equal(back.node, mesh.node)
    assert back.faces.dtype == np.int32 and back.organ.dtype == np.uint8
    assert back.vertices.dtype == np.float64


def test_ply_float32_option(tmp_path: Path, mesh: CanopyMesh) -> None:
    back = read_ply(write_ply(tmp_path / "f32.ply", mesh, float32=True))
    assert np.allclose(back.vertices, mesh.vertices, atol=1e-6, rtol=0)
    assert np.array_equal(back.organ, mesh.organ)


def test_read_open3d_meshes_without_labels(tmp_path: Path, mesh: CanopyMesh) -> None:
    import open3d as o3d

    om = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(mesh.vertices), o3d.utility.Vector3iVector(mesh.faces)
    )
    for ascii_ in (False, True):
        path = tmp_path / f"o3d_{ascii_}.ply"
        assert o3d.io.write_triangle_mesh(str(path), om, write_ascii=ascii_)
        back = read_ply(path)
        assert back.n_faces == mesh.n_faces
        assert np.allclose(back.vertices, mesh.vertices, atol=1e-6)
        assert np.array_equal(back.faces, mesh.faces)
        assert np.all(back.organ == Organ.LEAF)
        assert np.all(back.plant == 0) and np.all(back.node == 0)


def test_read_open3d_point_cloud(tmp_path: Path) -> None:
    import open3d as o3d

    rng = np.random.default_rng(1)
    pts, cols = rng.uniform(-1, 1, (500, 3)), rng.uniform(0, 1, (500, 3))
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    pc.colors = o3d.utility.Vector3dVector(cols)
    path = tmp_path / "cloud.ply"
    assert o3d.io.write_point_cloud(str(path), pc)
    geom = read_geometry(path)
    assert isinstance(geom, PointCloud) and len(geom) == 500
    assert np.allclose(geom.points, pts, atol=1e-6)
    assert geom.colors is not None and np.allclose(geom.colors, cols, atol=1 / 255 + 1e-9)
    with pytest.raises(InputError, match="cloud.ply.*point cloud"):
        read_ply(path)


def test_read_ascii_polygons_are_fan_triangulated(tmp_path: Path) -> None:
    text = (
        "ply\nformat ascii 1.0\ncomment hand-written\nelement vertex 5\n"
        "property float x\nproperty float y\nproperty float z\n"
        "element face 2\nproperty list uchar int vertex_indices\nend_header\n"
        "0 0 0\n1 0 0\n1 1 0\n0 1 0\n2 2 2\n"
        "4 0 1 2 3\n3 1 4 2\n"
    )
    path = tmp_path / "quads.ply"
    path.write_text(text)
    back = read_ply(path)
    assert back.faces.tolist() == [[0, 1, 2], [0, 2, 3], [1, 4, 2]]
    assert np.isclose(back.select(np.arange(3) < 2).face_areas().sum(), 1.0)


def test_read_binary_big_endian_quads(tmp_path: Path) -> None:
    verts = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], ">f4")
    face = struct.pack(">B4i", 4, 0, 1, 2, 3)
    header = (
        b"ply\nformat binary_big_endian 1.0\nelement vertex 4\nproperty float x\n"
        b"property float y\nproperty float z\nelement face 1\n"
        b"property list uchar int vertex_indices\nend_header\n"
    )
    path = tmp_path / "be.ply"
    path.write_bytes(header + verts.tobytes() + face)
    back = read_ply(path)
    assert back.n_faces == 2 and np.isclose(back.face_areas().sum(), 1.0)


def test_malformed_ply_errors_name_the_file(tmp_path: Path, mesh: CanopyMesh) -> None:
    good = write_ply(tmp_path / "good.ply", mesh)
    data = good.read_bytes()
    cases = {
        "missing.ply": None,
        "notply.ply": b"solid ascii stl\n",
        "noheaderend.ply": b"ply\nformat ascii 1.0\nelement vertex 1\n",
        "truncated.ply": data[: len(data) - 100],
        "badtype.ply": b"ply\nformat ascii 1.0\nelement vertex 1\nproperty quad x\nend_header\n",
    }
    for name, content in cases.items():
        if content is not None:
            (tmp_path / name).write_bytes(content)
        with pytest.raises(InputError, match=name):
            read_ply(tmp_path / name)
    bad_index = (
        "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
        "property float z\nelement face 1\nproperty list uchar int vertex_indices\n"
        "end_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 7\n"
    )
    (tmp_path / "badindex.ply").write_text(bad_index)
    with pytest.raises(InputError, match="badindex.ply.*outside"):
        read_ply(tmp_path / "badindex.ply")
    bad_organ = bad_index.replace("vertex_indices\n", "vertex_indices\nproperty uchar organ\n")
    bad_organ = bad_organ.replace("3 0 1 7", "3 0 1 2 9")
    (tmp_path / "badorgan.ply").write_text(bad_organ)
    with pytest.raises(InputError, match="badorgan.ply.*organ"):
        read_ply(tmp_path / "badorgan.ply")
    # a damaged list length: negative, or far past the file's end
    face = "property list char int vertex_indices\nend_header\n0 0 0\n1 0 0\n0 1 0\n"
    head = bad_index[: bad_index.index("property list")]
    (tmp_path / "negative.ply").write_text(head + face + "-1 0 1 2\n")
    pts = np.zeros((3, 3), "<f4").tobytes()
    binary = head.replace("ascii", "binary_little_endian")
    for name, count in (("negative.bin.ply", b"\xff"), ("huge.bin.ply", b"\x7f")):
        (tmp_path / name).write_bytes(
            binary.encode() + face[: face.index("end_header") + 11].encode() + pts + count
        )
    for name, what in (
        ("negative.ply", "negative list length -1"),
        ("negative.bin.ply", "negative list length -1"),
        ("huge.bin.ply", "ends inside element 'face'"),
    ):
        with pytest.raises(InputError, match=f"{name}: .*{what}"):
            read_ply(tmp_path / name)


def test_ascii_colours_keep_the_scale_of_their_declared_type(tmp_path: Path) -> None:
    """Colours are scaled by the type the header declares, in ASCII files as in binary ones:
    ushort by 65535 (was 255), a dark uchar cloud of values 0-1 by 255 (was taken as 0-1)."""
    for kind, row, expect in (
        ("ushort", "65535 32896 0", [1.0, 32896 / 65535, 0.0]),
        ("uchar", "1 0 1", [1 / 255, 0.0, 1 / 255]),
        ("float", "0.5 0.25 1", [0.5, 0.25, 1.0]),
    ):
        text = (
            "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\n"
            f"property float z\nproperty {kind} red\nproperty {kind} green\n"
            f"property {kind} blue\nend_header\n0 0 0 {row}\n"
        )
        (tmp_path / f"{kind}.ply").write_text(text)
        cloud = read_geometry(tmp_path / f"{kind}.ply")
        assert np.allclose(cloud.colors[0], expect), kind
    bad = text.replace("float red", "uchar red").replace("0.5 0.25", "0.5 0")
    (tmp_path / "bad.ply").write_text(bad)
    with pytest.raises(InputError, match="bad.ply: PLY property 'red'.*declared uint8"):
        read_geometry(tmp_path / "bad.ply")


# --------------------------------------------------------------------------- OBJ / GLB


def test_obj_has_one_group_per_organ(tmp_path: Path, mesh: CanopyMesh) -> None:
    path = write_obj(tmp_path / "canopy.obj", mesh)
    lines = path.read_text().splitlines()
    assert sum(ln.startswith("v ") for ln in lines) == len(mesh.vertices)
    counts: dict[str, int] = {}
    group = None
    for ln in lines:
        if ln.startswith("g "):
            group = ln[2:]
            assert group not in counts, "each organ is one contiguous group"
            counts[group] = 0
        elif ln.startswith("f "):
            assert group is not None
            counts[group] += 1
    assert counts == {
        "leaf": int(np.sum(mesh.organ == Organ.LEAF)),
        "petiole": int(np.sum(mesh.organ == Organ.PETIOLE)),
        "stem": int(np.sum(mesh.organ == Organ.STEM)),
    }
    assert "mtllib canopy.mtl" in lines and "usemtl petiole" in lines
    mtl = (tmp_path / "canopy.mtl").read_text()
    assert all(f"newmtl {g}" in mtl for g in ("leaf", "petiole", "stem"))
    # The first two faces of the leaf group are the flat leaf, 1-based.
    first = lines.index("g leaf")
    assert lines[first + 2 : first + 4] == ["f 1 2 3", "f 1 3 4"]
    import open3d as o3d

    assert len(o3d.io.read_triangle_mesh(str(path)).triangles) == mesh.n_faces


def _glb_json(path: Path) -> dict:
    data = path.read_bytes()
    magic, version, length = struct.unpack_from("<III", data)
    assert (magic, version, length) == (0x46546C67, 2, len(data))
    n, kind = struct.unpack_from("<II", data, 12)
    assert kind == 0x4E4F534A
    return json.loads(data[20 : 20 + n])


def test_glb_structure_and_open3d_load(tmp_path: Path, mesh: CanopyMesh) -> None:
    path = write_glb(tmp_path / "canopy.glb", mesh)
    gltf = _glb_json(path)
    assert [n["name"] for n in gltf["nodes"]] == ["canopy", "leaf", "petiole", "stem"]
    assert all(m["doubleSided"] for m in gltf["materials"])
    n_idx = sum(a["count"] for a in gltf["accessors"] if a["type"] == "SCALAR")
    assert n_idx == 3 * mesh.n_faces
    import open3d as o3d

    loaded = o3d.io.read_triangle_mesh(str(path))
    assert len(loaded.triangles) == mesh.n_faces
    assert np.isclose(loaded.get_surface_area(), mesh.face_areas().sum(), rtol=1e-4)


def test_a_georeferenced_canopy_keeps_its_leaves_in_float32_files(tmp_path, mesh) -> None:
    """float32 resolves 0.5 m at 4,000 km: a UTM canopy's GLB had zero-area leaves (now stored
    about its centre, given as the asset's extras), and write_ply(float32=True) wrote a file
    that read_ply refuses (now refused when written)."""
    import open3d as o3d

    utm = CanopyMesh(
        mesh.vertices + [500_000.0, 4_000_000.0, 0.0], mesh.faces, mesh.organ, mesh.plant,
        mesh.node,
    )  # fmt: skip
    gltf = _glb_json(write_glb(tmp_path / "utm.glb", utm))
    assert gltf["extras"]["offset_m"][1] == pytest.approx(4_000_000.0, abs=5)
    loaded = o3d.io.read_triangle_mesh(str(tmp_path / "utm.glb"))
    assert np.isclose(loaded.get_surface_area(), mesh.face_areas().sum(), rtol=1e-4)
    with pytest.raises(GeometryError, match="beyond what 32-bit floats resolve"):
        write_ply(tmp_path / "utm.ply", utm, float32=True)
    assert "extras" not in _glb_json(write_glb(tmp_path / "near.glb", mesh))


def test_ply_header_ends_at_its_own_end_header_line(tmp_path: Path) -> None:
    """A comment that ends in "end_header" ended the header there ("no vertex element")."""
    text = (
        "ply\nformat ascii 1.0\ncomment written before end_header\nelement vertex 3\n"
        "property float x\nproperty float y\nproperty float z\nelement face 1\n"
        "property list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n"
    )
    (tmp_path / "c.ply").write_text(text)
    assert read_ply(tmp_path / "c.ply").n_faces == 1


def test_a_mesh_of_float_face_indices_is_refused(mesh: CanopyMesh) -> None:
    """1.9 and 2.6 were cut to 1 and 2 by the writers, and failed as raw IndexErrors."""
    with pytest.raises(GeometryError, match="faces must be integer vertex indices"):
        CanopyMesh(mesh.vertices, mesh.faces + 0.5, mesh.organ, mesh.plant, mesh.node)


def test_glb_loads_with_trimesh(tmp_path: Path, mesh: CanopyMesh) -> None:
    trimesh = pytest.importorskip("trimesh", reason="trimesh is not installed in this env")
    scene = trimesh.load(write_glb(tmp_path / "canopy.glb", mesh))
    per_organ = {name: len(g.faces) for name, g in scene.geometry.items()}
    assert per_organ == {
        "leaf": int(np.sum(mesh.organ == Organ.LEAF)),
        "petiole": int(np.sum(mesh.organ == Organ.PETIOLE)),
        "stem": int(np.sum(mesh.organ == Organ.STEM)),
    }
    assert sum(per_organ.values()) == mesh.n_faces


# --------------------------------------------------------------------------- Helios


def test_helios_transform_maps_unit_triangle(mesh: CanopyMesh) -> None:
    tri = mesh.triangles()
    T = helios_transforms(tri)
    unit = np.array([[0, 0, 0, 1], [0, 1, 0, 1], [1, 1, 0, 1]], float)
    mapped = np.einsum("mij,kj->mki", T, unit)[..., :3]
    assert np.allclose(mapped, tri, atol=1e-12)
    assert np.all(np.abs(np.linalg.det(T)) > 0)


def test_helios_round_trip_with_pyhelios(tmp_path: Path, mesh: CanopyMesh) -> None:
    from pyhelios import Context  # real Helios native library, no mock

    path = write_helios_xml(tmp_path / "canopy.xml", mesh)
    text = path.read_text()
    assert "<objID>" not in text and "<vertex>" not in text
    with Context() as ctx:
        uuids = ctx.loadXML(str(path), quiet=True)
        assert len(uuids) == mesh.n_faces == ctx.getPrimitiveCount()
        areas = np.asarray(ctx.getPrimitiveArea(uuids), dtype=np.float64)
        ours = mesh.face_areas()
        assert np.allclose(areas, ours, rtol=1e-3)
        by_label = {
            label: ctx.filterPrimitivesByData(uuids, "object_label", label)
            for label in ("leaf", "petiole", "shoot")
        }
        for label, organ in (("leaf", 0), ("petiole", 1), ("shoot", 2)):
            assert len(by_label[label]) == int(np.sum(mesh.organ == organ))
        leaf_area = float(np.sum(ctx.getPrimitiveArea(by_label["leaf"])))
        ours_leaf = float(ours[mesh.organ == Organ.LEAF].sum())
        assert abs(leaf_area - ours_leaf) <= 0.005 * ours_leaf
        assert np.array_equal(ctx.getPrimitiveDataArray(uuids, "plantID"), mesh.plant)
        assert np.array_equal(ctx.getPrimitiveDataArray(uuids, "nodeID"), mesh.node)
        # The known flat leaf: faces 0 and 1, vertices in order, area 0.005 m².
        flat, _ = ctx.getPrimitiveVertices(uuids[:2])
        assert np.allclose(np.asarray(flat).reshape(2, 3, 3), mesh.triangles()[:2], atol=1e-6)
        assert np.isclose(areas[:2].sum(), LEAF_AREA, rtol=1e-5)
        assert ctx.getPrimitiveData(uuids[0], "object_label") == "leaf"
        c = ctx.getPrimitiveColor(uuids[0])
        assert np.allclose([c.r, c.g, c.b], [0.18, 0.55, 0.14], atol=1e-6)


def test_helios_plant_selection_and_colours(tmp_path: Path, mesh: CanopyMesh) -> None:
    from pyhelios import Context

    rgb = np.tile([0.1, 0.2, 0.3], (mesh.n_faces, 1))
    path = write_helios_xml(tmp_path / "p7.xml", mesh, plant_ids=[7], colors=rgb)
    with Context() as ctx:
        uuids = ctx.loadXML(str(path), quiet=True)
        assert len(uuids) == int(np.sum(mesh.plant == 7))
        assert set(ctx.getPrimitiveDataArray(uuids, "plantID").tolist()) == {7}
        c = ctx.getPrimitiveColor(uuids[0])
        assert np.allclose([c.r, c.g, c.b], [0.1, 0.2, 0.3], atol=1e-6)
    with pytest.raises(ConfigError, match="999"):
        write_helios_xml(tmp_path / "x.xml", mesh, plant_ids=[999])
    with pytest.raises(ConfigError, match=r"\.xml"):
        write_helios_xml(tmp_path / "canopy.helios", mesh)
    with pytest.raises(ConfigError, match="stem"):
        write_helios_xml(tmp_path / "x.xml", mesh, colors={"stem": (2.0, 0.0, 0.0)})


# --------------------------------------------------------------------------- atomic writes / errors


def test_atomic_path_keeps_old_file_when_writer_raises(tmp_path: Path) -> None:
    target = tmp_path / "out.ply"
    atomic_write_text(target, "previous\n")
    with pytest.raises(RuntimeError, match="boom"):
        with atomic_path(target) as tmp:
            assert tmp.parent == tmp_path and tmp.suffix == ".ply"
            tmp.write_bytes(b"half a fi")
            raise RuntimeError("boom")
    assert target.read_text() == "previous\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.ply"]
    umask = os.umask(0o022)
    os.umask(umask)
    atomic_write_bytes(target, b"new")
    # the temporary file's private mode is not kept: a new file's usual mode under the umask
    assert target.read_bytes() == b"new" and target.stat().st_mode & 0o777 == 0o666 & ~umask


def test_writers_failing_midway_leave_the_previous_file(tmp_path: Path) -> None:
    """A file-size limit (as a full disk) stops each writer part-way through its temporary
    file, in a process of its own: OutputError naming the target, the previous file intact,
    no temporary left behind."""
    script = """
import resource, signal, sys
from pathlib import Path
from cropcraft_core.export import write_helios_xml, write_obj, write_ply
from cropcraft_core.errors import OutputError
from tests.test_export import make_mesh
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a write past the limit fails with EFBIG
big = make_mesh(n_random=30_000, seed=2)
folder = Path(sys.argv[1])
resource.setrlimit(resource.RLIMIT_FSIZE, (200_000, resource.RLIM_INFINITY))
for writer, name in ((write_ply, "c.ply"), (write_obj, "c.obj"), (write_helios_xml, "c.xml")):
    try:
        writer(folder / name, big)
    except OutputError as e:
        assert str(folder / name) in str(e), e
    else:
        raise SystemExit(name + " was written past the limit")
"""
    for name in ("c.ply", "c.obj", "c.xml"):
        (tmp_path / name).write_text("previous\n")
    import subprocess
    import sys

    repo = Path(__file__).resolve().parents[1]
    run = subprocess.run(
        [sys.executable, "-c", script, str(tmp_path)],
        cwd=repo,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert run.returncode == 0, run.stderr[-2000:]
    for name in ("c.ply", "c.obj", "c.xml"):
        assert (tmp_path / name).read_text() == "previous\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c.mtl", "c.obj", "c.ply", "c.xml"]


def test_face_labels_that_are_not_integers_are_refused_by_every_writer(tmp_path: Path) -> None:
    base = make_mesh(10)
    node = base.node.astype(np.float64)
    node[3] = np.nan
    bad = CanopyMesh(base.vertices, base.faces, base.organ, base.plant, node)
    for writer, name in (
        (write_ply, "m.ply"),
        (write_obj, "m.obj"),
        (write_glb, "m.glb"),
        (write_helios_xml, "m.xml"),
    ):
        with pytest.raises(GeometryError, match="node ids of dtype float64"):
            writer(tmp_path / name, bad)
    assert not list(tmp_path.iterdir())


def test_unwritable_output_raises_output_error(tmp_path: Path, mesh: CanopyMesh) -> None:
    blocker = tmp_path / "a_file"
    blocker.write_text("x")
    for writer, name in (
        (write_ply, "m.ply"),
        (write_obj, "m.obj"),
        (write_glb, "m.glb"),
        (write_helios_xml, "m.xml"),
    ):
        target = blocker / "sub" / name
        with pytest.raises(OutputError, match=str(target)):
            writer(target, mesh)
    with pytest.raises(OutputError, match="a directory"):
        atomic_write_bytes(tmp_path, b"x")


def test_writers_reject_broken_meshes(tmp_path: Path, mesh: CanopyMesh) -> None:
    v = mesh.vertices.copy()
    v[5] = np.nan
    nan_mesh = CanopyMesh(v, mesh.faces, mesh.organ, mesh.plant, mesh.node)
    bad_organ = CanopyMesh(
        mesh.vertices, mesh.faces, np.full(mesh.n_faces, 9, np.uint8), mesh.plant, mesh.node
    )
    for writer, name in ((write_ply, "a.ply"), (write_glb, "a.glb"), (write_helios_xml, "a.xml")):
        with pytest.raises(GeometryError, match="non-finite"):
            writer(tmp_path / name, nan_mesh)
        with pytest.raises(GeometryError, match="organ"):
            writer(tmp_path / name, bad_organ)
        assert not (tmp_path / name).exists()


def test_empty_mesh_round_trips(tmp_path: Path) -> None:
    back = read_ply(write_ply(tmp_path / "empty.ply", CanopyMesh.empty()))
    assert back.n_faces == 0 and back.vertices.shape == (0, 3)
    gltf = _glb_json(write_glb(tmp_path / "empty.glb", CanopyMesh.empty()))
    assert "meshes" not in gltf


def test_the_bundles_preview_draws_the_plants_its_files_hold(tmp_path: Path) -> None:
    """``preview.png`` drew the planted border too (420 plants beside the files' 126), a
    field 3x the plot that the files hold (session 91's export audit)."""
    from PIL import Image

    from cropcraft_core.bundle import write_bundle_files
    from cropcraft_core.config import CanopyLayout
    from cropcraft_core.procedural import generate_canopy
    from cropcraft_core.render.preview import oblique_camera, shade_rgb

    layout = CanopyLayout(plot_width=1.0, plot_length=1.0)
    canopy = generate_canopy("soybean", {"num_nodes": 4.0}, layout, seed=2)
    write_bundle_files(canopy, tmp_path, {"lai": 1.0})
    top = float(canopy.mesh.vertices[:, 2].max())
    cam = oblique_camera((-0.5, 0.5, -0.5, 0.5), height=top)
    with Image.open(tmp_path / "preview.png") as im:
        drawn = np.asarray(im.convert("RGB"))
    np.testing.assert_array_equal(drawn, shade_rgb(canopy.plot_mesh(), cam))
