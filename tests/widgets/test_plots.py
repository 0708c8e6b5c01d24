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
