"""Matplotlib figures embedded in the docks (Qt canvas), styled like napari's dark theme."""

from __future__ import annotations

import numpy as np
from matplotlib.backends.backend_qtagg import FigureCanvasQTAgg
from matplotlib.figure import Figure
from qtpy.QtCore import QSize

from ..report.plots import FIELD_COLORS  # one colour per field, the report's (noqa: F401)

BACKGROUND = "#262930"
FOREGROUND = "#d1d2d4"
#: Share of its asked height a figure may shrink to in a crowded dock.
MIN_SHARE = 0.6
PHASE_COLORS = ("#9c755f", "#bab0ac", "#76b7b2", "#edc948", "#ff9da7", "#59a14f", "#e15759")


def style_axes(axes) -> None:
    axes.set_facecolor(BACKGROUND)
    for spine in axes.spines.values():
        spine.set_color(FOREGROUND)
    axes.tick_params(colors=FOREGROUND, labelsize=7)
    axes.xaxis.label.set_color(FOREGROUND)
    axes.yaxis.label.set_color(FOREGROUND)
    axes.title.set_color(FOREGROUND)


class PlotCanvas(FigureCanvasQTAgg):
    """A small figure with ``ncols`` axes side by side."""

    def __init__(self, ncols: int = 1, height: float = 2.0, parent=None) -> None:
        # constrained layout: worked out when the figure draws (draw_idle, a later turn of the
        # event loop), not in the slot that plots (tight_layout rendered every label there)
        self.figure = Figure(
            figsize=(4.0, height), dpi=90, facecolor=BACKGROUND, layout="constrained"
        )
        super().__init__(self.figure)
        self.setParent(parent)
        self.axes = [self.figure.add_subplot(1, ncols, i + 1) for i in range(ncols)]
        for axes in self.axes:
            style_axes(axes)
        # asks for ``height`` but may get less in a crowded dock: a fixed minimum made Qt lay the
        # next widget over the figure's bottom (the histogram's x label under the threshold
        # slider); constrained layout fits the labels into whatever height the canvas gets
        self._height = int(height * 90)
        self.setMinimumHeight(int(MIN_SHARE * self._height))

    def sizeHint(self) -> QSize:
        return QSize(super().sizeHint().width(), self._height)

    def redraw(self) -> None:
        self.draw_idle()

    def draw_idle(self) -> None:
        """Draw at the next turn of the event loop, or, while the canvas cannot be seen (its
        dock a tab not on top: Qt keeps it "visible" with an empty visible region; or hidden),
        when it is painted next: a figure drawn unseen took 0.04–0.15 s of main-thread CPU
        each (constrained layout, text; 0.3–0.7 s of frozen window at load 4-8), after every
        run that changed the layers."""
        if not self.isVisible() or self.visibleRegion().isEmpty():
            self._stale = True
            return
        self._stale = False
        super().draw_idle()

    def paintEvent(self, event) -> None:
        if getattr(self, "_stale", False):  # seen again: draw what changed meanwhile
            self._stale = False
            self.draw()
        super().paintEvent(event)


class HistogramCanvas(PlotCanvas):
    """The gray histogram with the phase thresholds drawn on it."""

    def __init__(self, parent=None) -> None:
        super().__init__(1, 1.8, parent)
        self.counts = None
        self.edges = None
        self.lines = []

    def set_histogram(self, counts: np.ndarray, edges: np.ndarray) -> None:
        axes = self.axes[0]
        axes.clear()
        style_axes(axes)
        self.counts, self.edges = counts, edges
        centers = 0.5 * (edges[:-1] + edges[1:])
        axes.fill_between(centers, counts, step="mid", color="#8a8d93", alpha=0.8, linewidth=0)
        axes.set_yscale("log")
        axes.set_xlabel("gray value", fontsize=8)
        axes.set_yticks([])
        self.lines = []
        self.redraw()

    def set_thresholds(self, thresholds) -> None:
        axes = self.axes[0]
        for line in self.lines:
            line.remove()
        self.lines = [
            axes.axvline(t, color=PHASE_COLORS[(i + 1) % len(PHASE_COLORS)], linewidth=1.5)
            for i, t in enumerate(thresholds)
        ]
        self.draw_idle()


