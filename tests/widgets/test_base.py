"""A failing worker shows one line and never re-raises on the main thread (issue 12, item 5)."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import pytest

from napari_dvc_correct.engine.progress import Progress
from napari_dvc_correct.widgets._base import EngineWidget


class Failing(EngineWidget):
    def __init__(self, error):
        super().__init__(napari_viewer=None)
        self.error = error

    def prepare(self):
        def generator():
            yield Progress("work", 0, 1, "")
            raise self.error

        return generator()

    def on_result(self, result):  # pragma: no cover - never reached
        raise AssertionError("no result expected")


@pytest.mark.parametrize(
    "error", [ValueError("bad\nchoice"), RuntimeError("deep failure"), KeyError("lost")]
)
def test_worker_error_is_one_line_and_not_reraised(qtbot, error):
    widget = Failing(error)
    qtbot.addWidget(widget)
    worker = widget.run(start=False)
    # pytest-qt fails the test if an exception escapes into the Qt event loop (the re-raise)
    with qtbot.waitSignal(worker.finished, timeout=30_000):
        worker.start()
    qtbot.waitUntil(lambda: widget.last_error is not None and not widget.running, timeout=5000)
    assert widget.last_error is not None and "\n" not in widget.last_error
    assert widget.stage_label.text() == "failed"
    assert widget.run_button.isEnabled() and not widget.running


def test_plain_qt_host_survives_a_worker_error(tmp_path):
    """A host without napari's event loop (plain QApplication) does not abort (was rc 134)."""
    script = textwrap.dedent(
        """
        import sys
        from qtpy.QtWidgets import QApplication
        from qtpy.QtCore import QTimer
        app = QApplication(sys.argv)
        from napari_dvc_correct.widgets._base import EngineWidget

        class Failing(EngineWidget):
            def prepare(self):
                def generator():
                    yield from ()
                    raise RuntimeError("deep failure")
                return generator()
            def on_result(self, result):
                pass

        widget = Failing(None)
        worker = widget.run(start=False)
        worker.finished.connect(lambda: QTimer.singleShot(100, app.quit))
        worker.start()
        QTimer.singleShot(20_000, app.quit)
        app.exec_()
        print("message:", widget.last_error)
        """
    )
    env = dict(os.environ, QT_QPA_PLATFORM="offscreen")
    done = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=120, env=env
    )
    assert done.returncode == 0, done.stderr[-2000:]
    assert "message: deep failure" in done.stdout


class BrokenResult(EngineWidget):
    def prepare(self):
        def generator():
            yield Progress("work", 0, 1, "")
            return 42

        return generator()

    def on_result(self, result):
        raise KeyError("no layer for this result")


def test_an_error_while_showing_the_result_is_one_line(qtbot):
    widget = BrokenResult(napari_viewer=None)
    qtbot.addWidget(widget)
    worker = widget.run(start=False)
    with qtbot.waitSignal(worker.finished, timeout=30_000):
        worker.start()
    qtbot.waitUntil(lambda: widget.last_error is not None, timeout=5000)
    assert widget.last_error == "KeyError: 'no layer for this result'"


def test_a_panel_closed_during_a_run_stops_it_and_the_process_ends_cleanly():
    """A script that closed its viewer while a run was going (the panel deleted) and then ended
    aborted the process (rc 134: the worker thread emitted through Qt objects the teardown had
    deleted). The closed panel's run now stops at its next progress report, and the process's
    end waits for it."""
    script = textwrap.dedent(
        """
        import sys, time
        from qtpy.QtWidgets import QApplication
        from napari_dvc_correct.engine.progress import Progress
        from napari_dvc_correct.widgets._base import EngineWidget

        app = QApplication(sys.argv)
        reports = []

        class Slow(EngineWidget):
            def prepare(self):
                def generator():
                    for k in range(400):  # 20 s when nobody stops it
                        time.sleep(0.05)
                        reports.append(k)
                        yield Progress("work", k, 400, "")
                return generator()
            def on_result(self, result):
                pass

        widget = Slow(None)
        widget.run()
        end = time.perf_counter() + 0.5
        while time.perf_counter() < end:
            app.processEvents(); time.sleep(0.02)
        widget.deleteLater()
        app.processEvents()
        app.sendPostedEvents(None, 0)  # the deferred delete
        print("closed after", len(reports), "reports", flush=True)
        """
    )
    env = dict(os.environ, QT_QPA_PLATFORM="offscreen")
    done = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=120, env=env
    )
    assert done.returncode == 0, done.stderr[-2000:]
    assert "aborted thread" not in done.stderr and "has been deleted" not in done.stderr
    assert "closed after" in done.stdout


