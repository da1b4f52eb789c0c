"""The ``dask`` runners' task runner: prefect-dask's, with the workers' progress on this
process's console, and a run that ends when its cluster has no worker left.

* Progress: a task on a Dask worker has no progress sink of its own
  (``tasks.common.set_progress_sink``): it sends its progress to the scheduler as an event on
  ``tasks.common.PROGRESS_TOPIC``, and the run's client, subscribed to that topic, hands each
  to this process's sink. Before, ``cropcraft run --runner dask`` printed nothing through
  minutes of stereo and the whole fit (session 92's Dask audit).
* No worker: a run waits on its tasks for as long as they take, so a cluster whose workers all
  ended (a worker that cannot import the project ends its whole ``dask worker`` command at its
  first task) left the run waiting silently for good (session 93's Dask audit: a nightly
  season would hang). The client's scheduler is asked for its workers every
  :data:`POLL_S`; with none for :data:`NO_WORKER_S`, the run's unfinished tasks are cancelled
  with the reason, and the run fails in one line naming it.

Imported only where a Dask runner is asked for (prefect-dask is needed then).
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Any

from prefect_dask import DaskTaskRunner

from tasks.common import PROGRESS_TOPIC, deliver_event

log = logging.getLogger("cropcraft")

#: Seconds between two questions to the scheduler for its workers.
POLL_S = 2.0
#: Seconds a run's cluster may go without a worker (a nanny restarts a killed one in ~2 s).
NO_WORKER_S = 20.0


class DaskTaskRunnerWithProgress(DaskTaskRunner):
    """``DaskTaskRunner`` whose client, once made, subscribes to the workers' progress and is
    watched for a cluster without workers (see the module docstring)."""

    no_worker_s: float = NO_WORKER_S

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._submitted: list[Any] = []  # the run's Dask futures, pruned as they finish
        self._watch_stop = threading.Event()
        self._watch: threading.Thread | None = None

    # Prefect pickles the flow's context, its task runner included, for each task it sends:
    # the watch's event, thread and futures stay in this process (they hold locks)
    _LOCAL = ("_submitted", "_watch_stop", "_watch")

    def __getstate__(self) -> dict[str, Any]:
        return {k: v for k, v in self.__dict__.items() if k not in self._LOCAL}

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        self._submitted, self._watch_stop, self._watch = [], threading.Event(), None

    @property
    def client(self) -> Any:
        fresh = self._client is None
        client = super().client
        if fresh:
            client.subscribe_topic(PROGRESS_TOPIC, deliver_event)
            self._watch = threading.Thread(
                target=self._watch_workers, args=(client,), name="cropcraft-dask-workers",
                daemon=True,
            )  # fmt: skip
            self._watch.start()
        return client

    def submit(self, task: Any, *args: Any, **kwargs: Any) -> Any:
        future = super().submit(task, *args, **kwargs)
        self._submitted = [f for f in self._submitted if not f.done()]
        self._submitted.append(future.wrapped_future)
        return future

    def __exit__(self, *args: Any) -> None:
        self._watch_stop.set()
        if self._watch is not None:
            self._watch.join(timeout=2 * POLL_S)
        super().__exit__(*args)

    def _watch_workers(self, client: Any) -> None:
        since: float | None = None
        while not self._watch_stop.wait(POLL_S):
            try:
                workers = len(client.nthreads())
            except Exception:  # the scheduler gone: Dask's own connection loss cancels
                continue
            if workers:
                since = None
                continue
            since = since or time.monotonic()
            waiting = [f for f in self._submitted if not f.done()]
            if waiting and time.monotonic() - since >= self.no_worker_s:
                msg = (
                    f"the Dask scheduler at {client.scheduler.address} has had no worker for "
                    f"{self.no_worker_s:.0f} s: its workers ended (a worker that cannot import "
                    "the project ends at its first task: see its log); start them as "
                    "deploy/README.md shows and run again"
                )
                log.error("%s", msg)
                client.cancel(waiting, reason="no-workers", msg=msg)
                since = None
