"""Latest-wins work: one worker thread that always handles the newest request.

Slider drags send many changes per second. Queuing them would make the
picture lag ever further behind the hand; dropping all but the newest keeps
the lag at most one update long.
"""

from __future__ import annotations

import logging
import threading
from typing import Callable, Generic, TypeVar

T = TypeVar("T")
log = logging.getLogger(__name__)


class LatestWins(Generic[T]):
    """Run ``handle(request)`` in a worker thread, for the newest request only.

    :meth:`submit` never blocks: a request submitted while the worker is busy
    replaces any request still waiting (no queue), so after a burst the worker
    handles the request in progress and then the last one submitted.

    Parameters
    ----------
    handle : callable(request)
        Runs in the worker thread; an exception is logged and passed to
        ``on_error`` and the worker carries on.
    on_error : callable(request, exception), optional

    Attributes
    ----------
    handled, replaced : int
        Requests handled, and requests dropped because a newer one came.
    """

    def __init__(self, handle: Callable[[T], None],
                 on_error: Callable[[T, BaseException], None] | None = None, *, name: str = "latest-wins") -> None:
        self._handle = handle
        self._on_error = on_error
        self._cv = threading.Condition()
        self._pending: list[T] = []          # at most one request
        self._busy = False
        self._closed = False
        self.handled = 0
        self.replaced = 0
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def submit(self, request: T) -> None:
        """Hand over a request; drops the one still waiting, if any."""
        with self._cv:
            if self._pending:
                self.replaced += 1
            self._pending[:] = [request]
            self._cv.notify_all()

    def wait_idle(self, timeout: float | None = None) -> bool:
        """Block until nothing is waiting or running; False on timeout."""
        with self._cv:
            return self._cv.wait_for(lambda: not self._pending and not self._busy, timeout)

    def close(self) -> None:
        """Stop the worker after the request in progress."""
        with self._cv:
            self._closed = True
            self._cv.notify_all()
        self._thread.join(timeout=5)

    def _run(self) -> None:
        while True:
            with self._cv:
                self._cv.wait_for(lambda: self._pending or self._closed)
                if self._closed:
                    return
                request = self._pending.pop()
                self._busy = True
            try:
                self._handle(request)
            except Exception as exc:  # the worker must survive any request
                log.exception("update failed")
                if self._on_error is not None:
                    try:
                        self._on_error(request, exc)
                    except Exception:
                        log.exception("error handler failed")
            finally:
                with self._cv:
                    self.handled += 1
                    self._busy = False
                    self._cv.notify_all()
