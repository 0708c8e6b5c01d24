"""A result shown in steps, one turn of the Qt event loop each, so the window never freezes for
long while napari builds the new layers.

A panel's ``on_result`` may be a generator: each ``yield`` ends a step (the viewer layer
helpers yield between two layers, :func:`..viewer_layers.show_field_steps`). napari builds a
new layer's visual, its layer controls and its colorbar on the main thread (0.1-0.7 s each on
the development machine); run back to back, a field's two layers froze the window for up to
1.25 s. Between two steps Qt draws, ticks its timers and takes clicks.

One :class:`Steps` per panel. Its timer is a child of the panel's top window (the napari
window when the panel is docked, floating or not), so the steps of a panel closed
mid-way still run (its layers end whole) and those of a closed window are dropped (nothing is
added to a viewer being torn down). :func:`finish_all` runs every pending step now: a new run
reads the layers the last one made.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Generator

from qtpy.QtCore import QEvent, QObject, QTimer

log = logging.getLogger(__name__)

#: The :class:`Steps` with steps pending (held, so their timers keep a live slot).
_PENDING: set = set()


def finish_all() -> None:
    """Run the pending steps of every panel now (before a run reads the layers)."""
    for steps in list(_PENDING):
        steps.finish()


class Steps(QObject):
    """Runs a generator's steps, one per event-loop turn, then calls ``done``.

    Parameters
    ----------
    on_error : callable(Exception)
        Gets an exception raised by a step; the steps after it are dropped.
    """

    def __init__(self, on_error: Callable[[Exception], None]) -> None:
        super().__init__()
        self.on_error = on_error
        self._steps: Generator | None = None
        self._done: Callable[[], None] | None = None
        self._timer: QTimer | None = None
        self._window = None
        self._in_step = False

    @property
    def pending(self) -> bool:
        """True while steps are left to run."""
        return self._steps is not None

    def start(self, steps: Generator, owner, done: Callable[[], None]) -> None:
        """Run the first step of ``steps`` now and the others one per turn of the event loop;
        then ``done()``. ``owner`` is the panel (its top window holds the timer). Steps still
        pending from before run first, now."""
        self.finish()
        self._steps, self._done = steps, done
        _PENDING.add(self)
        window = owner
        while window.parentWidget() is not None:
            window = window.parentWidget()
        self._window = window
        self._timer = QTimer(window)
        self._timer.setSingleShot(True)
        self._timer.setInterval(0)
        self._timer.timeout.connect(self._next)
        window.installEventFilter(self)
        self._next()

    def finish(self) -> None:
        """Run the pending steps now, to the end (not from inside a step: an event handled
        while napari works in a step must not run the next one)."""
        while self.pending and not self._in_step:
            self._next(schedule=False)

    def drop(self) -> None:
        """Forget the pending steps (their window is closing)."""
        if self._steps is not None:
            log.info("result steps dropped: the window closed")
        self._end()

    def eventFilter(self, watched, event) -> bool:
        if event.type() == QEvent.Type.Close and watched is self._window:
            self.drop()
        return False

    def _next(self, schedule: bool = True) -> None:
        steps = self._steps
        if steps is None or self._in_step:
            return
        self._in_step = True
        error = None
        try:
            next(steps)
        except StopIteration:
            ended = True
        except Exception as raised:  # shown by the panel; what is left is dropped
            ended, error = True, raised
        else:
            ended = False
        finally:
            self._in_step = False
        if ended:
            done = self._done
            self._end()
            if error is not None:
                self.on_error(error)
            elif done is not None:
                done()
        elif schedule and self._timer is not None:
            try:
                self._timer.start()
            except RuntimeError:  # the window was deleted without a close event
                self._end()

    def _end(self) -> None:
        self._steps = self._done = None
        _PENDING.discard(self)
        if self._window is not None:
            try:
                self._window.removeEventFilter(self)
                self._timer.stop()
                self._timer.deleteLater()
            except RuntimeError:  # deleted with its window
                pass
        self._window = self._timer = None
