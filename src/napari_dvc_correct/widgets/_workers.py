"""Helpers that run work off the main thread or later on it: :class:`Debouncer` (one call after
the last trigger) and :class:`LatestWorker` (derived values in thread workers, only the latest
request shown)."""

from __future__ import annotations

import logging
from collections.abc import Callable, Generator

from qtpy.QtCore import QTimer
from superqt.utils import GeneratorWorker, create_worker

from ._base import _guarded, one_line

log = logging.getLogger(__name__)


class Debouncer:
    """Call ``callback`` once, ``delay_ms`` after the last :meth:`trigger` (main thread)."""

    def __init__(self, callback: Callable[[], None], delay_ms: int = 150, parent=None) -> None:
        self.timer = QTimer(parent)
        self.timer.setSingleShot(True)
        self.timer.setInterval(delay_ms)
        self.timer.timeout.connect(callback)

    def trigger(self, *args) -> None:
        self.timer.start()

    def flush(self) -> None:
        """Run a pending call now (tests, and before a run)."""
        if self.timer.isActive():
            self.timer.stop()
            self.timer.timeout.emit()


class LatestWorker:
    """Derived values computed off the main thread, where only the latest request counts.

    :meth:`start` runs a generator function in a thread worker (signals connected before it
    starts, an ``errored`` handler always). A new :meth:`start` supersedes the running one: that
    one is asked to stop at its next ``yield`` (a computation between two yields cannot be
    interrupted) and its later results reach ``on_yielded`` with ``current=False`` (to be cached,
    not shown); its ``returned`` and errors are dropped. Layers are touched only in the slots,
    which run on the main thread.

    Parameters
    ----------
    on_error : callable(str)
        Shows the one-line message of an error of the latest computation.
    """

    def __init__(self, on_error: Callable[[str], None]) -> None:
        self.on_error = on_error
        self.generation = 0
        self.worker: GeneratorWorker | None = None

    @property
    def busy(self) -> bool:
        """True while the latest computation runs."""
        return self.worker is not None

    def start(
        self,
        function: Callable[..., Generator],
        *args,
        on_yielded: Callable | None = None,
        on_returned: Callable | None = None,
    ) -> GeneratorWorker:
        """Run ``function(*args)`` (a generator function) in a worker; returns the worker.

        ``on_yielded(value, current)`` gets every yielded value; ``on_returned(value)`` the
        return value, only if no later :meth:`start` came.
        """
        self.cancel()
        self.generation += 1
        generation = self.generation

        def current() -> bool:
            return generation == self.generation

        def yielded(value) -> None:
            if on_yielded is not None:
                _unless_closed(on_yielded, value, current())

        def returned(value) -> None:
            if on_returned is not None and current():
                _unless_closed(on_returned, value)

        def errored(error: Exception) -> None:
            if not isinstance(error, ValueError):
                log.error("computing for display failed", exc_info=(type(error), error, None))
            if current():
                _unless_closed(self.on_error, one_line(error))

        def finished() -> None:
            if self.worker is worker:
                self.worker = None

        worker = create_worker(
            _guarded, function(*args), _start_thread=False, _connect={"errored": errored}
        )
        worker.yielded.connect(yielded)
        worker.returned.connect(returned)
        worker.finished.connect(finished)
        self.worker = worker
        worker.start()
        return worker

    def cancel(self) -> None:
        """Stop the running computation at its next yield; nothing of it is shown."""
        self.generation += 1
        if self.worker is not None:
            self.worker.quit()
            self.worker = None


def _unless_closed(callback: Callable, *args) -> None:
    try:
        callback(*args)
    except RuntimeError as error:  # the dock was closed while the worker ran
        if "deleted" not in str(error):
            raise