def test_the_worker_imports_what_napari_needs_to_show_the_result(monkeypatch):
    """napari's first Vectors layer imports pandas (0.2 s CPU, the window frozen): the worker
    imports :data:`SHOWING_IMPORTS` after its work, so the main thread finds them loaded; a
    module that is not installed is left to napari."""
    from napari_dvc_correct.widgets import _base

    monkeypatch.setattr(_base, "SHOWING_IMPORTS", ("colorsys", "no_such_module_here"))
    monkeypatch.delitem(sys.modules, "colorsys", raising=False)

    def work():
        yield Progress("work", 0, 1, "")
        assert "colorsys" not in sys.modules  # not before the work (a cancelled run needs none)
        return "result"

    generator = _base._shown_ahead(work(), None)
    with pytest.raises(StopIteration) as stop:
        while True:
            next(generator)
    assert stop.value.value == "result"
    assert "colorsys" in sys.modules
    assert "no_such_module_here" not in sys.modules


class FieldResult(EngineWidget):
    """Returns a small field; shows it as the panels do (one layer per step)."""

    def prepare(self):
        import numpy as np

        from napari_dvc_correct.engine.fields.field import DisplacementField

        def generator():
            yield Progress("work", 0, 1, "")
            u = np.random.default_rng(1).normal(0, 1.0, (4, 5, 6, 3))
            return DisplacementField(origin=(5.0, 5.0, 5.0), step=(4.0, 4.0, 4.0), u=u)

        return generator()

    def on_result(self, result):
        from napari_dvc_correct import layers as L
        from napari_dvc_correct import viewer_layers as V

        yield from V.show_field_steps(self.viewer, L.field_layers(result, "uncorrected"))
        self.show_message("shown")


@pytest.fixture
def field_panel(make_napari_viewer):
    viewer = make_napari_viewer()
    viewer.add_image(__import__("numpy").zeros((30, 30, 30), "float32"), name="scan")
    panel = FieldResult(viewer)
    viewer.window.add_dock_widget(panel)
    return viewer, panel


def _start_with(qtbot, panel, on_returned):
    """Run ``panel``; ``on_returned`` is called right after the panel's own result slot."""
    worker = panel.run(start=False)
    worker.returned.connect(on_returned)
    with qtbot.waitSignal(worker.finished, timeout=30_000):
        worker.start()


def test_a_result_is_shown_one_layer_per_turn_then_shown_is_emitted(qtbot, field_panel):
    viewer, panel = field_panel
    at_returned, shown = [], []
    panel.shown.connect(lambda: shown.append(len(viewer.layers)))
    _start_with(qtbot, panel, lambda result: at_returned.append(len(viewer.layers)))
    assert at_returned == [1]  # the first step hides the other fields; the layers come after
    qtbot.waitUntil(lambda: bool(shown), timeout=10_000)
    assert shown == [3]
    assert [x.name for x in viewer.layers][1:] == [
        "|u| (uncorrected)",
        "displacement (uncorrected)",
    ]
    assert panel.message.text() == "shown" and not panel.running
    assert panel.run_button.isEnabled() and not panel.cancel_button.isEnabled()


def test_a_new_run_first_shows_the_last_result_whole(qtbot, field_panel):
    viewer, panel = field_panel
    _start_with(qtbot, panel, lambda result: None)
    if panel.running:  # its steps pending: a new run finishes them before it reads the layers
        assert panel.run(start=False) is not None and len(viewer.layers) == 3
        panel.worker.quit()
        panel.worker.start()
    qtbot.waitUntil(lambda: not panel.running, timeout=10_000)
    assert len(viewer.layers) == 3


def test_a_panel_closed_while_its_result_is_shown_leaves_the_field_whole(qtbot, field_panel):
    viewer, panel = field_panel
    _start_with(qtbot, panel, lambda result: viewer.window.remove_dock_widget(panel))
    qtbot.waitUntil(lambda: not panel._steps.pending, timeout=10_000)
    assert [x.name for x in viewer.layers][1:] == [
        "|u| (uncorrected)",
        "displacement (uncorrected)",
    ]


def test_a_viewer_closed_while_a_result_is_shown_drops_the_rest(qtbot, field_panel):
    viewer, panel = field_panel
    _start_with(qtbot, panel, lambda result: viewer.close())
    assert not panel._steps.pending
    qtbot.wait(50)  # nothing more is added to the closed viewer (pytest-qt fails on an error)
    assert "displacement (uncorrected)" not in viewer.layers  # (napari empties a closed one)


def test_the_process_ends_cleanly_with_a_result_half_shown():
    """A script whose last run's result is still being shown when it ends (no more turns of
    the event loop) exits with status 0."""
    script = textwrap.dedent(
        """
        import sys
        from qtpy.QtWidgets import QApplication
        from qtpy.QtCore import QTimer
        app = QApplication(sys.argv)
        from napari_dvc_correct.widgets._base import EngineWidget

        class Slow(EngineWidget):
            def prepare(self):
                def generator():
                    yield from ()
                    return 1
                return generator()
            def on_result(self, result):
                while True:  # never done
                    yield

        widget = Slow(None)
        worker = widget.run(start=False)
        worker.finished.connect(app.quit)
        worker.start()
        QTimer.singleShot(20_000, app.quit)
        app.exec_()
        print("pending:", widget._steps.pending)
        """
    )
    env = dict(os.environ, QT_QPA_PLATFORM="offscreen")
    done = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=120, env=env
    )
    assert done.returncode == 0, done.stderr[-2000:]
    assert "pending: True" in done.stdout
