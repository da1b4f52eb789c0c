"""Task runners for the CropCraft flows: ``processes`` (default: a local pool of spawned worker
processes), ``threads``, ``dask`` (a local cluster) or ``dask://host:port`` (an existing Dask
scheduler), through prefect-dask.

Tasks exchange store keys and small records only, so any runner works; on Dask the workers need
the ``cropcraft`` package and credentials for the scene store in their own environment.
"""

from __future__ import annotations

import copy
import logging
import multiprocessing
import os
import signal
import threading
from collections.abc import Callable
from typing import Any

from prefect.task_runners import ProcessPoolTaskRunner

from cropcraft_core.errors import ConfigError

#: Set (by the CLI) where the consoles of a run's worker processes print named errors in one
#: line (:func:`named_errors_in_one_line`).
ONE_LINE_ERRORS_ENV = "CROPCRAFT_ONE_LINE_ERRORS"

RUNNERS = ("processes", "threads", "dask", "dask://HOST:PORT")

#: The runner a flow gets when none is named: the demo's ten fit seeds took 24 % less time in
#: two processes than in two threads (benchmarks/RESULTS.md *#process-runner*).
DEFAULT_RUNNER = "processes"


def parse_runner(spec: str | None) -> tuple[str, str | None]:
    """``(kind, address)`` of a runner spec; ConfigError for anything else."""
    spec = (spec or DEFAULT_RUNNER).strip()
    if spec in ("threads", "processes"):
        return spec, None
    if spec == "dask":
        return "dask", None
    if spec.startswith("dask://"):
        hostport = spec[len("dask://") :].strip("/")
        host, sep, port = hostport.rpartition(":")
        if not sep or not host or not port.isdigit():
            raise ConfigError(
                f"runner {spec!r}: expected dask://HOST:PORT, e.g. dask://10.0.0.5:8786"
            )
        return "dask", f"tcp://{host}:{port}"
    raise ConfigError(
        f"unknown runner {spec!r}: choose processes, threads, dask or dask://HOST:PORT"
    )


def make_task_runner(spec: str | None = DEFAULT_RUNNER, *, workers: int | None = None) -> Any:
    """A Prefect task runner for ``spec``.

    threads: ``ThreadPoolTaskRunner`` with ``workers`` threads (default: CPU count, at most 8).
    processes: :class:`LocalProcessPool` of ``workers`` spawned processes (default as threads).
    dask: ``DaskTaskRunner`` over a temporary :func:`local_cluster` of ``workers``
    single-threaded worker processes (default as threads). dask://host:port:
    ``DaskTaskRunner(address=...)``.
    """
    kind, address = parse_runner(spec)
    n = workers or min(8, os.cpu_count() or 2)
    if kind in ("threads", "processes"):
        from prefect.task_runners import ThreadPoolTaskRunner

        if kind == "processes":
            return LocalProcessPool(max_workers=n)
        return ThreadPoolTaskRunner(max_workers=n)
    try:
        from flows.dask_runner import DaskTaskRunnerWithProgress as runner
    except ImportError as exc:  # pragma: no cover - a dependency
        raise ConfigError(f"runner {spec!r} needs prefect-dask: pip install prefect-dask") from exc
    if address:
        check_cluster(address)
        return runner(address=address)
    return runner(
        cluster_class=local_cluster,
        cluster_kwargs={
            "n_workers": n,
            "threads_per_worker": 1,
            "processes": True,
            "dashboard_address": None,
        },
    )


#: Seconds a run waits for an existing Dask scheduler to answer, and then as long again for a
#: worker to join it (:func:`check_cluster`).
DASK_WAIT_S = 20.0


