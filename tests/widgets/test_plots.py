"""The docks' matplotlib figures: the histogram with its thresholds, styled for the dark theme."""

import numpy as np

from napari_dvc_correct.widgets import _plots


def test_the_histogram_shows_the_counts_and_one_line_per_threshold(qtbot):
    canvas = _plots.HistogramCanvas()
    qtbot.addWidget(canvas)
    counts, edges = np.array([5, 50, 500, 50]), np.array([0.0, 1.0, 2.0, 3.0, 4.0])
    canvas.set_histogram(counts, edges)
    assert canvas.counts is counts and canvas.edges is edges
    axes = canvas.axes[0]
    assert axes.get_yscale() == "log" and axes.get_xlabel() == "gray value"
    canvas.set_thresholds([1.5, 2.5])
    assert [line.get_xdata()[0] for line in canvas.lines] == [1.5, 2.5]
    assert len(axes.lines) == 2
    canvas.set_thresholds([3.0])  # the old lines go
    assert len(axes.lines) == 1 and canvas.lines[0].get_xdata()[0] == 3.0
    colors = {line.get_color() for line in canvas.lines}
    assert colors <= set(_plots.PHASE_COLORS)


def test_every_axes_is_styled_for_the_dark_theme(qtbot):
    canvas = _plots.PlotCanvas(ncols=3)
    qtbot.addWidget(canvas)
    assert len(canvas.axes) == 3
    for axes in canvas.axes:
        assert axes.get_facecolor()[:3] == _rgb(_plots.BACKGROUND)


def _rgb(color):
    from matplotlib.colors import to_rgb

    return to_rgb(color)


def test_a_crowded_dock_shrinks_the_histogram_instead_of_covering_its_label(qtbot):
    """The Evaluate dock put the threshold slider over the histogram's 'gray value' label when
    it had less height than it asked for (user audit, item 4): the canvas now shrinks, its
    labels inside it, and nothing is laid over it."""
    from qtpy.QtCore import Qt
    from qtpy.QtWidgets import QLayout, QSlider, QVBoxLayout, QWidget

    host = QWidget()
    qtbot.addWidget(host)
    layout = QVBoxLayout(host)
    layout.setSizeConstraint(QLayout.SizeConstraint.SetNoConstraint)
    canvas = _plots.HistogramCanvas()
    slider = QSlider(Qt.Orientation.Horizontal)
    layout.addWidget(canvas)
    layout.addWidget(slider)
    canvas.set_histogram(np.array([5, 50, 500, 50]), np.array([0.0, 1.0, 2.0, 3.0, 4.0]))
    assert canvas.sizeHint().height() == 162  # what it asks for
    host.resize(400, 150)  # less than that and the slider
    host.show()
    qtbot.waitExposed(host)
    assert canvas.geometry().bottom() < slider.geometry().top()
    canvas.draw()
    label = canvas.axes[0].xaxis.label.get_window_extent(canvas.get_renderer())
    assert label.y0 >= 0 and label.y1 <= canvas.figure.bbox.height  # inside the figure


def test_a_hidden_figure_draws_when_it_is_shown_not_before(qtbot, monkeypatch):
    """A figure in a dock tab not on top drew on every change (0.04–0.15 s of main-thread CPU
    each, more at load, the window frozen after a run): it now draws once, when it is shown."""
    canvas = _plots.HistogramCanvas()
    qtbot.addWidget(canvas)
    drawn = []
    monkeypatch.setattr(canvas, "draw", lambda: drawn.append(1))
    canvas.set_histogram(np.array([5, 50, 500, 50]), np.array([0.0, 1.0, 2.0, 3.0, 4.0]))
    canvas.set_thresholds([1.5, 2.5])
    qtbot.wait(100)
    assert drawn == []  # hidden: nothing drawn
    canvas.show()
    qtbot.waitExposed(canvas)
    qtbot.waitUntil(lambda: len(drawn) >= 1, timeout=5000)
    count = len(drawn)
    canvas.set_thresholds([2.0])  # shown: a change draws at the next turn of the loop
    qtbot.waitUntil(lambda: len(drawn) > count, timeout=5000)


def test_a_figure_in_a_dock_tab_not_on_top_draws_when_its_tab_is_raised(qtbot, monkeypatch):
    """napari tabs the plugin's docks: Qt keeps a dock under another tab "visible" (with an
    empty visible region), so the figure waits for its tab to be raised."""
    from qtpy.QtCore import Qt
    from qtpy.QtWidgets import QDockWidget, QLabel, QMainWindow

    window = QMainWindow()
    qtbot.addWidget(window)
    window.setCentralWidget(QLabel("canvas"))
    canvas = _plots.HistogramCanvas()
    docks = [QDockWidget("Evaluate"), QDockWidget("Correlate")]
    docks[0].setWidget(canvas)
    docks[1].setWidget(QLabel("another panel"))
    for dock in docks:
        window.addDockWidget(Qt.DockWidgetArea.RightDockWidgetArea, dock)
    window.tabifyDockWidget(docks[0], docks[1])
    window.resize(900, 600)
    window.show()
    qtbot.waitExposed(window)
    docks[1].raise_()
    qtbot.wait(100)
    drawn = []
    monkeypatch.setattr(canvas, "draw", lambda: drawn.append(1))
    canvas.set_histogram(np.array([5, 50, 500, 50]), np.array([0.0, 1.0, 2.0, 3.0, 4.0]))
    canvas.set_thresholds([1.5])
    qtbot.wait(200)
    assert drawn == []  # under the other tab: nothing drawn
    docks[0].raise_()
    qtbot.waitUntil(lambda: len(drawn) >= 1, timeout=5000)
