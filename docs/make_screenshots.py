"""Regenerate the screenshots of docs/user-guide.md from real runs on the sample data.

Run under a (virtual) display, e.g. ``xvfb-run -a .venv/bin/python docs/make_screenshots.py``.
Every picture comes from the panels doing their job on the 96³ soil sample: Correlate, then
Self-correct, then Evaluate; nothing is drawn by hand.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
from qtpy.QtWidgets import QApplication

from napari_dvc_correct.demo import make_viewer

IMAGES = Path(__file__).resolve().parent / "images"
SIZE = (1500, 950)


def wait(widget) -> float:
    """Run a panel and keep the event loop turning until its worker is done; seconds taken."""
    started = time.perf_counter()
    worker = widget.run()
    if worker is None:
        sys.exit(f"{type(widget).__name__}: {widget.message.text()}")
    while widget.running:
        QApplication.processEvents()
        time.sleep(0.02)
    if widget.last_error:
        sys.exit(f"{type(widget).__name__}: {widget.last_error}")
    return time.perf_counter() - started


def settle(seconds: float = 0.5) -> None:
    end = time.perf_counter() + seconds
    while time.perf_counter() < end:
        QApplication.processEvents()
        time.sleep(0.02)


def front(dock) -> None:
    dock.raise_()
    settle()


def shot(viewer, name: str) -> None:
    settle(1.0)
    viewer.window.screenshot(str(IMAGES / name), canvas_only=False)
    print("wrote", IMAGES / name)


def main() -> None:
    IMAGES.mkdir(exist_ok=True)
    viewer, panels, docks = make_viewer(show=True)
    viewer.window._qt_window.resize(*SIZE)
    settle(1.0)
    correlate = panels["Correlate"]
    front(docks["Correlate"])
    correlate.subvolume.setValue(31)
    correlate.step.setValue(6)
    # look at the z-x plane, where the shear band slips, through the middle row of POIs
    viewer.dims.order = (1, 0, 2)
    correlate._update.flush()
    points = viewer.layers["POI grid (preview)"].data
    rows = np.unique(points[:, 1])
    viewer.dims.set_point(1, float(rows[len(rows) // 2]))
    viewer.layers.selection.active = viewer.layers["POI grid (preview)"]
    shot(viewer, "correlate-preview.png")

    print(f"correlate: {wait(correlate):.1f} s")
    for layer in viewer.layers:
        layer.visible = layer.name in (
            "reference",
            "εeq (uncorrected)",
            "displacement (uncorrected)",
        )
    viewer.layers.selection.active = viewer.layers["displacement (uncorrected)"]
    correlate.inspect((48.0, 48.0, 60.0))
    front(docks["Correlate"])
    shot(viewer, "correlate-vectors.png")

    correct = panels["Self-correct"]
    front(docks["Self-correct"])
    print(f"self-correct: {wait(correct):.1f} s")
    for layer in viewer.layers:
        layer.visible = layer.name in (
            "reference",
            "εeq (corrected)",
            "displacement (corrected)",
        )
    viewer.layers.selection.active = viewer.layers["εeq (corrected)"]
    shot(viewer, "self-correct.png")

    evaluate = panels["Evaluate"]
    front(docks["Evaluate"])
    print(f"evaluate: {wait(evaluate):.1f} s")
    for layer in viewer.layers:
        layer.visible = layer.name in ("reference", "phases")
    viewer.layers.selection.active = viewer.layers["phases"]
    shot(viewer, "evaluate.png")
    for layer in viewer.layers:
        layer.visible = layer.name in ("residual (uncorrected)",)
    residual = viewer.layers["residual (uncorrected)"]
    residual.colormap = "magma"
    viewer.layers.selection.active = residual
    shot(viewer, "residual-uncorrected.png")
    residual.visible = False
    viewer.layers["residual (corrected)"].visible = True
    viewer.layers["residual (corrected)"].colormap = "magma"
    viewer.layers["residual (corrected)"].contrast_limits = residual.contrast_limits
    viewer.layers.selection.active = viewer.layers["residual (corrected)"]
    shot(viewer, "residual-corrected.png")

    # 3-D view of the equivalent strain of the corrected field
    for layer in viewer.layers:
        layer.visible = layer.name in ("εeq (corrected)",)
    strain = viewer.layers["εeq (corrected)"]
    strain.rendering = "mip"
    strain.interpolation3d = "linear"
    finite = np.asarray(strain.data)[np.isfinite(strain.data)]
    strain.contrast_limits = (0.0, float(np.percentile(finite, 99)))
    viewer.layers.selection.active = strain
    viewer.dims.order = (0, 1, 2)
    viewer.dims.ndisplay = 3
    viewer.reset_view()
    camera = viewer.scene.camera if hasattr(viewer, "scene") else viewer.camera
    camera.angles = (15, -35, 130)
    shot(viewer, "strain-3d.png")
    viewer.close()


if __name__ == "__main__":
    main()
