"""One run of a scene at a time (cropcraft_core/lease.py) and manifests that lose no update to
writers in other processes (SceneStore._change_manifest), on a local folder and on a real
S3-compatible server (moto) -- in separate processes, as two runs on two workers are."""

from __future__ import annotations

import json
import multiprocessing as mp
import os
import signal
import subprocess
import sys
import textwrap
import time
import uuid

import pytest

from cropcraft_core.lease import (
    LEASE_NAME,
    LOCK_NAME,
    SceneLease,
    hold_scene,
    require_holder,
    scene_holder,
)
from cropcraft_core.store import SceneBusyError, SceneKey, SceneStore, StoreError, scene_prefix
from tests import conftest_s3
from tests.conftest_s3 import S3Server

s3_server = conftest_s3.s3_server  # the session fixture, made visible to this module

SCENE = SceneKey("plotA", "soybean", "2024-07-01")


@pytest.fixture(params=["local", "s3"])
def store(request, tmp_path) -> SceneStore:
    if request.param == "local":
        return SceneStore(str(tmp_path / "store"))
    server: S3Server = request.getfixturevalue("s3_server")
    return SceneStore(
        f"s3://{server.bucket}/{uuid.uuid4().hex}", storage_options=server.storage_options()
    )


def _spawned() -> mp.context.SpawnContext:
    return mp.get_context("spawn")


# ---- manifests: no lost update across processes -----------------------------------------------


def _record_stages(root: str, options: dict, worker: int, n: int) -> None:
    store = SceneStore(root, storage_options=options)
    for i in range(n):
        store.update_stage(SCENE, f"fit_seed_{worker}_{i}", status="done", seconds=float(i))


def test_manifest_updates_from_many_processes_are_all_kept(store):
    """Four processes record five stages each into one manifest at the same time: every
    record is there (on S3 each writer replaces only the version it read, and retries)."""
    store.init_manifest(SCENE, {}, {"seeds": 20})
    options = store._storage_options
    procs = [
        _spawned().Process(target=_record_stages, args=(store._raw_root, options, w, 5))
        for w in range(4)
    ]
    for p in procs:
        p.start()
    for p in procs:
        p.join(timeout=120)
        assert p.exitcode == 0
    expected = sorted(f"fit_seed_{w}_{i}" for w in range(4) for i in range(5))
    assert store.load_manifest(SCENE).done_stages() == expected


def test_a_conditional_write_replaces_only_the_version_it_read(store):
    key = f"{scene_prefix(SCENE)}/note.json"
    first = store._write_if(key, b"1", None)
    assert first is not None
    assert store._write_if(key, b"2", None) is None  # something is there
    second = store._write_if(key, b"2", first)
    assert second is not None and store.get_bytes(key) == b"2"
    assert store._write_if(key, b"3", first) is None  # the version read is gone
    assert store.get_bytes(key) == b"2"
    assert not store._delete_if(key, first) and store.isfile(key)
    assert store._delete_if(key, second) and not store.isfile(key)


# ---- the scene lease ---------------------------------------------------------------------------


def test_a_store_without_cross_process_exclusion_is_warned_of_once(tmp_path, caplog):
    """A store with neither S3's conditional writes nor a local disk's flock (``gs://`` and
    the like; here fsspec's in-memory filesystem registered under another protocol, which
    this code cannot tell from one other processes share) holds the lease and the manifest
    within this process only: the first lease or manifest change on it says so, once per
    process, naming the store; ``memory://`` (no other process sees it) and a local store
    are not warned of."""
    import logging

    import fsspec
    from fsspec.implementations.memory import MemoryFileSystem

    class SharedFileSystem(MemoryFileSystem):
        protocol = ("sharedfs",)
        store: dict = {}
        pseudo_dirs = [""]

    fsspec.register_implementation("sharedfs", SharedFileSystem, clobber=True)
    shared = SceneStore(f"sharedfs://cropcraft/{uuid.uuid4().hex}")
    said = "no conditional writes"
    with caplog.at_level(logging.WARNING, logger="cropcraft_core.store"):
        with hold_scene(shared, SCENE) as lease:
            lease.check()
            shared.init_manifest(SCENE, {}, {"seeds": 2})
            shared.update_stage(SCENE, "ingest", status="done", seconds=1.0)
        with hold_scene(shared, SceneKey("plotA", "soybean", "2024-07-08")):
            pass
        warned = [r.getMessage() for r in caplog.records if said in r.getMessage()]
        assert len(warned) == 1, warned
        assert shared.root in warned[0] and "one worker at a time" in warned[0]
        for other in (SceneStore(f"memory://{uuid.uuid4().hex}"), SceneStore(str(tmp_path))):
            with hold_scene(other, SCENE):
                other.init_manifest(SCENE, {}, {"seeds": 2})
                other.update_stage(SCENE, "ingest", status="done", seconds=1.0)
    assert [r.getMessage() for r in caplog.records if said in r.getMessage()] == warned


