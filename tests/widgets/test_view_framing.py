"""The view follows a change of placement: after a voxel size is typed or a session reopened,
the camera frames the scans and the slice on view stays (item 2 of issue 28)."""

from __future__ import annotations

import numpy as np
import tifffile
from qtpy.QtWidgets import QApplication

from napari_dvc_correct.widgets import CorrelateWidget

SHAPE = (40, 60, 80)


def _scan(seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).random(SHAPE, dtype=np.float32)


def assert_frames_the_scans(viewer) -> None:
    """The displayed world extent of the layers fills the canvas, centred (not a thumbnail)."""
    extent = np.asarray(viewer.layers.extent.world)[:, -2:]
    size = extent[1] - extent[0]
    middle = extent.mean(axis=0)
    center = np.asarray(viewer.scene.camera.center)[-2:]
    np.testing.assert_allclose(center, middle, atol=0.1 * size.max())
    canvas = np.asarray(viewer.canvas.size, float)
    drawn = size * viewer.scene.camera.zoom  # screen pixels the scans take
    assert np.all(drawn <= canvas * 1.01) and np.any(drawn >= 0.8 * canvas), (drawn, canvas)


def test_typing_a_voxel_size_keeps_the_scan_framed(make_napari_viewer):
    viewer = make_napari_viewer(show=True)
    viewer.add_image(_scan(), name="reference")
    viewer.add_image(_scan(1), name="deformed")
    widget = CorrelateWidget(viewer)
    viewer.window.add_dock_widget(widget)
    viewer.dims.set_current_step(0, 12)
    assert_frames_the_scans(viewer)
    widget.voxel_size.setValue(0.05)  # typed (mm), then Enter
    widget.voxel_size.editingFinished.emit()
    np.testing.assert_allclose(viewer.layers["reference"].scale, (0.05, 0.05, 0.05))
    assert viewer.dims.current_step[0] == 12  # the same slice, not the last one
    assert_frames_the_scans(viewer)


def test_reopening_a_session_frames_its_scans(make_napari_viewer, tmp_path):
    for k in range(2):
        tifffile.imwrite(tmp_path / f"scan_{k}.tif", _scan(k))
    viewer = make_napari_viewer(show=True)
    for k in range(2):
        viewer.open(str(tmp_path / f"scan_{k}.tif"), plugin="napari-dvc-correct")
    _, correlate = viewer.window.add_plugin_dock_widget("napari-dvc-correct", "Correlate")
    _, export = viewer.window.add_plugin_dock_widget("napari-dvc-correct", "Export")
    correlate.voxel_size.setValue(0.05)
    correlate.voxel_size.editingFinished.emit()
    assert export.session(tmp_path / "run") is not None, export.message.text()
    viewer.close()

    viewer = make_napari_viewer(show=True)
    viewer.add_image(np.zeros((500, 500), np.float32), name="something else")  # a large view
    _, export = viewer.window.add_plugin_dock_widget("napari-dvc-correct", "Export")
    _, correlate = viewer.window.add_plugin_dock_widget("napari-dvc-correct", "Correlate")
    viewer.layers.remove("something else")
    QApplication.processEvents()  # the docks laid out: the canvas has its size
    assert export.session(tmp_path / "run.dvc-session.json", save=False) is not None
    np.testing.assert_allclose(viewer.layers["scan_0"].scale, (0.05, 0.05, 0.05))
    assert_frames_the_scans(viewer)


def test_units_agree_after_a_unit_is_chosen_and_in_series_mode(make_napari_viewer):
    """napari warns "Inconsistent units across layers" on every draw where they disagree: a
    unit chosen in the pair mode reaches the other scans (a series' states) and later layers."""
    viewer = make_napari_viewer()
    for k in range(3):
        viewer.add_image(_scan(k)[:32, :32, :32], name=f"state{k}")
    widget = CorrelateWidget(viewer)
    viewer.window.add_dock_widget(widget)
    widget.unit.setCurrentIndex(widget.unit.findData("mm"))
    widget._update.flush()
    assert viewer.layers.extent.units is not None  # napari's test before its warning
    widget.mode.setCurrentIndex(widget.mode.findData("series"))
    widget._update.flush()
    assert viewer.layers.extent.units is not None
    viewer.add_image(_scan(4)[:32, :32, :32], name="state3")  # opened later
    assert viewer.layers.extent.units is not None
    assert str(viewer.layers["state3"].units[0]) == "millimeter"
