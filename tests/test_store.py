"""Scene store: the same suite on a local folder and on a real S3-compatible server (moto)."""

from __future__ import annotations

import datetime as dt
import io
import json
import pickle
import sys
import time
import uuid
import zipfile
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest

from cropcraft_core import __version__
from cropcraft_core.errors import ConfigError, CropCraftError, InputError
from cropcraft_core.store import (
    TMP_PREFIX,
    Manifest,
    SceneKey,
    SceneStore,
    StoreError,
    artefact_key,
    canonical_json,
    code_version,
    config_hash,
    environment_versions,
    redact,
    scene_prefix,
    sha256_bytes,
    sha256_file,
    stage_prefix,
)
from tests import conftest_s3
from tests.conftest_s3 import S3Server, free_port

s3_server = conftest_s3.s3_server  # the session fixture, made visible to this module

SCENE = SceneKey("plotA", "soybean", "2024-07-01")
BACKENDS = ["local", "s3-options", "s3-env"]


@pytest.fixture(params=BACKENDS)
def store(request, tmp_path, monkeypatch) -> SceneStore:
    """A fresh, empty store on each backend (S3 tests get their own prefix in one bucket)."""
    if request.param == "local":
        return SceneStore(str(tmp_path / "store"))
    server: S3Server = request.getfixturevalue("s3_server")
    root = f"s3://{server.bucket}/{uuid.uuid4().hex}"
    if request.param == "s3-options":
        return SceneStore(root, storage_options=server.storage_options())
    # endpoint, credentials and root entirely from the environment
    for var in ("FSSPEC_S3_ENDPOINT_URL", "AWS_ENDPOINT_URL_S3"):
        monkeypatch.delenv(var, raising=False)
    monkeypatch.setenv("CROPCRAFT_STORE", root)
    monkeypatch.setenv("AWS_ENDPOINT_URL", server.endpoint)
    monkeypatch.setenv("AWS_ACCESS_KEY_ID", server.key)
    monkeypatch.setenv("AWS_SECRET_ACCESS_KEY", server.secret)
    monkeypatch.setenv("AWS_DEFAULT_REGION", server.region)
    return SceneStore()


def backend_paths(store: SceneStore) -> list[str]:
    """Every path the backend holds under the root, dot-objects included."""
    store.fs.invalidate_cache()
    try:
        return store.fs.find(store._root_path)
    except FileNotFoundError:
        return []


# ---- put/get of every kind ----------------------------------------------------------------


def test_bytes_json_exists_list_delete_url(store):
    key = artefact_key(SCENE, "sfm", "raw.bin")
    digest = store.put_bytes(key, b"\x00\x01hello")
    assert digest == sha256_bytes(b"\x00\x01hello") == store.sha256(key)
    assert store.get_bytes(key) == b"\x00\x01hello"
    assert store.exists(key) and store.isfile(key)
    assert not store.exists(artefact_key(SCENE, "sfm", "nope.bin"))

    jkey = artefact_key(SCENE, "sfm", "cameras.json")
    h1 = store.put_json(jkey, {"b": [1, 2.5, None], "a": {"z": 1, "y": "é"}})
    assert store.get_json(jkey) == {"a": {"y": "é", "z": 1}, "b": [1, 2.5, None]}
    text = store.get_bytes(jkey).decode()
    assert text.index('"a"') < text.index('"b"') and text.endswith("\n")
    # same content in another key order: byte-identical
    assert store.put_json(jkey, {"a": {"y": "é", "z": 1}, "b": [1, 2.5, None]}) == h1
    with pytest.raises(InputError, match="NaN"):
        store.put_json(jkey, {"x": float("nan")})

    other = "plotA/soybean2/2024-07-01/images/x.jpg"
    store.put_bytes(other, b"x")
    assert store.list(stage_prefix(SCENE, "sfm")) == sorted([key, jkey])
    assert store.list("plotA/soybean") == sorted([key, jkey])  # folder, not string, prefix
    assert store.list() == sorted([key, jkey, other])
    assert store.list("nothing/here") == []

    assert store.url(key).endswith("/plotA/soybean/2024-07-01/sfm/raw.bin")
    assert store.url(key).startswith(("s3://", "file://"))

    store.delete(key)
    assert not store.exists(key)
    store.delete(key)  # idempotent
    store.delete("plotA/soybean2", recursive=True)
    assert store.list() == [jkey]
    with pytest.raises(InputError, match="no such object"):
        store.get_bytes(key)


