"""The demo ``make run`` opens: sample data loaded and the four panels docked."""

from __future__ import annotations

import napari
import pytest

from napari_dvc_correct import demo
from napari_dvc_correct.widgets import CorrelateWidget, EvaluateWidget


@pytest.fixture
def closing():
    viewers = []
    yield viewers
    for viewer in viewers:
        viewer.close()


def test_demo_viewer_has_the_sample_and_the_panels(closing, monkeypatch, qtbot):
    viewer, widgets, docks = demo.make_viewer(show=False)
    closing.append(viewer)
    assert [layer.name for layer in viewer.layers] == ["reference", "deformed"]
    assert set(widgets) == set(demo.PANELS)
    correlate = widgets["Correlate"]
    assert isinstance(correlate, CorrelateWidget)
    assert isinstance(widgets["Evaluate"], EvaluateWidget)
    # the sample's roles picked the inputs
    assert correlate.reference.currentText() == "reference"
    assert correlate.deformed.currentText() == "deformed"
    assert set(docks) == set(demo.PANELS)
    assert all(docks[name].widget() is not None for name in demo.PANELS)


def test_main_runs_napari(monkeypatch, closing):
    made = []

    def fake_make_viewer(sample, show=True):
        made.append(sample)
        return None, {}, {}

    monkeypatch.setattr(demo, "make_viewer", fake_make_viewer)
    monkeypatch.setattr(napari, "run", lambda: None)
    assert demo.main(["--series"]) == 0
    assert demo.main(["--no-sample"]) == 0
    assert made == ["scan_series", None]


def test_the_window_shows_the_canvas_large_next_to_tabbed_panels(closing, qtbot):
    """``make run``: the window fills the screen and the canvas takes most of its width."""
    from qtpy.QtWidgets import QApplication

    viewer, widgets, docks = demo.make_viewer(show=True)
    closing.append(viewer)
    window = viewer.window._qt_window
    QApplication.processEvents()
    area = window.screen().availableGeometry()
    assert window.width() >= 0.9 * area.width() and window.height() >= 0.9 * area.height()
    # the panels take their share, or what their widest needs, not more (the canvas the rest)
    dock = docks["Correlate"]
    needed = max(d.widget().minimumSizeHint().width() for d in docks.values())
    assert dock.width() <= max(demo.PANEL_SHARE * window.width(), needed) + 60
    assert needed <= 0.4 * window.width()  # compact panels (combo boxes elided)
    tabbed = window.tabifiedDockWidgets(docks["Correlate"])
    assert {docks[name] for name in demo.PANELS[1:]} <= set(tabbed)