def test_a_second_run_of_a_held_scene_is_refused_naming_the_first(store):
    with hold_scene(store, SCENE, owner="flow run nightly-plotA (1234)") as lease:
        lease.check()
        with pytest.raises(SceneBusyError) as err:
            with hold_scene(store, SCENE, owner="flow run ad-hoc"):
                pass
        message = str(err.value)
        assert "plotA/soybean/2024-07-01 is being run by flow run nightly-plotA (1234)" in message
        assert f"pid {os.getpid()}" in message and "wait for that run" in message
        # another date of the same plot is another scene
        with hold_scene(store, SceneKey("plotA", "soybean", "2024-07-08")):
            pass
    # released: the next run takes it, and the lease is hidden from the scene's listing
    with hold_scene(store, SCENE, owner="flow run ad-hoc"):
        pass
    assert not any(k.endswith((LOCK_NAME, LEASE_NAME)) for k in store.list(scene_prefix(SCENE)))


def test_work_started_by_a_run_learns_whether_that_run_still_holds_the_scene(store):
    """A fit seed on a Dask worker goes on after its run has ended; before it writes it asks
    whether the run that started it (its lease's token) still holds the scene: yes while it
    does, no once another run holds it or none does (session 92's Dask audit: an orphaned seed
    wrote over the scene 9 s after its run had failed)."""
    with hold_scene(store, SCENE, owner="flow run nightly-plotA") as first:
        require_holder(store, SCENE, first.token, "fit seed 2")  # held: goes on
        with pytest.raises(SceneBusyError, match="fit seed 2 of plotA/soybean/2024-07-01 stops"):
            require_holder(store, SCENE, "0" * 32, "fit seed 2")
    with pytest.raises(SceneBusyError, match="no run holds it now"):
        require_holder(store, SCENE, first.token, "fit seed 2")
    with hold_scene(store, SCENE, owner="flow run ad-hoc"):
        with pytest.raises(SceneBusyError, match="flow run ad-hoc holds it now"):
            require_holder(store, SCENE, first.token, "fit seed 2")


_HOLD = textwrap.dedent(
    """
    import json, sys, time
    from cropcraft_core.lease import hold_scene
    from cropcraft_core.store import SceneKey, SceneStore
    store = SceneStore(sys.argv[1], storage_options=json.loads(sys.argv[2]))
    with hold_scene(store, SceneKey("plotA", "soybean", "2024-07-01"), owner="held",
                    ttl_s=float(sys.argv[3]), renew_s=float(sys.argv[4])):
        print("held", flush=True)
        time.sleep(600)
    """
)


def _holder(store: SceneStore, ttl_s: float, renew_s: float) -> subprocess.Popen:
    """Another process holding the scene until it is killed."""
    proc = subprocess.Popen(
        [
            sys.executable,
            "-c",
            _HOLD,
            store._raw_root,
            json.dumps(store._storage_options),
            str(ttl_s),
            str(renew_s),
        ],
        stdout=subprocess.PIPE,
        text=True,
    )
    assert proc.stdout is not None and proc.stdout.readline().strip() == "held"
    return proc