def test_npz_roundtrip(store):
    key = artefact_key(SCENE, "observe", "obs.npz")
    arrays = {
        "depth": np.linspace(0, 1, 4 * 6, dtype=np.float32).reshape(4, 6),
        "mask": np.arange(24).reshape(4, 6) % 3 == 0,
        "ids": np.arange(5, dtype=np.int64),
        "scalar": np.float64(3.5),
        "names": np.array(["leaf", "stem"]),
    }
    for compress in (True, False):
        digest = store.put_npz(key, arrays, compress=compress)
        assert digest == store.sha256(key) == sha256_bytes(store.get_bytes(key))
        back = store.get_npz(key)
        assert set(back) == set(arrays)
        for name, value in arrays.items():
            np.testing.assert_array_equal(back[name], value)
            assert back[name].dtype == np.asarray(value).dtype
    # damaged objects (cut short, a byte flipped in the header or the data) are named errors
    raw = store.get_bytes(key)
    first = zipfile.ZipFile(io.BytesIO(raw)).infolist()[0]
    data_at = (
        first.header_offset
        + 30
        + len(first.filename)
        + int.from_bytes(raw[first.header_offset + 28 : first.header_offset + 30], "little")
    )
    for damaged in (raw[: len(raw) // 2], flip(raw, data_at + 3), flip(raw, len(raw) - 30)):
        store.put_bytes(key, damaged)
        with pytest.raises(InputError, match=r"obs\.npz is not a readable"):
            store.get_npz(key)


def flip(data: bytes, pos: int) -> bytes:
    """``data`` with the byte at ``pos`` inverted."""
    return data[:pos] + bytes([data[pos] ^ 0xFF]) + data[pos + 1 :]


def test_files_and_open_local(store, tmp_path):
    src = tmp_path / "in.bin"
    payload = bytes(range(256)) * 5000
    src.write_bytes(payload)
    key = artefact_key(SCENE, "images", "IMG_0001.JPG")
    assert store.put_file(src, key) == sha256_file(src)
    out = store.get_file(key, tmp_path / "out" / "copy.bin")
    assert out.read_bytes() == payload
    assert not [p for p in out.parent.iterdir() if p.name.startswith(TMP_PREFIX)]
    with pytest.raises(InputError):
        store.put_file(tmp_path / "missing.bin", key)

    with store.open_local(key) as path:
        assert path.read_bytes() == payload

    tree = tmp_path / "colmap"
    (tree / "sparse" / "0").mkdir(parents=True)
    (tree / "sparse" / "0" / "cameras.txt").write_text("cams")
    (tree / "database.db").write_bytes(b"db")
    (tree / ".hidden").write_text("skip me")
    prefix = stage_prefix(SCENE, "sfm") + "/colmap"
    written = store.put_tree(tree, prefix)
    assert sorted(written) == [f"{prefix}/database.db", f"{prefix}/sparse/0/cameras.txt"]
    with store.open_local(prefix) as path:
        assert (path / "sparse" / "0" / "cameras.txt").read_text() == "cams"
        assert (path / "database.db").read_bytes() == b"db"
    # Storing the folder again holds exactly the new tree: a file since removed goes (a photo
    # the user dropped must not reach SfM), another writer's hidden temporary stays.
    store.put_bytes(f"{prefix}/sparse/0/images.txt", b"old poses")
    (tree / "database.db").unlink()
    (tree / "sparse" / "0" / "cameras.txt").write_text("cams 2")
    temp = store._full(f"{prefix}/{TMP_PREFIX}0123-late.bin")  # a writer still busy
    store.fs.pipe_file(temp, b"half an upload")
    written = store.put_tree(tree, prefix)
    assert store.fs.exists(temp)
    assert sorted(written) == [f"{prefix}/sparse/0/cameras.txt"]
    assert store.list(prefix) == [f"{prefix}/sparse/0/cameras.txt"]
    assert store.get_bytes(f"{prefix}/sparse/0/cameras.txt") == b"cams 2"
    # a name the store cannot hold (a '\\' is legal in a Linux file name) is named before
    # anything is replaced: the folder stays as it was, not half the new tree
    (tree / "a\\b.txt").write_text("x")
    (tree / "sparse" / "0" / "cameras.txt").write_text("cams 3")
    with pytest.raises(InputError, match=r"a\\\\b.txt"):
        store.put_tree(tree, prefix)
    assert store.get_bytes(f"{prefix}/sparse/0/cameras.txt") == b"cams 2"
    with pytest.raises(InputError), store.open_local("plotA/none"):
        pass


# ---- atomicity ----------------------------------------------------------------------------


class Exploding:
    """Array-like whose conversion fails: numpy has already written earlier arrays by then."""

    def __array__(self, dtype=None, copy=None):
        raise RuntimeError("disk on fire")


def test_failed_writes_leave_old_value_and_no_tmp(store):
    key = artefact_key(SCENE, "surfaces", "points.npz")
    old = {"xyz": np.arange(30, dtype=np.float64).reshape(10, 3)}
    old_hash = store.put_npz(key, old)
    big = np.random.default_rng(0).random((200, 200))

    # numpy refuses the object array after writing "big" into the zip stream
    with pytest.raises(InputError, match="dtype object"):
        store.put_npz(key, {"big": big, "bad": np.array([{}, None], dtype=object)})
    with pytest.raises(RuntimeError, match="disk on fire"):
        store.put_npz(key, {"big": big, "boom": Exploding()})
    # a raw writer dying halfway; meanwhile readers still see the old object
    with pytest.raises(ZeroDivisionError), store.open_write(key) as f:
        f.write(b"PK\x03\x04 half a zip" * 1000)
        assert store.sha256(key) == old_hash
        _ = 1 / 0

    assert store.sha256(key) == old_hash
    np.testing.assert_array_equal(store.get_npz(key)["xyz"], old["xyz"])
    assert store.list() == [key]
    assert not [p for p in backend_paths(store) if TMP_PREFIX in p]


def test_tmp_objects_are_hidden_and_swept(store):
    key = artefact_key(SCENE, "rowfit", "rows.json")
    store.put_json(key, {"rows": 4})
    stale = f"{store._root_path}/{stage_prefix(SCENE, 'rowfit')}/{TMP_PREFIX}dead-rows.json"
    store.fs.pipe_file(stale, b"partial")
    assert store.list() == [key]
    assert store.sweep_tmp(older_than_s=3600) == []  # too young
    removed = store.sweep_tmp(older_than_s=0)
    assert removed == [f"{stage_prefix(SCENE, 'rowfit')}/{TMP_PREFIX}dead-rows.json"]
    assert not [p for p in backend_paths(store) if TMP_PREFIX in p]
    # the scene's lease holder sweeps them all, young ones too; on S3 also the multipart
    # uploads a writer of a large object left unfinished (invisible, billed until aborted),
    # other uploads left alone (session 94's store audit)
    store.fs.pipe_file(stale, b"partial")
    uploads = []
    if store.protocol in ("s3", "s3a"):
        for rel in (f"{stage_prefix(SCENE, 'surfaces')}/{TMP_PREFIX}dead-big.npz", "other/big.npz"):
            bucket, path = store._s3_key(rel)
            store.fs.call_s3("create_multipart_upload", Bucket=bucket, Key=path)
            uploads.append(path)
    removed = store.sweep_tmp(SCENE.prefix, older_than_s=None)
    assert f"{stage_prefix(SCENE, 'rowfit')}/{TMP_PREFIX}dead-rows.json" in removed
    assert not [p for p in backend_paths(store) if TMP_PREFIX in p]
    if uploads:
        bucket = store._s3_key("x")[0]
        left = store.fs.call_s3("list_multipart_uploads", Bucket=bucket).get("Uploads") or []
        assert [u["Key"] for u in left if u["Key"] in uploads] == [uploads[1]]
        assert f"{stage_prefix(SCENE, 'surfaces')}/{TMP_PREFIX}dead-big.npz" in removed


# ---- manifest -----------------------------------------------------------------------------


def test_manifest_roundtrip_and_stage_updates(store):
    with pytest.raises(InputError, match="manifest.json"):
        store.load_manifest(SCENE)
    img = artefact_key(SCENE, "images", "a.jpg")
    inputs = {img: store.put_bytes(img, b"jpeg")}
    config = {"crop": "soybean", "seeds": 10, "fit": {"iters": 50, "lr": 0.1}}
    sources = {"images": "s3://field/plotA/photos", "poses": None}
    m = store.init_manifest(SCENE, inputs, config, sources=sources)
    assert m.config_hash == config_hash(config) == config_hash({"fit": config["fit"], **config})
    assert m.code_version.startswith(__version__)
    loaded = store.load_manifest(SCENE)
    assert loaded == m
    assert loaded.inputs == inputs and loaded.config == config and loaded.scene == SCENE
    assert loaded.sources == sources  # where the run read them, for cropcraft status

    cameras = artefact_key(SCENE, "sfm", "cameras.json")
    store.update_stage(SCENE, "sfm", status="running", config_hash="c1", inputs=inputs)
    rec = store.load_manifest(SCENE).stages["sfm"]
    assert rec.status == "running" and rec.started is not None and rec.finished is None
    digest = store.put_json(cameras, {"n": 1})
    env = {"numpy": "2.4.6", "python": "3.11.2"}
    m = store.update_stage(
        SCENE, "sfm", status="done", artefacts={cameras: digest}, environment=env
    )
    rec = store.load_manifest(SCENE).stages["sfm"]
    assert m.stages["sfm"] == rec
    assert rec.environment == env  # which libraries computed it, kept with the record
    assert rec.status == "done" and rec.artefacts == {cameras: digest}
    assert rec.inputs == inputs and rec.config_hash == "c1"
    assert rec.seconds is not None and rec.seconds >= 0 and rec.finished >= rec.started
    assert store.stage_is_current(SCENE, "sfm", config_hash="c1", inputs=inputs, verify=True)
    assert not store.stage_is_current(SCENE, "sfm", config_hash="c2")
    assert not store.stage_is_current(SCENE, "rowfit")

    store.put_json(cameras, {"n": 2})  # tampered behind the manifest's back
    assert store.stage_is_current(SCENE, "sfm", config_hash="c1")
    assert not store.stage_is_current(SCENE, "sfm", config_hash="c1", verify=True)

    secret = "hunter2-secret"
    store.update_stage(
        SCENE,
        "rowfit",
        status="failed",
        error=RuntimeError(f"cannot read s3://admin:{secret}@bucket/x\nsecond line"),
    )
    rec = store.load_manifest(SCENE).stages["rowfit"]
    assert rec.status == "failed" and rec.error.startswith("RuntimeError: cannot read s3://bucket")
    assert "\n" not in rec.error
    assert secret not in store.get_bytes(f"{scene_prefix(SCENE)}/manifest.json").decode()
    assert store.load_manifest(SCENE).done_stages() == ["sfm"]

    # same inputs and config: stage records survive re-ingest; a new config resets them
    assert set(store.init_manifest(SCENE, inputs, dict(config)).stages) == {"sfm", "rowfit"}
    assert store.init_manifest(SCENE, inputs, {**config, "seeds": 3}).stages == {}
    with pytest.raises(ConfigError, match="status"):
        store.update_stage(SCENE, "sfm", status="finished")
    with pytest.raises(InputError):
        store.update_stage(SceneKey("plotB", "maize", "2024-07-01"), "sfm", status="running")
    assert store.list(scene_prefix(SCENE)) == sorted(
        [cameras, img, f"{scene_prefix(SCENE)}/manifest.json"]
    )

    # a manifest there but unreadable (cut short, or a newer version's) is kept aside, not
    # lost, and its replacement's ``written`` is read from the files: a cached record is still
    # judged against what the store holds
    mkey = f"{scene_prefix(SCENE)}/manifest.json"
    damaged = store.get_bytes(mkey)[:-40]
    store.put_bytes(mkey, damaged)
    with pytest.raises(InputError, match="manifest.json"):
        store.load_manifest(SCENE)
    m = store.init_manifest(SCENE, inputs, config)
    assert m.stages == {}
    assert m.written == {cameras: store.sha256(cameras), img: store.sha256(img)}
    aside = [k for k in store.list(scene_prefix(SCENE)) if "manifest.unreadable-" in k]
    assert len(aside) == 1 and store.get_bytes(aside[0]) == damaged
    assert store.load_manifest(SCENE) == m


def test_an_attempt_never_recorded_is_settled_into_written_by_the_next_run(store):
    """A run notes each stage attempt's folder before it may write (``writing``) and clears
    it with the stage's record. A run that dies in between leaves the note, across a config
    change too; the next run hashes that folder into ``written`` (so a cached record of other
    settings naming its keys is not served) and clears the note."""
    key = artefact_key(SCENE, "surfaces", "points.npz")
    store.init_manifest(SCENE, {}, {"voxel": 0.01})
    first = store.put_bytes(key, b"settings A")
    store.update_stage(SCENE, "surfaces", status="done", artefacts={key: first})
    folder = f"{scene_prefix(SCENE)}/surfaces"
    store.update_stage(SCENE, "surfaces", status="running", writing={"surfaces": folder})
    second = store.put_bytes(key, b"settings B")  # ... and the run dies here
    m = store.init_manifest(SCENE, {}, {"voxel": 0.02})  # the next run, other settings
    assert m.writing == {"surfaces": folder} and m.written[key] == first
    assert store.settle_writing(SCENE) == {key: second}
    m = store.load_manifest(SCENE)
    assert m.writing == {} and m.written[key] == second
    assert store.settle_writing(SCENE) == {}  # nothing left to settle
    # a recorded attempt clears its own note
    store.update_stage(SCENE, "surfaces", status="running", writing={"surfaces": folder})
    store.update_stage(SCENE, "surfaces", status="done", writing={"surfaces": None})
    assert store.load_manifest(SCENE).writing == {}


def test_a_stage_done_after_a_failure_keeps_no_error(store):
    """``cropcraft status`` showed a stage done beside the error of the attempt before."""
    store.init_manifest(SCENE, {}, {"a": 1})
    store.update_stage(SCENE, "generate", status="failed", error=OSError("disk full"))
    store.update_stage(SCENE, "generate", status="done", seconds=1.0)
    rec = store.load_manifest(SCENE).stages["generate"]
    assert rec.status == "done" and rec.error is None


def test_a_copied_scene_folder_updates_its_own_manifest(tmp_path):
    """A scene folder copied under another date keeps the manifest that names the first
    date: updating the copy writes the copy's manifest (and names the copy), never the
    first scene's."""
    import shutil

    store = SceneStore(str(tmp_path / "store"))
    store.init_manifest(SCENE, {}, {"a": 1})
    store.update_stage(SCENE, "ingest", status="done")
    copy = SceneKey(SCENE.site, SCENE.crop, "2024-07-02")
    shutil.copytree(
        tmp_path / "store" / scene_prefix(SCENE), tmp_path / "store" / scene_prefix(copy)
    )
    store.update_stage(copy, "ingest", status="failed", error="bad photo")
    assert store.load_manifest(SCENE).stages["ingest"].status == "done"
    m = store.load_manifest(copy)
    assert m.scene == copy and m.stages["ingest"].status == "failed"


def test_concurrent_stage_updates_are_not_lost(store):
    store.init_manifest(SCENE, {}, {"seeds": 8})
    stages = [f"fit_seed_{i}" for i in range(8)]
    with ThreadPoolExecutor(max_workers=8) as pool:
        list(pool.map(lambda s: store.update_stage(SCENE, s, status="done"), stages))
    assert store.load_manifest(SCENE).done_stages() == sorted(stages)


def test_list_dates_and_discover(store):
    for date in ("2024-07-15", "2024-06-01"):
        store.put_bytes(artefact_key(SceneKey("plotA", "maize", date), "images", "1.jpg"), b"1")
    store.put_bytes("plotA/maize/2024-06-01/images/2.jpg", b"2")
    store.put_bytes("plotA/maize/2024-08-01/sfm/x.json", b"{}")  # no images
    store.put_bytes("plotA/maize/notes/images/readme.txt", b"not a date")
    store.put_bytes("plotA/maize/2024-02-30/images/1.jpg", b"impossible date")
    assert store.list_dates("plotA", "maize") == ["2024-06-01", "2024-07-15"]
    assert store.list_dates("plotA", "soybean") == []

    june = SceneKey("plotA", "maize", "2024-06-01")
    store.init_manifest(june, {}, {"seeds": 1})
    store.update_stage(june, "sfm", status="running")
    store.update_stage(june, "sfm", status="done")
    store.update_stage(june, "rowfit", status="running")
    found = store.discover("plotA", "maize")
    assert [d.scene for d in found] == [june, SceneKey("plotA", "maize", "2024-07-15")]
    assert found[0].n_images == 2 and found[0].has_manifest
    assert found[0].stages == {"rowfit": "running", "sfm": "done"} and found[0].done == ("sfm",)
    assert found[1].n_images == 1 and not found[1].has_manifest and found[1].done == ()
    # a scene run from photos kept elsewhere: no inbox, a manifest
    sept = SceneKey("plotA", "maize", "2024-09-01")
    store.init_manifest(sept, {}, {"seeds": 1})
    assert "2024-09-01" not in store.list_dates("plotA", "maize")
    assert store.list_dates("plotA", "maize", with_runs=True) == [
        "2024-06-01",
        "2024-07-15",
        "2024-09-01",
    ]
    run = store.discover("plotA", "maize", with_runs=True)[-1]
    assert run.scene == sept and run.n_images == 0 and run.has_manifest
    # photos dropped into the date's folder, not its images/ inbox: named by the season
    store.put_bytes("plotA/maize/2024-08-19/DJI_0001.JPG", b"a photo one level too high")
    assert store.photos_out_of_place("plotA", "maize") == ["2024-08-19"]
    assert "2024-08-19" not in store.list_dates("plotA", "maize", with_runs=True)
    with pytest.raises(ConfigError):
        store.list_dates("../etc", "maize")


def test_a_sites_folder_as_people_copy_it(store):
    """Session 94's folders audit: one stray file beside a site's date folders (notes.txt,
    Thumbs.db) failed the whole season on a local store; photos in ``Images/``, in a camera
    card's ``DCIM/100MEDIA/`` under a date, or straight in a ``20240707/`` folder were neither
    run nor named; a site typed in another case was a new, empty site."""
    photo = b"not decoded here"
    store.put_bytes("PlotA/soybean/2024-07-01/images/a.jpg", photo)
    for stray in ("notes.txt", "Thumbs.db", "2024-07-02", "IMG_0001.JPG"):
        store.put_bytes(f"PlotA/soybean/{stray}", b"beside the dates")
    store.put_bytes("PlotA/soybean/2024-07-14/Images/a.JPG", photo)
    store.put_bytes("PlotA/soybean/2024-07-10/DCIM/100MEDIA/DJI_0001.JPG", photo)
    store.put_bytes("PlotA/soybean/20240707/a.jpg", photo)
    store.put_bytes("PlotA/soybean/old-flights/2023/a.png", photo)
    store.put_bytes("PlotA/soybean/season/summary.png", photo)  # the season's own plot
    # macOS junk only (hidden: the store's own API refuses such keys): nothing there
    store.fs.makedirs(store._full("PlotA/soybean/2024-07-20"), exist_ok=True)
    store.fs.pipe_file(store._full("PlotA/soybean/2024-07-20/._a.jpg"), photo)
    assert store.list_dates("PlotA", "soybean") == ["2024-07-01"]
    assert store.misnamed_dates("PlotA", "soybean") == ["20240707", "old-flights"]
    assert store.photos_out_of_place("PlotA", "soybean") == [
        "2024-07-10/DCIM/100MEDIA",
        "2024-07-14/Images",
    ]
    assert store.sites_like("plota") == ["PlotA"] and store.sites_like("PlotA") == []


def test_reachable_and_pickle(store):
    store.check_reachable()
    clone = pickle.loads(pickle.dumps(store))
    assert clone.root == store.root
    clone.put_bytes("plotA/x.bin", b"via clone")
    assert store.get_bytes("plotA/x.bin") == b"via clone"
    assert store.list() == ["plotA/x.bin"]  # the reachability probe left nothing behind


# ---- names and keys -------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("site", "crop", "date", "match"),
    [
        ("..", "soybean", "2024-07-01", "site"),
        ("a..b", "soybean", "2024-07-01", "site"),
        ("a/b", "soybean", "2024-07-01", "site"),
        ("/abs", "soybean", "2024-07-01", "site"),
        ("", "soybean", "2024-07-01", "site"),
        (".hidden", "soybean", "2024-07-01", "site"),
        ("plot A", "soybean", "2024-07-01", "site"),
        ("plotA", "wheat", "2024-07-01", "unknown crop"),
        ("plotA", "soybean", "2024-13-01", "date"),
        ("plotA", "soybean", "2024-7-1", "date"),
        ("plotA", "soybean", "20240701", "date"),
        ("plotA", "soybean", "2024-02-30", "date"),
    ],
)
def test_scene_key_validation(site, crop, date, match):
    with pytest.raises(ConfigError, match=match):
        SceneKey(site, crop, date)


def test_scene_key_accepts_dates_and_parses():
    key = SceneKey("plot_A-1.north", "maize", dt.date(2024, 7, 1))
    assert key.date == "2024-07-01" and str(key) == "plot_A-1.north/maize/2024-07-01"
    assert SceneKey.parse(key.prefix) == key
    assert stage_prefix(key, "fit_seed") == "plot_A-1.north/maize/2024-07-01/fit_seed"
    with pytest.raises(ConfigError):
        stage_prefix(key, "../images")
    with pytest.raises(ConfigError):
        SceneKey("plotA", "maize", dt.datetime(2024, 7, 1, 12))


@pytest.mark.parametrize(
    "key", ["../x", "/abs/x", "a//b", "a/../b", "a/./b", "a\\b", "a/.tmp-x", "s3://b/x", ""]
)
def test_bad_keys_are_refused(tmp_path, key):
    store = SceneStore(str(tmp_path / "s"))
    with pytest.raises(ConfigError):
        store.put_bytes(key, b"x")
    assert not (tmp_path / "x").exists()


def test_errors_are_one_family():
    assert issubclass(StoreError, CropCraftError) and issubclass(StoreError, OSError)


# ---- hashing, redaction, code version -------------------------------------------------------


def test_canonical_json_and_hash():
    a = {"b": 1, "a": [1.5, {"y": np.float32(2.0), "x": np.int64(3)}]}
    b = {"a": [1.5, {"x": 3, "y": 2.0}], "b": 1}
    assert canonical_json(a) == canonical_json(b) == b'{"a":[1.5,{"x":3,"y":2.0}],"b":1}'
    assert config_hash(a) == config_hash(b) == sha256_bytes(canonical_json(b))
    with pytest.raises(InputError):
        canonical_json({"x": float("inf")})
    assert code_version().startswith(__version__)


def test_environment_versions_name_the_installed_numeric_libraries():
    """Each entry is what importlib.metadata reports for an installed distribution, the
    alternatives (open3d-cpu / open3d) resolved to the one installed."""
    from importlib import metadata

    import numpy
    import open3d
    import scipy

    env = environment_versions()
    assert env["numpy"] == numpy.__version__ and env["scipy"] == scipy.__version__
    assert env["python"] == ".".join(map(str, sys.version_info[:3]))
    (o3d,) = [k for k in env if k.startswith("open3d")]
    assert env[o3d] == metadata.version(o3d) and open3d.__version__.startswith(env[o3d])
    assert {"numba", "pycolmap", "torch"} <= set(env)


def test_the_cpu_kernels_that_ran_are_named_as_numpy_and_openblas_chose_them():
    """``numpy-simd`` and ``openblas-core`` follow what the process runs: numpy's highest
    enabled dispatch target and OpenBLAS's core type, with the host's own choice
    (``CROPCRAFT_KERNELS=native`` in a second interpreter) and where the environment turns the
    machine's best ones off (a third with the top target disabled and OpenBLAS told to use its
    Haswell kernels)."""
    from numpy._core._multiarray_umath import __cpu_dispatch__, __cpu_features__
    from threadpoolctl import threadpool_info

    from tests.test_kernels import _child

    env = environment_versions()
    enabled = [t for t in __cpu_dispatch__ if __cpu_features__.get(t)]
    if enabled:
        assert env["numpy-simd"] == enabled[-1]
    (blas,) = [i for i in threadpool_info() if "numpy" in i["filepath"]]
    assert env["openblas-core"] == blas["architecture"]
    code = (
        "import json; from cropcraft_core.store import numeric_kernels as k\n"
        "from numpy._core._multiarray_umath import __cpu_dispatch__ as d, __cpu_features__ as f\n"
        "print(json.dumps([k(), [t for t in d if f.get(t)]]))"
    )

    native, enabled = _child(code, CROPCRAFT_KERNELS="native")
    if enabled:
        assert native["numpy-simd"] == enabled[-1]
    if len(enabled) < 2 or not __cpu_features__.get("AVX2"):
        pytest.skip("needs two of numpy's dispatch targets and AVX2 (Haswell kernels)")
    forced, _ = _child(
        code,
        CROPCRAFT_KERNELS="native",
        NPY_DISABLE_CPU_FEATURES=enabled[-1],
        OPENBLAS_CORETYPE="Haswell",
    )
    assert forced == {"numpy-simd": enabled[-2], "openblas-core": "Haswell"}


def test_redact():
    assert redact("s3://AKIA:sEcReT@bucket/prefix") == "s3://bucket/prefix"
    assert "sEcReT" not in redact("see https://u:sEcReT@host/x?X-Amz-Signature=abc&n=1")
    assert redact("https://h/x?X-Amz-Signature=abc&n=1") == "https://h/x?X-Amz-Signature=***&n=1"
    opts = {
        "key": "AKIA",
        "secret": "sEcReT",
        "endpoint_url": "http://u:pw@127.0.0.1:9000",
        "client_kwargs": {"aws_session_token": "tok", "region_name": "us-east-1"},
        "anon": False,
    }
    out = redact(opts)
    assert out == {
        "key": "***",
        "secret": "***",
        "endpoint_url": "http://127.0.0.1:9000",
        "client_kwargs": {"aws_session_token": "***", "region_name": "us-east-1"},
        "anon": False,
    }
    assert opts["secret"] == "sEcReT"  # input untouched


def test_credentials_in_uri_are_refused():
    with pytest.raises(ConfigError) as info:
        SceneStore("s3://AKIA:sEcReT@bucket/prefix")
    assert "sEcReT" not in str(info.value) and "s3://bucket/prefix" in str(info.value)


# ---- reachability -------------------------------------------------------------------------


def test_unreachable_endpoint_fails_fast_and_redacted(caplog):
    secret = "very-secret-value"
    store = SceneStore(
        "s3://some-bucket/prefix",
        storage_options={
            "endpoint_url": f"http://127.0.0.1:{free_port()}",  # nothing listens there
            "key": "AKIDEXAMPLE",
            "secret": secret,
        },
    )
    assert secret not in repr(store) and secret not in json.dumps(store.describe())
    start = time.monotonic()
    with caplog.at_level("DEBUG", logger="cropcraft_core"), pytest.raises(StoreError) as info:
        store.check_reachable(timeout_s=2.0)
    elapsed = time.monotonic() - start
    assert elapsed < 5.0, elapsed
    message = str(info.value)
    assert "s3://some-bucket/prefix" in message
    assert secret not in message and "AKIDEXAMPLE" not in message
    assert secret not in caplog.text


def test_missing_bucket_is_a_store_error(s3_server, monkeypatch):
    store = SceneStore("s3://no-such-bucket/p", storage_options=s3_server.storage_options())
    with pytest.raises(StoreError, match="bucket"):
        store.check_reachable()
    with pytest.raises(StoreError):
        store.put_bytes("a/b.bin", b"x")
    # status named no bucket: an all-pending table and "no run recorded" (S3 audit 91)
    from cropcraft_core.errors import InputError
    from flows.service_cli import scene_status

    monkeypatch.setenv("AWS_ACCESS_KEY_ID", s3_server.key)
    monkeypatch.setenv("AWS_SECRET_ACCESS_KEY", s3_server.secret)
    monkeypatch.setenv("AWS_DEFAULT_REGION", s3_server.region)
    monkeypatch.setenv("AWS_ENDPOINT_URL", s3_server.endpoint)
    with pytest.raises(InputError, match="its bucket 'no-such-bucket' does not exist"):
        scene_status("s3://no-such-bucket/p", "plotA/soybean/2024-07-01")
    assert scene_status(f"s3://{s3_server.bucket}/p", "plotA/soybean/2024-07-01")


def test_unwritable_local_root(tmp_path):
    blocker = tmp_path / "file.txt"
    blocker.write_text("not a folder")
    store = SceneStore(str(blocker / "store"))
    with pytest.raises(StoreError, match="file.txt"):
        store.check_reachable()


def test_fsspec_endpoint_env(s3_server, monkeypatch):
    monkeypatch.setenv("FSSPEC_S3_ENDPOINT_URL", s3_server.endpoint)
    monkeypatch.setenv("AWS_ENDPOINT_URL", "http://127.0.0.1:1")  # lower priority
    opts = {"key": s3_server.key, "secret": s3_server.secret}
    store = SceneStore(f"s3://{s3_server.bucket}/{uuid.uuid4().hex}", storage_options=opts)
    assert store.describe()["storage_options"]["endpoint_url"] == s3_server.endpoint
    store.check_reachable()
    store.put_json("x/y.json", {"ok": True})
    assert store.get_json("x/y.json") == {"ok": True}


def test_default_root_is_local_folder(tmp_path, monkeypatch):
    monkeypatch.delenv("CROPCRAFT_STORE", raising=False)
    monkeypatch.chdir(tmp_path)
    store = SceneStore()
    assert store.root == (tmp_path / "cropcraft-data").as_uri()
    store.check_reachable()
    assert (tmp_path / "cropcraft-data").is_dir()


def test_manifest_model_is_plain_json():
    m = Manifest(site="p", crop="maize", date="2024-07-01")
    assert Manifest.model_validate_json(m.model_dump_json()) == m


# ---- input fingerprints ---------------------------------------------------------------------


def _photo(seed: int) -> bytes:
    from PIL import Image

    rng = np.random.default_rng(seed)
    buf = io.BytesIO()
    Image.fromarray(rng.integers(0, 255, (24, 32, 3), dtype=np.uint8)).save(buf, format="PNG")
    return buf.getvalue()


def test_photo_listings_on_s3_see_uploads_since(s3_server, tmp_path, monkeypatch):
    """fsspec keeps an S3 folder's listing for the life of the process: the input fingerprint
    and ingest must list afresh, or photos uploaded between two runs of a long-lived worker are
    silently left out (and the old set cached under the new run)."""
    import fsspec

    from cropcraft_core.sfm import ingest_images
    from tasks.common import fingerprint

    monkeypatch.setenv("AWS_ACCESS_KEY_ID", s3_server.key)
    monkeypatch.setenv("AWS_SECRET_ACCESS_KEY", s3_server.secret)
    monkeypatch.setenv("AWS_DEFAULT_REGION", s3_server.region)
    monkeypatch.setenv("AWS_ENDPOINT_URL", s3_server.endpoint)
    folder = f"{s3_server.bucket}/{uuid.uuid4().hex}/photos"
    other = fsspec.filesystem("s3", skip_instance_cache=True, **s3_server.storage_options())
    for i in range(3):
        other.pipe(f"{folder}/p{i}.png", _photo(i))
    first = fingerprint(f"s3://{folder}")
    assert sorted(first) == ["p0.png", "p1.png", "p2.png"]
    assert len(ingest_images(f"s3://{folder}", tmp_path / "a")) == 3

    other.pipe(f"{folder}/p3.png", _photo(3))  # another client: a new photo, one replaced
    other.pipe(f"{folder}/p0.png", _photo(10))
    second = fingerprint(f"s3://{folder}")
    assert sorted(second) == ["p0.png", "p1.png", "p2.png", "p3.png"]
    assert second["p0.png"] != first["p0.png"]
    assert len(ingest_images(f"s3://{folder}", tmp_path / "b")) == 4


def test_poses_fingerprint_covers_a_colmap_project(tmp_path):
    """A COLMAP project keeps its model in sparse/0/, which the poses stage reads: the
    fingerprint lists it, so an edited model is not served from the cache."""
    from tasks.common import fingerprint

    model = tmp_path / "proj" / "sparse" / "0"
    model.mkdir(parents=True)
    for name in ("cameras.txt", "images.txt", "points3D.txt"):
        (model / name).write_text("x")
    (tmp_path / "proj" / ".cache").mkdir()
    (tmp_path / "proj" / ".cache" / "junk").write_text("skip me")
    first = fingerprint(str(tmp_path / "proj"), what="poses")
    assert sorted(first) == ["sparse/0/cameras.txt", "sparse/0/images.txt", "sparse/0/points3D.txt"]
    (model / "images.txt").write_text("edited poses")
    assert fingerprint(str(tmp_path / "proj"), what="poses") != first
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="no poses found"):
        fingerprint(str(tmp_path / "empty"), what="poses")