class CurvesCanvas(PlotCanvas):
    """Residual vs equivalent strain (paper Fig. 10) and accuracy vs strain (Fig. 11)."""

    def __init__(self, parent=None) -> None:
        super().__init__(2, 2.3, parent)
        self.clear()

    def clear(self) -> None:
        for axes, title in zip(self.axes, ("gray residual", "accuracy index p")):
            axes.clear()
            style_axes(axes)
            axes.set_title(title, fontsize=8)
            axes.set_xlabel("equivalent strain", fontsize=8)
        self.redraw()

    def plot(self, evaluation) -> None:
        """One curve per field, before/after correction on the same axes, side by side plots."""
        self.clear()
        centers = 0.5 * (evaluation.edges[:-1] + evaluation.edges[1:])
        for index, item in enumerate(evaluation.fields):
            color = FIELD_COLORS[index % len(FIELD_COLORS)]
            self.axes[0].plot(
                centers, item.bins.mean_residual, "o-", color=color, markersize=3, label=item.name
            )
            self.axes[1].plot(
                centers, item.bin_accuracy, "o-", color=color, markersize=3, label=item.name
            )
        for axes in self.axes:
            axes.ticklabel_format(axis="x", style="sci", scilimits=(-2, 2))
            axes.xaxis.get_offset_text().set_color(FOREGROUND)
            axes.xaxis.get_offset_text().set_fontsize(7)
        legend = self.axes[1].legend(fontsize=7, facecolor=BACKGROUND, edgecolor=FOREGROUND)
        for text in legend.get_texts():
            text.set_color(FOREGROUND)
        self.redraw()


class SeriesCanvas(PlotCanvas):
    """A series: mean gray residual, accuracy index p and the error estimate against the load
    state, one curve per field, every state ticked (:func:`..report.series.draw_series`, the
    drawing of the command line's series report)."""

    def __init__(self, parent=None) -> None:
        super().__init__(3, 2.4, parent)
        self.rows = []

    def plot(self, rows, x_label: str | None = None) -> None:
        from ..report.series import draw_series

        self.rows = list(rows)
        for axes in self.axes:
            axes.clear()
        draw_series(self.axes, self.rows, x_label)
        for axes in self.axes:
            style_axes(axes)
            axes.title.set_fontsize(8)
        for legend in self.figure.legends:
            for text in legend.get_texts():
                text.set_color(FOREGROUND)
        self.redraw()


class ProfileCanvas(PlotCanvas):
    """Displacement (left) and strain (right) along a line, one curve per field."""

    def __init__(self, parent=None) -> None:
        super().__init__(2, 2.0, parent)

    def plot(self, groups) -> None:
        """``groups`` = [displacement profiles, strain profiles] (:mod:`.profile_model`)."""
        for axes, group in zip(self.axes, groups):
            axes.clear()
            style_axes(axes)
            for index, profile in enumerate(group):
                axes.plot(
                    profile.distance,
                    profile.values,
                    color=FIELD_COLORS[index % len(FIELD_COLORS)],
                    linewidth=1.2,
                    label=profile.source,
                )
            if group:
                unit = group[0].distance_unit
                label = f"distance along the line [{unit}]" if unit else "distance along the line"
                axes.set_xlabel(label, fontsize=8)
                axes.set_ylabel(f"{group[0].quantity} [{group[0].unit}]", fontsize=8)
        if groups and groups[0]:
            legend = self.axes[0].legend(fontsize=7, frameon=False)
            for text in legend.get_texts():
                text.set_color(FOREGROUND)
        self.redraw()