def check_cluster(address: str, wait_s: float = DASK_WAIT_S) -> int:
    """The number of workers of the Dask scheduler at ``address``; ConfigError, in one line,
    where none answers there within ``wait_s`` or it has no worker ``wait_s`` later.

    A wrong address or a stopped scheduler gave a 171-line traceback twice after ~126 s, and a
    scheduler without workers (the documented ``dask worker`` processes end ~19 s after their
    scheduler dies, so the rerun an error advised met a restarted scheduler alone) hung the
    run for good, silent (session 92's Dask audit)."""
    from distributed import Client

    hint = f"start them as deploy/README.md shows (dask worker {address})"
    try:
        client = Client(address, timeout=wait_s, set_as_default=False)
    except (OSError, TimeoutError) as exc:
        raise ConfigError(
            f"no Dask scheduler answers at {address} within {wait_s:.0f} s ({exc}): start it "
            "(dask scheduler; deploy/README.md) or check the runner's address"
        ) from None
    try:
        try:
            client.wait_for_workers(1, timeout=wait_s)
        except (OSError, TimeoutError):
            raise ConfigError(
                f"the Dask scheduler at {address} has no workers ({wait_s:.0f} s waited): {hint}"
            ) from None
        return len(client.scheduler_info().get("workers", {}))
    finally:
        client.close()


class LocalProcessPool(ProcessPoolTaskRunner):
    """Prefect's ``ProcessPoolTaskRunner`` whose worker processes run tasks as the flow's own
    threads would: their task runs report to the flow's Prefect API (``PREFECT_API_URL``; without
    it each worker would start an ephemeral server of its own), and the progress ticks
    (:class:`tasks.common.Tick`: the fit's evaluations, the surfaces' steps) reach the sink
    installed in the flow's process, through a queue drained by a thread while the pool is
    open.

    Seeds in processes skip the GIL that two optimisers share in one process (benchmarks/
    RESULTS.md *#process-runner*). Prefect re-enters a copy of the flow's runner in each worker
    (its context carries the flow); there it starts nothing of its own.
    """

    def __enter__(self) -> LocalProcessPool:
        if _IN_WORKER:
            return super().__enter__()
        ctx = multiprocessing.get_context("spawn")
        self._progress_queue = ctx.Queue()
        self._progress_thread = threading.Thread(
            target=_relay_progress,
            args=(self._progress_queue,),
            daemon=True,
            name="cropcraft-progress-relay",
        )
        self._progress_thread.start()
        self._initializer = _init_worker
        self._initargs = (_flow_api_url(), self._progress_queue, os.getpid())
        try:
            super().__enter__()
        except BaseException:
            self._stop_relay()
            raise
        self._executor = _TasksInterruptible(self._executor)
        return self

    def __exit__(self, *exc: Any) -> None:
        try:
            super().__exit__(*exc)
        finally:
            if not _IN_WORKER:
                self._stop_relay()

    def _stop_relay(self) -> None:
        queue = getattr(self, "_progress_queue", None)
        if queue is None:
            return
        queue.put(None)
        self._progress_thread.join(timeout=5)
        queue.close()
        queue.join_thread()
        self._progress_queue = None


class TaskInterrupted(Exception):
    """A task that Ctrl-C stopped in a :class:`LocalProcessPool` worker, as the flow's process
    receives it (:func:`_interruptible`)."""


class _TasksInterruptible:
    """The pool's executor, each task submitted through :func:`_interruptible`."""

    def __init__(self, executor: Any) -> None:
        self._executor = executor

    def submit(self, fn: Callable[..., Any], /, *args: Any, **kwargs: Any) -> Any:
        return self._executor.submit(_interruptible, fn, *args, **kwargs)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._executor, name)


def _interruptible(fn: Callable[..., Any], /, *args: Any, **kwargs: Any) -> Any:
    """Run one task in a pool worker: Ctrl-C (the terminal's SIGINT, which reaches the
    workers too) stops the task with ``KeyboardInterrupt``, whose crash Prefect records, and
    the flow's process gets it back as :class:`TaskInterrupted`, an Exception. A
    ``KeyboardInterrupt`` sent back as such escaped Prefect's result callback in the flow's
    process and killed the pool's manager thread (a traceback on the console); the pool's
    workers were then never told to exit, and the command hung at exit until its 15 s
    deadline ended it by force (session 91's CLI audit). Between tasks a worker ignores SIGINT
    (:func:`_init_worker`): an idle worker's ``KeyboardInterrupt`` broke the pool. Where the
    worker started with SIGINT ignored (a background job), it stays ignored."""
    main = threading.current_thread() is threading.main_thread()
    if _SIGINT_AT_START is signal.SIG_IGN or not main:
        return fn(*args, **kwargs)
    signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        return fn(*args, **kwargs)
    except KeyboardInterrupt:
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        raise TaskInterrupted("interrupted (Ctrl-C)") from None
    finally:
        signal.signal(signal.SIGINT, signal.SIG_IGN)