def test_a_transforms_json_brings_the_sparse_points_it_names(tmp_path):
    """ns-process-data writes sparse_pc.ply beside an SfM project's transforms.json and names
    it in ply_file_path: the poses' fingerprint covers it (an edited cloud is not served from
    the cache) and the poses stage fetches it with the json; a path leaving the folder is not
    followed."""
    from tasks.common import fingerprint
    from tasks.poses import _fetch

    src = tmp_path / "src"
    src.mkdir()
    (src / "transforms.json").write_text(json.dumps({"ply_file_path": "./sparse_pc.ply"}))
    (src / "sparse_pc.ply").write_text("ply points")
    first = fingerprint(str(src / "transforms.json"), what="poses")
    assert sorted(first) == ["sparse_pc.ply", "transforms.json"]
    (src / "sparse_pc.ply").write_text("other ply points")
    assert fingerprint(str(src / "transforms.json"), what="poses") != first
    dest = tmp_path / "dest"
    dest.mkdir()
    got = _fetch(str(src / "transforms.json"), dest)
    assert (got.parent / "sparse_pc.ply").read_text() == "other ply points"
    (src / "transforms.json").write_text(json.dumps({"ply_file_path": "../secret.ply"}))
    (tmp_path / "secret.ply").write_text("outside")
    assert sorted(fingerprint(str(src / "transforms.json"), what="poses")) == ["transforms.json"]


