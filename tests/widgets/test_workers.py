"""The helpers that run work later or off the main thread: a debounced call, the latest worker."""

from __future__ import annotations

from napari_dvc_correct.widgets import _workers


def test_a_debouncer_calls_once_after_the_last_trigger(qtbot):
    calls = []
    debouncer = _workers.Debouncer(lambda: calls.append(1), delay_ms=50)
    for _ in range(3):
        debouncer.trigger()
    qtbot.waitUntil(lambda: calls == [1], timeout=2000)
    debouncer.trigger()
    debouncer.flush()  # a pending call runs now
    assert calls == [1, 1] and not debouncer.timer.isActive()


def test_only_the_latest_computation_returns(qtbot):
    returned, errors = [], []
    latest = _workers.LatestWorker(errors.append)

    def work(value):
        yield
        return value

    first = latest.start(work, 1, on_returned=returned.append)
    second = latest.start(work, 2, on_returned=returned.append)
    qtbot.waitUntil(lambda: not first.is_running and not second.is_running, timeout=10_000)
    qtbot.waitUntil(lambda: not latest.busy, timeout=10_000)
    assert returned == [2] and errors == []
