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
        from prefect_dask import DaskTaskRunner
    except ImportError as exc:  # pragma: no cover - a dependency
        raise ConfigError(f"runner {spec!r} needs prefect-dask: pip install prefect-dask") from exc
    if address:
        return DaskTaskRunner(address=address)
    return DaskTaskRunner(
        cluster_class=local_cluster,
        cluster_kwargs={
            "n_workers": n,
            "threads_per_worker": 1,
            "processes": True,
            "dashboard_address": None,
        },
    )


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
        self._initargs = (_flow_api_url(), self._progress_queue)
        try:
            return super().__enter__()
        except BaseException:
            self._stop_relay()
            raise

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


_IN_WORKER = False


def _init_worker(api_url: str | None, progress_queue: Any) -> None:
    """A :class:`LocalProcessPool` worker's set-up: the flow's API, progress into the queue."""
    global _IN_WORKER
    from tasks.common import set_progress_sink

    _IN_WORKER = True
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
    says it all. Any other exception (a defect) keeps its traceback on the console, and the
    Prefect API (the UI) gets every traceback: the record is shortened for the console's
    formatting only."""
    from prefect.logging.handlers import PrefectConsoleHandler

    from cropcraft_core.errors import CropCraftError

    handlers = [h for h in logging.getLogger().handlers if isinstance(h, PrefectConsoleHandler)]
    for h in handlers:

        def fmt(record: logging.LogRecord, plain: Callable = h.format) -> str:
            if record.exc_info and isinstance(record.exc_info[1], CropCraftError):
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