def test_poses_in_a_folder_named_with_brackets_are_fetched(tmp_path):
    """``Trial [rep 2]/``: fsspec's ``get`` read the path as a glob pattern, and the poses
    stage failed on a bare ``FileNotFoundError: []`` (session 94's folders audit)."""
    from tasks.poses import _fetch

    src = tmp_path / "Plot [rep 2]"
    (src / "colmap" / "sparse" / "0").mkdir(parents=True)
    for name in ("cameras.txt", "images.txt", "points3D.txt"):
        (src / "colmap" / "sparse" / "0" / name).write_text(name)
    (src / "transforms.json").write_text(json.dumps({"ply_file_path": "sparse [1].ply"}))
    (src / "sparse [1].ply").write_text("ply points")
    dest = tmp_path / "dest"
    dest.mkdir()
    got = _fetch(str(src / "colmap"), dest)
    assert (got / "sparse" / "0" / "images.txt").read_text() == "images.txt"
    got = _fetch(str(src / "transforms.json"), dest)
    assert (got.parent / "sparse [1].ply").read_text() == "ply points"


def test_the_checkpoint_folder_is_the_users_own_and_a_bad_one_is_named(tmp_path, monkeypatch):
    """Fit seeds' checkpoints default to a per-user folder of the temp dir (mode 0700): one
    folder for every user belonged to the first, and the next user's seeds failed on a bare
    PermissionError. A CROPCRAFT_WORK that cannot hold the folder is named."""
    import os
    import stat
    import tempfile

    from tasks.common import checkpoint_dir

    monkeypatch.delenv("CROPCRAFT_WORK", raising=False)
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    path = checkpoint_dir()
    assert path == tmp_path / f"cropcraft-{os.getuid()}" / "checkpoints"
    assert stat.S_IMODE(path.stat().st_mode) == 0o700
    (tmp_path / "work").mkdir()
    (tmp_path / "work" / "checkpoints").write_text("not a folder")
    monkeypatch.setenv("CROPCRAFT_WORK", str(tmp_path / "work"))
    with pytest.raises(ConfigError, match="CROPCRAFT_WORK"):
        checkpoint_dir()


