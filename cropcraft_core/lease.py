"""One run of a scene at a time, on any store: the scene lease.

A scene's run (the scene flow, ingest to export) initialises the scene's manifest, writes
every stage's artefacts and records them. Two runs of one scene at once -- the nightly season
and an ad hoc ``cropcraft run`` of the same date, a run started twice from the Prefect UI, a
retry on a second worker while the first still runs -- would interleave both: a run with other
settings resets the stage records the first is still writing, and each may record artefacts
the other replaced. So a run holds the scene's lease from its first write to its last, and a
second run of the scene is refused at once with :class:`~cropcraft_core.store.SceneBusyError`
naming the holder (who, where, since when).

* Local store: an exclusive ``flock`` on ``{scene}/.run.lock``, held by the run's process and
  released by the kernel however the process ends (no stale lease, nothing to renew); the
  lock file holds the holder's description for the refusal's message.
* S3 (and MinIO, Ceph): an object ``{scene}/.run-lease.json`` created only where none is
  (``If-None-Match: *``) and renewed every ``renew_s`` by the holder (``If-Match`` its own
  version). A holder that stops renewing for ``ttl_s`` -- killed, its machine gone -- is
  taken over by the next run (the lease's age is read on the server's clock only). A holder
  whose lease was taken over (it stalled longer than ``ttl_s``) learns it at its next
  renewal, and :meth:`SceneLease.check`, which the flow calls before every stage and every
  record, then fails its run rather than write over the new holder's.
* Other fsspec stores (``memory://``, ``gs://``): the same object, but its writes are exact
  within one process only; on a store other processes can see (all but ``memory://``) the
  first lease or manifest change of a process warns of it
  (:meth:`~cropcraft_core.store.SceneStore._warn_unguarded`).

Core code: no Prefect here; ``flows/scene.py`` holds the lease around the run.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import json
import logging
import os
import socket
import threading
import uuid
from collections.abc import Iterator
from typing import Any

from cropcraft_core.parallel import process_gone
from cropcraft_core.store import SceneBusyError, SceneKey, SceneStore, StoreError, scene_prefix

__all__ = [
    "LEASE_NAME",
    "LOCK_NAME",
    "SceneLease",
    "hold_scene",
    "require_holder",
    "scene_holder",
]

log = logging.getLogger(__name__)

LOCK_NAME = ".run.lock"
"""A local store's lock file, under the scene's folder (dot-named: hidden from listings)."""

LEASE_NAME = ".run-lease.json"
"""Object storage's lease object, under the scene's prefix (dot-named: hidden)."""

DEFAULT_TTL_S = 600.0
"""Seconds without renewal after which a lease on object storage is taken as abandoned."""

_inprocess = threading.Lock()  # serialises lease writes where the store has no conditional ones


def _now() -> str:
    return _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")


class SceneLease:
    """The lease of one scene's run; see the module docstring. Use :func:`hold_scene`."""

    def __init__(
        self,
        store: SceneStore,
        scene: SceneKey,
        owner: str | None = None,
        *,
        ttl_s: float = DEFAULT_TTL_S,
        renew_s: float | None = None,
    ) -> None:
        if ttl_s <= 0:
            raise ValueError(f"ttl_s must be positive, got {ttl_s}")
        self.store = store
        self.scene = scene
        self.ttl_s = float(ttl_s)
        self.renew_s = float(renew_s) if renew_s is not None else self.ttl_s / 6.0
        self.holder: dict[str, Any] = {
            "owner": owner or f"process {os.getpid()}",
            "host": socket.gethostname(),
            "pid": os.getpid(),
            "pid_namespace": _pid_namespace(),
            "acquired": _now(),
            "token": uuid.uuid4().hex,
            "ttl_s": self.ttl_s,
        }
        self._fh: Any = None  # local: the open, locked file
        self._tag: str | None = None  # object storage: our version of the lease
        self._lost: str | None = None
        self._stop = threading.Event()
        self._renewer: threading.Thread | None = None

    # ---- public -------------------------------------------------------------------------

    @property
    def key(self) -> str:
        name = LOCK_NAME if self.store._local else LEASE_NAME
        return f"{scene_prefix(self.scene)}/{name}"

    def acquire(self) -> SceneLease:
        """Take the scene's lease, or raise :class:`SceneBusyError` naming its holder."""
        if self.store._local:
            self._acquire_local()
        else:
            self._acquire_object()
        log.info("%s: lease taken by %s", self.scene.prefix, self.holder["owner"])
        return self

    @property
    def token(self) -> str:
        """This lease's own token: what a task running elsewhere (a fit seed on a Dask
        worker) hands :func:`require_holder` to learn whether this run still holds the scene."""
        return str(self.holder["token"])

    def check(self) -> None:
        """Raise :class:`SceneBusyError` where this run no longer holds the scene."""
        if self._lost is not None:
            raise SceneBusyError(self._lost)

    def release(self) -> None:
        """Give the scene back (idempotent). A lease already taken over is left alone."""
        self._stop.set()
        if self._renewer is not None:
            self._renewer.join(timeout=30.0)
            self._renewer = None
        if self._fh is not None:
            import fcntl

            with contextlib.suppress(OSError):
                self._fh.seek(0)
                self._fh.truncate()
                fcntl.flock(self._fh.fileno(), fcntl.LOCK_UN)
            self._fh.close()
            self._fh = None
        if self._tag is not None:
            try:
                with self._serial():
                    self.store._delete_if(self.key, self._tag)
            except Exception as exc:  # it lapses after ttl_s anyway
                log.warning("%s: could not release the lease: %s", self.scene.prefix, exc)
            self._tag = None

    def _serial(self) -> contextlib.AbstractContextManager:
        """Where the store has no conditional writes, this process's lease writes one at a
        time (its read-compare-write is exact only so); S3's own conditions need no lock."""
        return contextlib.nullcontext() if self.store.conditional else _inprocess

    # ---- local: flock -------------------------------------------------------------------

    def _acquire_local(self) -> None:
        import fcntl

        folder = self.store._full(scene_prefix(self.scene))
        os.makedirs(folder, exist_ok=True)
        fh = open(os.path.join(folder, LOCK_NAME), "a+")  # noqa: SIM115 - held until release
        try:
            fcntl.flock(fh.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            fh.seek(0)
            text = fh.read()
            fh.close()
            raise SceneBusyError(self._busy_message(_parse(text), None)) from None
        except OSError as exc:  # a filesystem without locks (some network mounts)
            fh.close()
            raise StoreError(
                f"cannot lock {fh.name} ({exc}): the store's folder must allow flock; put the "
                "store on a local disk or on S3"
            ) from exc
        except BaseException:
            fh.close()
            raise
        fh.seek(0)
        fh.truncate()
        fh.write(json.dumps(self.holder, sort_keys=True) + "\n")
        fh.flush()
        self._fh = fh

    # ---- object storage: conditional writes -----------------------------------------------

    def _body(self) -> bytes:
        return (json.dumps({**self.holder, "renewed": _now()}, sort_keys=True) + "\n").encode()

    def _acquire_object(self) -> None:
        self.store._require_conditional(self.key)
        for _ in range(8):  # each turn: create, or find it released, abandoned or held
            with self._serial():
                tag = self.store._write_if(self.key, self._body(), None)
                if tag is None:
                    data, theirs, age = self.store._read_tagged(self.key)
                    if data is None:
                        continue  # released meanwhile: try to create it again
                    holder = _parse(data.decode("utf-8", "replace"))
                    ttl = float(holder.get("ttl_s") or self.ttl_s)
                    gone = _gone_here(holder)
                    if (age is None or age <= ttl) and not gone:
                        raise SceneBusyError(self._busy_message(holder, age))
                    tag = self.store._write_if(self.key, self._body(), theirs)
                    if tag is None:
                        continue  # renewed, released or taken by another run meanwhile
                    log.warning(
                        "%s: took over the lease of %s on %s, %s (its run ended without "
                        "releasing it)",
                        self.scene.prefix,
                        holder.get("owner", "an unknown run"),
                        holder.get("host", "an unknown host"),
                        f"whose process {holder.get('pid')} is gone"
                        if gone
                        else f"not renewed for {age:.0f} s",
                    )
            self._tag = tag
            self._renewer = threading.Thread(
                target=self._renew, name=f"lease-{self.scene.prefix}", daemon=True
            )
            self._renewer.start()
            return
        raise SceneBusyError(
            f"{self.store.url(self.key)}: the scene's lease changed hands 8 times while this run "
            "tried to take it; other runs of the scene are starting: try again later"
        )

    def _renew(self) -> None:
        while not self._stop.wait(self.renew_s):
            if not self._renew_once():
                return

    def _renew_once(self) -> bool:
        """One renewal: False once the lease was found taken over (then ``check`` fails)."""
        try:
            with self._serial():
                tag = self.store._write_if(self.key, self._body(), self._tag)
        except Exception as exc:  # transient: the next turn tries again within ttl_s
            log.warning("%s: could not renew the lease: %s", self.scene.prefix, exc)
            return True
        if tag is None and self._still_ours():
            return True
        if tag is None:
            self._lost = (
                f"{self.scene.prefix}: this run ({self.holder['owner']}) lost the scene's "
                f"lease: it was not renewed for {self.ttl_s:.0f} s and another run took it "
                "over; this run stops rather than write over that run's results"
            )
            log.error("%s", self._lost)
            self._tag = None
            return False
        self._tag = tag
        return True

    def _still_ours(self) -> bool:
        """After a renewal found another version: True where that version is still this
        run's own (a renewal whose answer was lost on the network did land), adopting it."""
        try:
            data, tag, _ = self.store._read_tagged(self.key)
        except Exception:
            return False
        if (
            data is None
            or _parse(data.decode("utf-8", "replace")).get("token") != (self.holder["token"])
        ):
            return False
        self._tag = tag
        return True

    # ---- messages -----------------------------------------------------------------------

    def _busy_message(self, holder: dict[str, Any], age: float | None) -> str:
        return busy_message(self.scene, holder, age, self.ttl_s)


def busy_message(
    scene: SceneKey, holder: dict[str, Any], age: float | None, ttl_s: float = DEFAULT_TTL_S
) -> str:
    """The refusal of a run of ``scene`` while ``holder`` holds it (its lease renewed ``age``
    seconds ago, on object storage)."""
    who = holder.get("owner") or "another run"
    where = f" on {holder['host']}" if holder.get("host") else ""
    pid = f" (pid {holder['pid']})" if holder.get("pid") else ""
    since = f" since {holder['acquired']}" if holder.get("acquired") else ""
    msg = f"scene {scene.prefix} is being run by {who}{where}{pid}{since}"
    if age is not None:
        ttl = float(holder.get("ttl_s") or ttl_s)
        msg += (
            f"; its lease was renewed {age:.0f} s ago and lapses after {ttl:.0f} s without renewal"
        )
    return msg + ": wait for that run to finish, or stop it, and run this one again"


def _parse(text: str) -> dict[str, Any]:
    try:
        data = json.loads(text)
    except ValueError:
        return {}
    return data if isinstance(data, dict) else {}


@contextlib.contextmanager
def hold_scene(
    store: SceneStore,
    scene: SceneKey,
    owner: str | None = None,
    *,
    ttl_s: float = DEFAULT_TTL_S,
    renew_s: float | None = None,
) -> Iterator[SceneLease]:
    """``with hold_scene(store, scene, owner) as lease: ...``: the scene's lease for the
    block (:class:`SceneLease`); :class:`SceneBusyError` at once where another run holds it.
    Call ``lease.check()`` before each write that must not land after a takeover."""
    lease = SceneLease(store, scene, owner, ttl_s=ttl_s, renew_s=renew_s).acquire()
    try:
        yield lease
    finally:
        lease.release()


def scene_holder(store: SceneStore, scene: SceneKey) -> dict[str, Any] | None:
    """Who holds the scene's lease now, read without taking it (``cropcraft status``): the
    holder's description, or None where no run holds it. Local store: the lock file names its
    holder until release, and holds it while its lock is held (a run killed without releasing
    it lost the lock with its process). Object storage: the
    lease object, within its ``ttl_s`` of its last renewal."""
    return _holder(store, scene)[0]


def require_holder(store: SceneStore, scene: SceneKey, token: str, what: str) -> None:
    """:class:`SceneBusyError` unless the run whose lease carries ``token``
    (:attr:`SceneLease.token`) still holds ``scene``: checked by work that runs apart from its
    run -- a fit seed on a Dask worker goes on after its run failed, was interrupted or lost its
    client -- before it writes into the scene, so that it never writes after its run's last
    write, over a later run's results (``what``: the work, for the message)."""
    holder, _ = _holder(store, scene)
    if holder is not None and holder.get("token") == token:
        return
    now = (
        "no run holds it now"
        if holder is None
        else f"{holder.get('owner') or 'another run'} holds it now"
    )
    raise SceneBusyError(
        f"{what} of {scene.prefix} stops without writing: the run that started it no longer "
        f"holds the scene ({now}); it ended, was interrupted or lost its lease, and a rerun "
        "computes what is missing"
    )


def refuse_if_busy(store: SceneStore, scene: SceneKey) -> None:
    """:class:`SceneBusyError`, with the message a run's own lease would give, where another
    run holds ``scene`` now: checked before a run starts its flow, so that a busy scene is
    refused in one line, not after Prefect has started a flow run that fails. The run still
    takes the lease itself (:func:`hold_scene`); this only answers early."""
    holder, age = _holder(store, scene)
    if holder is not None:
        raise SceneBusyError(busy_message(scene, holder, age))


def _holder(store: SceneStore, scene: SceneKey) -> tuple[dict[str, Any] | None, float | None]:
    """``(holder, seconds since its last renewal)``; see :func:`scene_holder`."""
    if store._local:
        path = os.path.join(store._full(scene_prefix(scene)), LOCK_NAME)
        try:
            with open(path) as fh:
                holder = _parse(fh.read())
                locked = _locked(fh) if holder else None
        except OSError:
            return None, None
        if not holder or locked is False:  # released, or its run was killed
            return None, None
        pid = holder.get("pid")
        if (
            locked is None
            and holder.get("host") == socket.gethostname()
            and isinstance(pid, int)
            and process_gone(pid)
        ):
            return None, None
        return holder, None
    key = f"{scene_prefix(scene)}/{LEASE_NAME}"
    try:
        data, _, age = store._read_tagged(key)
    except Exception:
        return None, None
    if data is None:
        return None, None
    holder = _parse(data.decode("utf-8", "replace"))
    ttl = float(holder.get("ttl_s") or DEFAULT_TTL_S)
    if _gone_here(holder):
        return None, None
    return (holder, age) if age is None or age <= ttl else (None, None)


def _gone_here(holder: dict[str, Any]) -> bool:
    """Whether ``holder`` (an object-storage lease's) ran on this host in a process that is
    gone: a run killed outright here holds no scene, though its lease lapses only after its
    ``ttl_s`` (a rerun after a kill -9 was refused for 10 minutes, while the local lock goes
    with its process; session 91's S3 audit). A pid now another process's reads as alive:
    that lease lapses as any other."""
    pid = holder.get("pid")
    if holder.get("host") != socket.gethostname() or not isinstance(pid, int) or pid <= 0:
        return False
    # the same pids: containers sharing the host's name (host networking) do not share them
    if holder.get("pid_namespace") is None or holder.get("pid_namespace") != _pid_namespace():
        return False
    return process_gone(pid)


def _pid_namespace() -> int | None:
    """This process's pid namespace (Linux: its inode), where a lease's pid can be asked; None
    elsewhere (then no holder is taken as gone before its lease lapses)."""
    try:
        return os.stat("/proc/self/ns/pid").st_ino
    except OSError:
        return None


def _locked(fh: Any) -> bool | None:
    """Whether a run holds the lock on the open lock file ``fh`` (a shared lock tried and
    given back at once; it cannot succeed while a run holds its exclusive one); None where the
    filesystem cannot tell (no flock: the holder's pid is read instead)."""
    import fcntl

    try:
        fcntl.flock(fh.fileno(), fcntl.LOCK_SH | fcntl.LOCK_NB)
    except BlockingIOError:
        return True
    except OSError:
        return None
    fcntl.flock(fh.fileno(), fcntl.LOCK_UN)
    return False