_IN_WORKER = False
#: A :class:`LocalProcessPool` worker's SIGINT handling as the worker started.
_SIGINT_AT_START: Any = None


def _init_worker(api_url: str | None, progress_queue: Any, parent: int | None = None) -> None:
    """A :class:`LocalProcessPool` worker's set-up: the flow's API, progress into the queue,
    SIGINT ignored between tasks (:func:`_interruptible`), and an end with its ``parent`` (the
    run's process): a ``kill -9`` of the command left its workers running, finishing their
    stage and writing it into the scene over a rerun's files (session 93's overlap audit),
    as :func:`cropcraft_core.parallel.one_thread`'s workers already end."""
    global _IN_WORKER, _SIGINT_AT_START
    from cropcraft_core.parallel import exit_when_orphaned
    from tasks.common import set_progress_sink

    if parent is not None:
        threading.Thread(target=exit_when_orphaned, args=(parent,), daemon=True).start()

    _IN_WORKER = True
    _SIGINT_AT_START = signal.getsignal(signal.SIGINT)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if api_url:
        os.environ["PREFECT_API_URL"] = api_url

    set_progress_sink(progress_queue.put_nowait)
    if os.environ.get(ONE_LINE_ERRORS_ENV):
        named_errors_in_one_line()


def named_errors_in_one_line() -> Callable[[], None]:
    """Make a named error's record (:class:`~cropcraft_core.errors.CropCraftError`: a corrupt
    photo, a failed SfM, a busy scene) print on this process's console as its one line,
    without Prefect's traceback; returns the undo. A CLI user read ~90 lines of Prefect's own
    frames (the task's record, then the flow's) before the command's one-line error, which
    says it all. So are Ctrl-C's records (``KeyboardInterrupt``, :class:`TaskInterrupted`):
    the command says "interrupted". Any other exception (a defect) keeps its traceback on the
    console, and the Prefect API (the UI) gets every traceback: the record is shortened for
    the console's formatting only."""
    from prefect.logging.handlers import PrefectConsoleHandler

    from cropcraft_core.errors import CropCraftError

    quiet = (CropCraftError, KeyboardInterrupt, TaskInterrupted)
    handlers = [h for h in logging.getLogger().handlers if isinstance(h, PrefectConsoleHandler)]
    for h in handlers:

        def fmt(record: logging.LogRecord, plain: Callable = h.format) -> str:
            if record.exc_info and isinstance(record.exc_info[1], quiet):
                record = copy.copy(record)
                record.exc_info = record.exc_text = record.stack_info = None
            return plain(record)

        h.format = fmt  # an instance attribute: removing it brings the class's back

    def undo() -> None:
        for h in handlers:
            vars(h).pop("format", None)

    return undo


def _relay_progress(queue: Any) -> None:
    """Hand each tick from the workers to this process's sink, until ``None`` arrives."""
    from tasks.common import deliver

    while True:
        try:
            tick = queue.get()
        except (EOFError, OSError):
            return
        if tick is None:
            return
        deliver(tick)