def test_a_relative_root_pickles_as_the_folder_it_names_here(tmp_path, monkeypatch):
    """A store opened on a relative root and sent to a process that starts elsewhere (a
    worker, a spawned seed) must open the same folder, not the relative one over there."""
    here, there = tmp_path / "here", tmp_path / "there"
    here.mkdir()
    there.mkdir()
    monkeypatch.chdir(here)
    store = SceneStore("cropcraft-data")
    store.put_bytes("plotA/soybean/2024-07-01/x.json", b"{}")
    blob = pickle.dumps(store)
    monkeypatch.chdir(there)
    assert pickle.loads(blob).exists("plotA/soybean/2024-07-01/x.json")


def test_a_key_that_clashes_with_a_folder_says_so(tmp_path):
    """Not 'check the store URI, endpoint, credentials and permissions': the key is wrong."""
    store = SceneStore(str(tmp_path / "store"))
    store.put_bytes("plotA/soybean/2024-07-01/ingest/images/a.png", b"png")
    store.put_bytes("plotA/soybean/2024-07-01/fit/fit.json", b"{}")
    with pytest.raises(InputError, match="it is a folder, not an object"):
        store.get_json("plotA/soybean/2024-07-01/ingest/images")
    with pytest.raises(InputError, match="an object stands where"):
        store.put_bytes("plotA/soybean/2024-07-01/fit/fit.json/x", b"x")
    with pytest.raises(InputError, match="cannot store"):
        store.put_file(tmp_path, "plotA/soybean/2024-07-01/x/y")


