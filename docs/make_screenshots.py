"""Regenerate the screenshots of docs/user-guide.md from real runs on the sample data.

Run under a (virtual) display, e.g. ``xvfb-run -a .venv/bin/python docs/make_screenshots.py``.
Every picture comes from the panels doing their job on the 96³ soil sample: Correlate, then
Self-correct, then Evaluate; nothing is drawn by hand.
"""

from __future__ import annotations

import os
import sys
import tempfile
import time
from pathlib import Path

# napari keeps the window's dock sizes in its settings: a fresh settings file per run, so every
# run lays the window out alike (set NAPARI_CONFIG to use another)
os.environ.setdefault("NAPARI_CONFIG", str(Path(tempfile.mkdtemp()) / "settings.yaml"))

import numpy as np  # noqa: E402
from qtpy.QtWidgets import QApplication  # noqa: E402

from napari_dvc_correct import viewer_layers as V  # noqa: E402
from napari_dvc_correct.demo import make_viewer  # noqa: E402

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


def quantity(view, key: str) -> None:
    """Switch the View panel's quantity and wait for its worker (quantities compute off the
    main thread)."""
    view.set_quantity(key)
    while view.busy:
        QApplication.processEvents()
        time.sleep(0.02)


def settle(seconds: float = 0.5) -> None:
    end = time.perf_counter() + seconds
    while time.perf_counter() < end:
        QApplication.processEvents()
        time.sleep(0.02)


def front(dock) -> None:
    dock.raise_()
    settle()


def shot(viewer, name: str) -> None:
    """Save the window; retake it while it is drawn without colour.

    Under Xvfb the whole window is now and then grabbed desaturated (every colormap gray, the
    thumbnails too) for a moment; every picture here has colour somewhere, so a gray one is
    taken again after a pause.
    """
    from imageio.v3 import imwrite

    for _ in range(10):
        settle(1.0)
        image = np.asarray(viewer.window.screenshot(canvas_only=False))[..., :3].astype(int)
        if (image.max(axis=-1) - image.min(axis=-1)).max() > 40:
            break
        print("gray grab of", name, "- taking it again")
    imwrite(IMAGES / name, image.astype(np.uint8))
    print("wrote", IMAGES / name)


def normal_size(viewer) -> None:
    """The pictures' window size (make_viewer maximises the window to the screen)."""
    window = viewer.window._qt_window
    window.showNormal()
    window.resize(*SIZE)


def show_only(viewer, names) -> None:
    for layer in viewer.layers:
        layer.visible = layer.name in names


def main() -> None:
    IMAGES.mkdir(exist_ok=True)
    viewer, panels, docks = make_viewer(show=True)
    normal_size(viewer)
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
    view = panels["View"]
    quantity(view, "εeq")
    show_only(viewer, ("reference", "εeq (uncorrected)", "displacement (uncorrected)"))
    view._decorate()
    viewer.layers.selection.active = viewer.layers["displacement (uncorrected)"]
    correlate.inspect((48.0, 48.0, 60.0))
    front(docks["Correlate"])
    shot(viewer, "correlate-vectors.png")

    # one quantity at a time: the shear component that the band carries, arrows off
    front(docks["View"])
    view.arrows.setChecked(False)
    quantity(view, "εzx")
    viewer.layers.selection.active = viewer.layers["εzx (uncorrected)"]
    shot(viewer, "view-quantity.png")

    correct = panels["Self-correct"]
    front(docks["Self-correct"])
    print(f"self-correct: {wait(correct):.1f} s")
    view.arrows.setChecked(True)
    quantity(view, "εeq")
    viewer.layers.selection.active = viewer.layers["εeq (corrected)"]
    shot(viewer, "self-correct.png")

    evaluate = panels["Evaluate"]
    front(docks["Evaluate"])
    print(f"evaluate: {wait(evaluate):.1f} s")
    phases = viewer.layers["phases"]
    hidden = [x for x in viewer.layers if x.visible and x.name not in ("reference", "phases")]
    for layer in hidden:
        layer.visible = False
    V.text_overlay(viewer).visible = False
    viewer.layers.selection.active = phases
    shot(viewer, "evaluate.png")
    # the summary's lines per field: error estimate, its resolution, likely/possibly > 0.5
    bar = evaluate.summary_box.verticalScrollBar()
    bar.setValue(bar.maximum())
    settle()
    shot(viewer, "evaluate-error-estimate.png")
    print(evaluate.summary.text())
    bar.setValue(0)
    phases.visible = False

    # the gray residual of each field, same colour range, toggled before/after
    front(docks["View"])
    view.arrows.setChecked(False)
    view.show_source("uncorrected")
    quantity(view, "residual")
    viewer.layers.selection.active = viewer.layers["residual (uncorrected)"]
    shot(viewer, "residual-uncorrected.png")
    view.before_after()
    viewer.layers.selection.active = viewer.layers["residual (corrected)"]
    shot(viewer, "residual-corrected.png")

    # the evaluation's error estimate per node (voxels), uncorrected field
    view.show_source("uncorrected")
    quantity(view, "error estimate")
    viewer.layers.selection.active = viewer.layers["error estimate (uncorrected)"]
    shot(viewer, "view-error-estimate.png")

    # 3-D view of the equivalent strain of the corrected field, from an oblique angle
    quantity(view, "εeq")
    viewer.dims.order = (0, 1, 2)
    view.oblique_3d()
    strain = next(x for x in viewer.layers if x.name == "εeq (corrected)")
    viewer.layers["reference"].visible = False
    strain.interpolation3d = "linear"
    viewer.layers.selection.active = strain
    shot(viewer, "strain-3d.png")

    viewer.dims.ndisplay = 2
    viewer.layers["reference"].visible = True
    front(docks["Export"])
    shot(viewer, "export.png")
    viewer.close()
    tiff_walkthrough()
    points_walkthrough()
    series_walkthrough()