def test_a_run_holds_its_scene_against_another_process_until_it_dies(store):
    """A live holder renews its lease past the lease's time to live and is not taken over;
    killed outright (no release), a local lock goes with the process, and so does an S3 lease
    whose holder ran on this host (its pid is gone): the next run takes the scene at once (it
    waited out the lease's 10 minutes; session 91's S3 audit)."""
    proc = _holder(store, ttl_s=3.0, renew_s=0.5)
    try:
        time.sleep(4.0)  # past the time to live: only renewals keep it
        with pytest.raises(SceneBusyError, match="being run by held"):
            SceneLease(store, SCENE, "second").acquire()
        assert scene_holder(store, SCENE)["owner"].startswith("held")  # read, not taken
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
    assert scene_holder(store, SCENE) is None  # cropcraft status: its stages were interrupted
    lease = SceneLease(store, SCENE, "next").acquire()
    assert scene_holder(store, SCENE)["owner"] == "next"
    lease.release()
    assert scene_holder(store, SCENE) is None


def test_an_s3_lease_of_another_host_lapses_only_after_its_time_to_live(s3_server):
    """A lease written on another host (its process cannot be asked), or here in another pid
    namespace (a container sharing the host's name), holds the scene until it has gone
    unrenewed for its time to live, whatever its pid is here."""
    import socket

    gone = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          capture_output=True, text=True, check=True)  # fmt: skip
    pid = int(gone.stdout)
    for where in ({"host": "another-host"}, {"host": socket.gethostname(), "pid_namespace": 1}):
        store = SceneStore(
            f"s3://{s3_server.bucket}/{uuid.uuid4().hex}",
            storage_options=s3_server.storage_options(),
        )
        key = f"{scene_prefix(SCENE)}/{LEASE_NAME}"
        holder = {"owner": "elsewhere", "pid": pid, "ttl_s": 3, **where}
        assert store._write_if(key, json.dumps(holder).encode(), None) is not None
        with pytest.raises(SceneBusyError, match=f"being run by elsewhere on {where['host']}"):
            SceneLease(store, SCENE, "too soon").acquire()
        time.sleep(4.5)  # the server's clock counts whole seconds
        lease = SceneLease(store, SCENE, "next").acquire()
        assert scene_holder(store, SCENE)["owner"] == "next"
        lease.release()


def test_a_killed_runs_lock_file_naming_a_live_process_does_not_hold_the_scene(tmp_path):
    """A run killed outright leaves its lock file naming its pid; once another process has
    that pid, the file alone read as a holder (``cropcraft status``: running, and the early
    refusal would refuse every run). The lock itself is what holds the scene."""
    import socket

    from cropcraft_core.lease import refuse_if_busy

    store = SceneStore(str(tmp_path / "store"))
    path = store._full(f"{scene_prefix(SCENE)}/{LOCK_NAME}")
    os.makedirs(os.path.dirname(path))
    with open(path, "w") as fh:  # as the killed run left it, its pid now another process's
        json.dump({"owner": "killed", "host": socket.gethostname(), "pid": os.getpid()}, fh)
    assert scene_holder(store, SCENE) is None
    refuse_if_busy(store, SCENE)
    with hold_scene(store, SCENE, owner="flow run nightly"):  # a live holder is refused early
        assert scene_holder(store, SCENE)["owner"] == "flow run nightly"
        with pytest.raises(SceneBusyError, match="being run by flow run nightly on"):
            refuse_if_busy(store, SCENE)
    refuse_if_busy(store, SCENE)


def test_a_holder_that_stalled_past_its_lease_learns_it_was_taken_over(s3_server):
    """On object storage a holder that stops renewing (a stalled process) loses the scene to
    the next run; when it resumes, its next renewal finds another version and ``check``
    fails its run rather than let it write over the new holder's results."""
    store = SceneStore(
        f"s3://{s3_server.bucket}/{uuid.uuid4().hex}",
        storage_options=s3_server.storage_options(),
    )
    stalled = SceneLease(store, SCENE, "stalled", ttl_s=2.0, renew_s=1000.0).acquire()
    time.sleep(3.5)
    taker = SceneLease(store, SCENE, "taker", ttl_s=60.0).acquire()
    # the stalled one resumes: one renewal turn
    stalled.renew_s = 0.05
    stalled._stop.set()
    stalled._renewer.join()
    stalled._stop.clear()
    stalled._renew_once()
    with pytest.raises(SceneBusyError, match="lost the scene's lease"):
        stalled.check()
    stalled.release()  # gives back nothing: the lease is the taker's
    with pytest.raises(SceneBusyError, match="being run by taker"):
        SceneLease(store, SCENE, "third").acquire()
    taker.release()


