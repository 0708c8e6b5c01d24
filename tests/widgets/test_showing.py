"""A result shown in steps: one step per turn of the event loop, all of them before a new run,
none after its window closed."""

from __future__ import annotations

import pytest
from qtpy.QtCore import QTimer
from qtpy.QtWidgets import QWidget

from napari_dvc_correct.widgets import _showing


def _counting(record: list, n: int):
    for k in range(n):
        record.append(k)
        if k < n - 1:
            yield


@pytest.fixture
def window(qtbot):
    widget = QWidget()
    qtbot.addWidget(widget)
    return widget


def test_one_step_per_turn_of_the_event_loop(qtbot, window):
    done, errors, record, ticks = [], [], [], []
    steps = _showing.Steps(errors.append)
    timer = QTimer()  # a tick between two steps: the event loop turned (and could draw)
    timer.setInterval(0)
    timer.timeout.connect(lambda: ticks.append(len(record)))
    timer.start()
    steps.start(_counting(record, 4), window, lambda: done.append(True))
    assert record == [0] and steps.pending  # the first step at once, the others later
    qtbot.waitUntil(lambda: not steps.pending, timeout=5000)
    timer.stop()
    assert record == [0, 1, 2, 3] and done == [True] and errors == []
    assert {1, 2, 3} <= set(ticks), ticks  # the loop ticked after each of the first three steps


def test_finish_all_runs_what_is_pending_now(window):
    record, done = [], []
    steps = _showing.Steps(print)
    steps.start(_counting(record, 3), window, lambda: done.append(True))
    _showing.finish_all()
    assert record == [0, 1, 2] and done == [True] and not steps.pending
    # a new start finishes the steps still pending before
    first, second = [], []
    steps.start(_counting(first, 3), window, lambda: None)
    steps.start(_counting(second, 2), window, lambda: None)
    assert first == [0, 1, 2] and second == [0]
    steps.finish()


def test_an_error_in_a_step_is_reported_and_ends_the_steps(qtbot, window):
    errors, done = [], []

    def failing():
        yield
        raise KeyError("no such layer")

    steps = _showing.Steps(errors.append)
    steps.start(failing(), window, lambda: done.append(True))
    qtbot.waitUntil(lambda: bool(errors), timeout=5000)
    assert isinstance(errors[0], KeyError) and not done and not steps.pending


def test_steps_of_a_closed_window_are_dropped(qtbot):
    top = QWidget()
    panel = QWidget(top)  # a panel in its window
    record, done = [], []
    steps = _showing.Steps(print)
    steps.start(_counting(record, 5), panel, lambda: done.append(True))
    top.close()
    assert not steps.pending
    qtbot.wait(50)
    assert record == [0] and not done
    top.deleteLater()


def test_steps_of_a_closed_panel_go_on_in_its_window(qtbot, window):
    """A panel taken out of its window (napari's close button on a dock) mid-way: the
    result's layers are still added, whole."""
    panel = QWidget(window)
    record, done = [], []
    steps = _showing.Steps(print)
    steps.start(_counting(record, 3), panel, lambda: done.append(True))
    panel.setParent(None)
    panel.deleteLater()
    qtbot.waitUntil(lambda: not steps.pending, timeout=5000)
    assert record == [0, 1, 2] and done == [True]


def test_a_step_that_asks_to_finish_does_not_reenter(qtbot, window):
    """An event handled inside a step (a click on Run while napari works) that finishes the
    pending steps leaves the running step alone; the steps go on in their turns."""
    record = []

    def steps():
        record.append(0)
        yield
        _showing.finish_all()  # from inside a step: nothing runs twice
        record.append(1)
        yield
        record.append(2)

    runner = _showing.Steps(print)
    runner.start(steps(), window, lambda: record.append("done"))
    qtbot.waitUntil(lambda: not runner.pending, timeout=5000)
    assert record == [0, 1, 2, "done"]