def tiff_walkthrough() -> None:
    """A 16-bit CT pair opened from TIFF files: pairing, voxel size, a cylinder region."""
    import tempfile

    import tifffile

    from napari_dvc_correct._sample_data import soil_pair

    folder = Path(tempfile.mkdtemp(prefix="dvc-tiff-"))
    reference, deformed, _ = soil_pair((96, 96, 96))
    for name, volume in (("scan_0.tif", reference), ("scan_1.tif", deformed)):
        tifffile.imwrite(folder / name, np.clip(volume * 200, 0, 65535).astype(np.uint16))
    viewer, panels, docks = make_viewer(sample=None, show=True)
    normal_size(viewer)
    for name in ("scan_0.tif", "scan_1.tif"):
        viewer.open(str(folder / name), plugin="napari-dvc-correct")  # the reader chosen
    viewer.layers["scan_1"].visible = False
    correlate = panels["Correlate"]
    front(docks["Correlate"])
    correlate.voxel_size.setValue(12.5)
    correlate.unit.setCurrentIndex(correlate.unit.findData("µm"))
    correlate.apply_voxel_size()
    correlate.subvolume.setValue(21)
    correlate.region.set_kind("cylinder")
    correlate.region.radius.setValue(40.0)  # (defaults follow the scans: centred, full z)
    correlate._update.flush()
    viewer.reset_view()
    shot(viewer, "tiff-pair.png")
    viewer.close()


def points_walkthrough() -> None:
    """Points of interest clicked on the scan (a Points layer), correlated at exactly those points.

    40 points scattered over the middle z-x plane of the 96³ soil sample, across the shear band;
    the result shows as points coloured by the displacement along x, with their arrows.
    """
    viewer, panels, docks = make_viewer(show=True)
    normal_size(viewer)
    settle(1.0)
    correlate = panels["Correlate"]
    front(docks["Correlate"])
    viewer.dims.order = (1, 0, 2)  # the z-x plane, where the band slips
    rng = np.random.default_rng(4)
    points = np.column_stack(
        [rng.uniform(18, 78, 40), np.full(40, 48.0), rng.uniform(18, 78, 40)]
    ).round()
    scan = viewer.layers["reference"]
    world = points * np.asarray(scan.scale) + np.asarray(scan.translate)
    viewer.add_points(world, name="my points", size=3, face_color="yellow")
    correlate.placement.setCurrentIndex(correlate.placement.findData("points"))
    correlate.subvolume.setValue(31)
    correlate.step.setValue(8)
    correlate._update.flush()
    viewer.dims.set_point(1, float(world[0, 1]))
    print(f"correlate at points: {wait(correlate):.1f} s")
    view = panels["View"]
    quantity(view, "ux")
    viewer.layers["my points"].visible = False
    viewer.layers.selection.active = viewer.layers["ux (points)"]
    front(docks["Correlate"])
    shot(viewer, "correlate-points.png")
    viewer.close()


def series_walkthrough() -> None:
    """A scan series (four states of the soil sample under growing shear, one 4-D layer):
    Correlate (total), one self-correcting pass, Evaluate; the series plot against the slip
    typed as the load of each state."""
    from napari_dvc_correct._sample_data import scan_series

    slips = (0.0, 1.5, 3.0, 4.5)
    volumes, _ = scan_series((64, 64, 64), slips=slips)
    viewer, panels, docks = make_viewer(sample=None, show=True)
    normal_size(viewer)
    viewer.add_image(volumes, name="scan")
    correlate = panels["Correlate"]
    front(docks["Correlate"])
    correlate.mode.setCurrentIndex(correlate.mode.findData("series4d"))
    correlate.reference.set_layer("scan")
    correlate.subvolume.setValue(21)
    correlate.step.setValue(6)
    print(f"correlate series: {wait(correlate):.1f} s")
    correct = panels["Self-correct"]
    front(docks["Self-correct"])
    correct.max_passes.setValue(1)
    print(f"self-correct series: {wait(correct):.1f} s")
    evaluate = panels["Evaluate"]
    front(docks["Evaluate"])
    print(f"evaluate series: {wait(evaluate):.1f} s")
    evaluate.loads.setText(", ".join(f"{s:g}" for s in slips[1:]))
    evaluate.plot_series()
    viewer.dims.set_current_step(0, len(slips) - 1)
    shot(viewer, "evaluate-series.png")
    viewer.close()


if __name__ == "__main__":
    parts = {
        "all": main,
        "tiff": tiff_walkthrough,
        "points": points_walkthrough,
        "series": series_walkthrough,
    }
    parts[sys.argv[1] if len(sys.argv) > 1 else "all"]()