def test_a_renewal_whose_answer_was_lost_keeps_the_lease(s3_server):
    """A renewal that landed but whose answer never came back leaves the holder with an old
    version tag: the next renewal finds the lease still carries this run's token and goes on,
    rather than stopping a healthy run as taken over."""
    store = SceneStore(
        f"s3://{s3_server.bucket}/{uuid.uuid4().hex}",
        storage_options=s3_server.storage_options(),
    )
    lease = SceneLease(store, SCENE, "healthy", ttl_s=60.0, renew_s=1000.0).acquire()
    try:
        lease._tag = '"0123456789abcdef0123456789abcdef"'  # the version before the lost answer
        assert lease._renew_once()
        lease.check()
        assert lease._renew_once() and lease._tag == store._read_tagged(lease.key)[1]
    finally:
        lease.release()
    assert not store._read_tagged(lease.key)[0]


def test_a_server_that_ignores_conditional_writes_is_refused(s3_server):
    """An S3-compatible server that predates conditional writes writes a PUT whatever its
    ``If-None-Match`` / ``If-Match``: two runs could both take a scene and manifest updates
    could be lost. The store finds that out with a probe before its first lease or manifest
    change and refuses the server by name, having written nothing; a server that honours
    them passes the same probe, which leaves nothing behind."""
    root = f"s3://{s3_server.bucket}/{uuid.uuid4().hex}"
    with conftest_s3.server_without_conditional_writes(s3_server) as old:
        store = SceneStore(root, storage_options=old.storage_options())
        refused = (
            r"ignores conditional writes: a PUT with 'If-None-Match: \*'.* and one with "
            r"'If-Match'"
        )
        with pytest.raises(StoreError, match=refused):
            SceneLease(store, SCENE, "first").acquire()
        with pytest.raises(StoreError, match=refused):
            store.update_stage(SCENE, "ingest", status="done", seconds=1.0)
        store.fs.invalidate_cache()
        assert store.fs.find(root) == []
    honest = SceneStore(root, storage_options=s3_server.storage_options())
    with hold_scene(honest, SCENE, "second"):
        honest.fs.invalidate_cache()
        assert [p.rsplit("/", 1)[-1] for p in honest.fs.find(root)] == [LEASE_NAME]


def test_a_stage_whose_run_no_longer_holds_the_scene_writes_nothing(store, request, monkeypatch):
    """A stage on a Dask worker goes on after its run ended (a Ctrl-C, a killed command), and
    a killed run's stage wrote its surfaces over those of a rerun that held the scene, which
    then failed (session 93's overlap audit). A stage's store asks its run's lease before each
    object is moved into place or deleted: the rerun's files stay as they were."""
    from tasks.common import open_store

    if not store._local:  # a stage reads the credentials from its worker's environment
        server: S3Server = request.getfixturevalue("s3_server")
        monkeypatch.setenv("AWS_ACCESS_KEY_ID", server.key)
        monkeypatch.setenv("AWS_SECRET_ACCESS_KEY", server.secret)
        monkeypatch.setenv("AWS_DEFAULT_REGION", server.region)
        monkeypatch.setenv("AWS_ENDPOINT_URL", server.endpoint)
    key = f"{scene_prefix(SCENE)}/surfaces/surfaces.json"
    with hold_scene(store, SCENE, owner="flow run first") as first:
        ours = open_store(store._raw_root, scene=SCENE.prefix, lease=first.token, what="surfaces")
        ours.put_bytes(key, b"first")  # held: written
    with hold_scene(store, SCENE, owner="flow run rerun") as rerun:
        store.put_bytes(key, b"rerun")
        late = open_store(store._raw_root, scene=SCENE.prefix, lease=first.token, what="surfaces")
        with pytest.raises(SceneBusyError, match="surfaces of plotA/soybean/2024-07-01 stops"):
            late.put_bytes(key, b"late")
        with pytest.raises(SceneBusyError, match="flow run rerun holds it now"):
            late.delete(key)
        assert store.get_bytes(key) == b"rerun" and rerun.token != first.token
    hidden = [k for k in store.fs.find(store._full(scene_prefix(SCENE))) if "/.tmp-" in k]
    assert hidden == []  # the refused write's temporary object went with it
