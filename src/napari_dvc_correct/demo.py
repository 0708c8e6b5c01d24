"""``python -m napari_dvc_correct.demo``: napari with the sample data and the plugin's panels.

This is what ``make run`` opens. Options: ``--series`` loads the four-state scan series instead
of the soil pair, ``--no-sample`` starts empty.
"""

from __future__ import annotations

import argparse
import sys

PLUGIN = "napari-dvc-correct"
#: Display names of the panels (napari.yaml), in the order they are docked.
PANELS = ("Correlate", "View", "Self-correct", "Evaluate", "Export")


def make_viewer(sample: str | None = "soil_shear_band", show: bool = True):
    """A viewer with ``sample`` loaded and the four panels docked as tabs on the right.

    Parameters
    ----------
    sample : {"soil_shear_band", "scan_series"} or None
        The sample data to open (npe2 keys), or None for none.
    show : bool
        Show the window (False for tests).

    Returns
    -------
    viewer : napari.Viewer
    widgets : dict of panel name -> widget
    docks : dict of panel name -> the dock holding it (``docks[name].raise_()`` shows its tab)
    """
    import napari

    viewer = napari.Viewer(title="napari-dvc-correct", show=show)
    if sample:
        viewer.open_sample(PLUGIN, sample)
    widgets, docks = {}, {}
    for index, name in enumerate(PANELS):
        dock, widget = viewer.window.add_plugin_dock_widget(PLUGIN, name, tabify=index > 0)
        widgets[name], docks[name] = widget, dock
    # the Correlate tab in front, once the window is on screen (raising before has no effect)
    from qtpy.QtCore import QTimer

    first = docks[PANELS[0]]
    first.raise_()
    QTimer.singleShot(0, first.raise_)
    fit_window(viewer, docks, show=show)
    return viewer, widgets, docks


#: Width of the tabbed panels, as a share of the window (the canvas gets the rest).
PANEL_SHARE = 0.3


def fit_window(viewer, docks: dict, show: bool = True) -> None:
    """Size the window to the screen (maximised when shown) and the tabbed panels to at most
    :data:`PANEL_SHARE` of it (their combo boxes compacted), so the canvas shows the scan large
    next to them."""
    from qtpy.QtCore import Qt

    from .widgets._base import compact

    window = viewer.window._qt_window
    screen = window.screen() if hasattr(window, "screen") else None
    if screen is not None:
        window.setGeometry(screen.availableGeometry())
    for dock in docks.values():
        compact(dock.widget())
        dock.setMinimumWidth(dock.widget().minimumSizeHint().width())
    width = int(PANEL_SHARE * window.width())
    window.resizeDocks(list(docks.values()), [width] * len(docks), Qt.Orientation.Horizontal)
    if show:
        window.showMaximized()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m napari_dvc_correct.demo", description=__doc__)
    parser.add_argument("--series", action="store_true", help="load the four-state scan series")
    parser.add_argument("--no-sample", action="store_true", help="start without sample data")
    args = parser.parse_args(argv)
    sample = None if args.no_sample else ("scan_series" if args.series else "soil_shear_band")
    import napari

    make_viewer(sample)
    napari.run()
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