def test_sources_are_noted_only_on_the_settings_they_were_read_for(store):
    """``cropcraft run`` answered from the cache notes where it read its photos, but only
    where the manifest still holds its inputs and settings, checked and written as one change:
    a run of other settings that started meanwhile keeps its own manifest."""
    inputs = {"images:a.jpg": "1:1"}
    store.init_manifest(SCENE, inputs, {"a": 1}, sources={"images": "/old"})
    store.update_stage(SCENE, "ingest", status="done")
    mine = {"images": "/new", "poses": None}
    assert not store.note_sources(SCENE, mine, inputs=inputs, config_hash=config_hash({"a": 2}))
    assert store.load_manifest(SCENE).sources == {"images": "/old"}
    assert store.note_sources(SCENE, mine, inputs=inputs, config_hash=config_hash({"a": 1}))
    m = store.load_manifest(SCENE)
    assert m.sources == mine and m.stages["ingest"].status == "done"
    assert not store.note_sources(SCENE, mine, inputs=inputs, config_hash=config_hash({"a": 1}))


def test_a_deleted_manifest_is_replaced_from_the_files_there(store):
    """Without its manifest a scene's ``written`` started empty, and a cached record of other
    settings was served over whatever the store held. Now it starts from the artefacts there
    (not the inbox's photos, which a first run would otherwise read in full)."""
    photo = artefact_key(SCENE, "images", "a.jpg")
    fit = artefact_key(SCENE, "fit", "fit.json")
    store.put_bytes(photo, b"jpeg")
    assert store.init_manifest(SCENE, {}, {"a": 1}).written == {}  # a first run: nothing
    store.update_stage(SCENE, "fit", status="done", artefacts={fit: store.put_json(fit, {"a": 1})})
    now = store.put_json(fit, {"a": 2})  # another run's answer ...
    store.delete(f"{scene_prefix(SCENE)}/manifest.json")  # ... and the manifest gone
    assert store.init_manifest(SCENE, {}, {"a": 1}).written == {fit: now}