def local_cluster(**kwargs: Any) -> Any:
    """The ``dask`` runner's ``LocalCluster`` (``kwargs`` as LocalCluster's), started when the
    flow starts its task runner, with workers that compute as ``cropcraft``'s own processes do:

    - no ``MALLOC_TRIM_THRESHOLD_`` (Dask's nanny default of 64 KiB made every large array a
      fresh ``mmap``: a fit seed ran 1.9x slower, benchmarks/RESULTS.md *#dask-malloc*; stages
      also undo it themselves on any worker, ``cropcraft_core.parallel.reuse_freed_memory``);
    - the flow's Prefect API (``PREFECT_API_URL``), so that task runs report to the server the
      flow reports to, instead of each worker starting an ephemeral server of its own.
    """
    import dask
    from distributed import LocalCluster

    env = {}
    api = _flow_api_url()
    if api:
        env["PREFECT_API_URL"] = api
    with dask.config.set({"distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None}):
        return LocalCluster(env=env, **kwargs)


def _flow_api_url() -> str | None:
    """The HTTP address of the Prefect API this process talks to (a server's, or the ephemeral
    server's that the flow started), None where there is none to share (an in-process app)."""
    from prefect.client.orchestration import get_client

    try:
        url = str(get_client(sync_client=True).api_url).rstrip("/")
    except Exception:  # no API at all: the workers do as they would have
        return None
    return url if url.startswith(("http://", "https://")) and "//ephem" not in url else None


#: What the temporary server's process runs in place of ``python -m uvicorn ARGS``
#: (:func:`keep_temporary_server_apart`): it asks the kernel to end it (SIGTERM, which uvicorn
#: handles) when the command that started it dies, by any signal, SIGKILL and the OOM killer
#: included; argv[1] is that command's pid, checked after the request so that a command killed
#: before it leaves no server either.
_SERVER_LAUNCH = (
    "import ctypes, os, runpy, signal, sys\n"
    "ctypes.CDLL(None).prctl(1, int(signal.SIGTERM))\n"  # PR_SET_PDEATHSIG
    "if os.getppid() != int(sys.argv[1]):\n"
    "    sys.exit(0)\n"
    "sys.argv = ['uvicorn', *sys.argv[2:]]\n"
    "runpy.run_module('uvicorn', run_name='__main__', alter_sys=True)\n"
)


def keep_temporary_server_apart() -> None:
    """Have the temporary Prefect API server that a flow run without ``PREFECT_API_URL``
    starts run in a session of its own, ended with the command.

    A terminal's Ctrl-C reaches its whole foreground process group: it stopped that server at
    once, and the flow's crash handling then retried the dead server (measured: the main
    thread in ``set_flow_run_state``'s connection retries) until ``cropcraft``'s 15 s deadline
    ended the command by force (session 91's CLI audit). Apart, the server records the
    interrupted run, the flow returns, and Prefect stops the server at exit
    (:func:`flows.cli.end_children` on the forced path); the kernel ends it should the command
    die without either (:data:`_SERVER_LAUNCH`). Prefect's clients take the one server instance
    Prefect keeps for "no port given": this registers ours there, unstarted, so a command that
    answers from the cache starts none. Prefect starts it from the flow's (main) thread, whose
    end is the process's (from another thread, it starts apart without the kernel's end).
    Linux only (``prctl``); elsewhere, or where a server is already made, nothing changes.
    """
    import subprocess
    import sys

    from prefect.server.api import server as prefect_server

    base = prefect_server.SubprocessASGIServer
    if not sys.platform.startswith("linux") or None in base._instances:
        return

    class ServerApart(base):
        def _run_uvicorn_command(self) -> Any:
            # Prefect's own command line, launched apart: its module's `subprocess` is
            # swapped for the call only (the server starts before any pool or thread spawns)
            def popen(args: Any, **kwargs: Any) -> subprocess.Popen:
                cmd = list(args)
                # the kernel's "parent died" is the starting thread's end: only the main one's
                # is the process's (a Prefect thread that started it would end it early)
                main = threading.current_thread() is threading.main_thread()
                if main and cmd[1:3] == ["-m", "uvicorn"]:
                    cmd = [cmd[0], "-c", _SERVER_LAUNCH, str(os.getpid()), *cmd[3:]]
                return subprocess.Popen(cmd, start_new_session=True, **kwargs)

            class Apart:
                def __getattr__(self, name: str) -> Any:
                    return popen if name == "Popen" else getattr(subprocess, name)

            prefect_server.subprocess = Apart()
            try:
                return super()._run_uvicorn_command()
            finally:
                prefect_server.subprocess = subprocess

    ServerApart()  # Prefect's SubprocessASGIServer() now returns this instance
