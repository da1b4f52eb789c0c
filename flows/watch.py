"""Watching a scene's flow run from inside it: a cancel asked of Prefect, and an API gone.

A run started by ``cropcraft run`` or ``season`` is the flow itself, in the command's own
process: no worker stands by to end it when someone cancels it in the UI or with
``prefect flow-run cancel``, so the cancel was ignored (the run finished, left "Cancelling"
for good). And where the Prefect server went away mid-run, a pool worker's task engine died
on it and the flow waited on its future for ever, holding the scene's lease, so that every
later night's run of the scene was refused (session 95's operations audit).

:class:`RunWatch` polls from a daemon thread: the flow run (and its root run, a season's) for
a cancel, and the API's health. Either ends the run as SIGTERM does, which the command and
Prefect already handle: the running stage ends, finished stages stay cached, the lease is
released, children are ended (``flows.cli.interrupt_deadline``). A cancelled run is first
marked Cancelled, so that the UI shows what was asked.
"""

from __future__ import annotations

import contextvars
import logging
import os
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterable
from typing import Any

#: Seconds between two looks at the run's state and the API's health.
POLL_S = 10.0

#: Seconds the API may fail to answer before the run is ended: a server restart takes less.
API_LOST_S = 120.0

#: Seconds after its SIGTERM by which a run the watch ended must have exited: with its API
#: gone, Prefect's engine reports the crash to it and waits there (seen for minutes), so the
#: process then ends its children and exits by itself, 143.
END_GRACE_S = 30.0


_STOPPED: str | None = None


def stop_reason() -> str | None:
    """Why a :class:`RunWatch` of this process ended its run (None: none did), for the
    command's last line."""
    return _STOPPED


class RunWatch:
    """Watch ``run_ids`` (flow run ids: the run and its root) from a daemon thread; call
    ``on_stop(reason, cancelled)`` once, where one is being cancelled (``cancelled``: its id)
    or the API has not answered for ``api_lost_s`` seconds (``cancelled`` None). ``reason`` is
    one line for the log and the user.

    The thread runs in a copy of the starting thread's context, so that it reaches the API
    the flow reaches (the command's temporary server is set there, not in the environment).
    """

    def __init__(
        self,
        run_ids: Iterable[str],
        on_stop: Callable[[str, str | None], None],
        *,
        poll_s: float = POLL_S,
        api_lost_s: float = API_LOST_S,
    ) -> None:
        self.run_ids = [str(r) for r in dict.fromkeys(run_ids) if r]
        self.on_stop = on_stop
        self.poll_s = float(poll_s)
        self.api_lost_s = float(api_lost_s)
        self._halt = threading.Event()
        self._thread: threading.Thread | None = None

    def __enter__(self) -> RunWatch:
        ctx = contextvars.copy_context()
        self._thread = threading.Thread(
            target=ctx.run, args=(self._loop,), name="cropcraft-run-watch", daemon=True
        )
        self._thread.start()
        return self

    def __exit__(self, *exc: Any) -> None:
        self._halt.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=self.poll_s + 5.0)

    def _loop(self) -> None:
        from prefect.client.orchestration import get_client
        from prefect.settings import PREFECT_API_URL

        url = PREFECT_API_URL.value() or "Prefect's API"
        lost_since: float | None = None
        with get_client(sync_client=True) as client:
            while not self._halt.wait(self.poll_s):
                try:
                    error = client.api_healthcheck()
                    cancelling = None if error else self._cancelling(client)
                except Exception as exc:  # the server answered, then failed
                    error, cancelling = exc, None
                if error is None:
                    lost_since = None
                    if cancelling is not None:
                        self._stop(f"flow run {cancelling} was cancelled in Prefect", cancelling)
                        return
                    continue
                now = time.monotonic()
                lost_since = now if lost_since is None else lost_since
                if now - lost_since >= self.api_lost_s:
                    self._stop(
                        f"the Prefect API at {url} has not answered for "
                        f"{now - lost_since:.0f} s ({type(error).__name__}): the run stops, "
                        "its finished stages kept; run it again once the server is back",
                        None,
                    )
                    return

    def _cancelling(self, client: Any) -> str | None:
        from prefect.client.schemas.objects import StateType

        for run_id in self.run_ids:
            state = client.read_flow_run(run_id).state
            if state is not None and state.type in (StateType.CANCELLING, StateType.CANCELLED):
                return run_id
        return None

    def _stop(self, reason: str, cancelled: str | None) -> None:
        global _STOPPED
        if not self._halt.is_set():  # not once the run has finished
            _STOPPED = reason
            self.on_stop(reason, cancelled)


def end_this_run(log: logging.Logger | logging.LoggerAdapter) -> Callable:
    """The ``on_stop`` of a flow in this process: log the reason, mark the cancelled run
    Cancelled, then SIGTERM this process (as a scheduler's stop: the command exits 143)."""

    def stop(reason: str, cancelled: str | None) -> None:
        log.error("%s", reason)
        if cancelled:
            try:
                from prefect.client.orchestration import get_client
                from prefect.states import Cancelled

                with get_client(sync_client=True) as client:
                    client.set_flow_run_state(cancelled, Cancelled(message=reason), force=True)
            except Exception as exc:  # the state is the UI's; ending the run matters more
                log.warning("could not mark flow run %s cancelled: %s", cancelled, exc)
            try:  # Prefect 3.9's engine then ends the run Cancelled, as a worker's cancel, not
                # Crashed over the state above (the intent a worker's runner sets)
                from prefect._internal.control_listener import _set_intent

                _set_intent("cancel")
            except ImportError:  # pragma: no cover - older Prefect: Crashed, with the reason
                pass
        timer = threading.Timer(END_GRACE_S, _end_now, args=(reason,))
        timer.daemon = True
        timer.start()
        os.kill(os.getpid(), signal.SIGTERM)

    return stop


def _end_now(reason: str) -> None:
    from flows.cli import end_children

    print(f"cropcraft: {reason}; ending its processes", file=sys.stderr, flush=True)
    end_children()
    os._exit(143)


def watch_this_run(log: logging.Logger | logging.LoggerAdapter) -> RunWatch | None:
    """A :class:`RunWatch` of the flow run this code runs in and of its root run, ending this
    process's run on a cancel or a lost API; None outside a flow run."""
    try:
        from prefect.runtime import flow_run

        run_id = flow_run.id
        root = flow_run.root_flow_run_id
    except Exception:  # pragma: no cover - outside a run
        return None
    if not run_id:
        return None
    return RunWatch([run_id, root], end_this_run(log))