def test_a_killed_stage_leaves_no_scratch_for_long(tmp_path, monkeypatch):
    """A deployment's run cancelled from Prefect ends its stage's process without unwinding:
    its scratch folder stayed in the worker's temp folder for good (40 MB an export; session
    92's deployment audit). The next stage's scratch sweeps those of dead processes of this
    host, and only those."""
    import os
    import signal
    import subprocess
    import tempfile
    from pathlib import Path

    from tasks.common import _host_tag, sweep_scratch, workdir

    code = (
        "import sys, time\n"
        "from tasks.common import workdir\n"
        "with workdir('export') as d:\n"
        "    (d / 'canopy.ply').write_bytes(b'x' * 1000)\n"
        "    print(d, flush=True)\n"
        "    time.sleep(120)\n"
    )
    env = {**os.environ, "TMPDIR": str(tmp_path)}
    proc = subprocess.Popen(
        [sys.executable, "-c", code], env=env, stdout=subprocess.PIPE, text=True
    )
    left = Path(proc.stdout.readline().strip())
    proc.send_signal(signal.SIGKILL)  # no unwinding, as a cancelled run's worker
    proc.wait()
    assert left.parent == tmp_path and (left / "canopy.ply").is_file()
    tag = _host_tag()
    mine = tmp_path / f"cropcraft-seed@{os.getpid()}.{tag}-live"  # a live process's
    other = tmp_path / f"cropcraft-seed@{proc.pid}.{'0' * 8 if tag != '0' * 8 else '1' * 8}-x"
    stranger = tmp_path / f"cropcraft-notes@{proc.pid}"  # not one of ours
    for d in (mine, other, stranger):
        d.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    with workdir("generate") as fresh:
        assert fresh.is_dir() and not left.exists()
    assert not fresh.exists()
    assert mine.is_dir() and other.is_dir() and stranger.is_dir()
    assert sweep_scratch(tmp_path) == []
