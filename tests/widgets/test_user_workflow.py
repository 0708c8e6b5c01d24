"""The plugin as a researcher uses it: own 16-bit TIFF scans in, the corrected field out.

Open two TIFF files (as File ▸ Open does), check they pair as reference/deformed in the order
opened, correlate, self-correct, evaluate with two phases, export with the panel's defaults to
NPZ and HDF5, and check that the files hold the corrected field, say so, and read with plain
numpy / h5py.
"""

from __future__ import annotations

import json

import h5py
import numpy as np
import pytest
import tifffile

from napari_dvc_correct._sample_data import soil_pair
from napari_dvc_correct.layers import fields_in
from napari_dvc_correct.viewer_layers import canvas_overlay
from napari_dvc_correct.widgets import (
    CorrectWidget,
    CorrelateWidget,
    EvaluateWidget,
    ExportWidget,
    ViewWidget,
)

SHAPE = (40, 40, 40)


@pytest.fixture
def tiff_pair(tmp_path):
    """A 16-bit CT-like pair written as two TIFF files (reference first)."""
    reference, deformed, _ = soil_pair(SHAPE, slip=2.0, compression=0.01)

    def to_uint16(volume):
        return np.clip(volume * 200.0, 0, 65535).astype(np.uint16)

    paths = tmp_path / "scan_0.tif", tmp_path / "scan_1.tif"
    for path, volume in zip(paths, (reference, deformed)):
        tifffile.imwrite(path, to_uint16(volume))
    return paths


def _dock(viewer, cls):
    """Dock a panel as napari does for a user (through the plugin, with napari's viewer proxy)."""
    name = {
        CorrelateWidget: "Correlate",
        CorrectWidget: "Self-correct",
        EvaluateWidget: "Evaluate",
        ExportWidget: "Export",
        ViewWidget: "View",
    }[cls]
    _, widget = viewer.window.add_plugin_dock_widget("napari-dvc-correct", name)
    assert isinstance(widget, cls)
    return widget


def test_tiff_pair_to_corrected_export(make_napari_viewer, tiff_pair, run_panel, tmp_path, qtbot):
    viewer = make_napari_viewer()
    correlate = _dock(viewer, CorrelateWidget)
    evaluate = _dock(viewer, EvaluateWidget)
    for path in tiff_pair:
        viewer.open(str(path), plugin="napari-dvc-correct")
    assert [layer.name for layer in viewer.layers][:2] == ["scan_0", "scan_1"]
    assert viewer.layers["scan_0"].data.dtype == np.uint16
    # paired in the order opened, in every panel that is already open
    for panel in (correlate, evaluate):
        assert (panel.reference.currentText(), panel.deformed.currentText()) == (
            "scan_0",
            "scan_1",
        )
    assert viewer.dims.axis_labels == ("z", "y", "x")

    correlate.voxel_size.setValue(2.5)
    correlate.unit.setCurrentIndex(correlate.unit.findData("µm"))
    correlate.subvolume.setValue(11)
    correlate.step.setValue(8)
    run_panel(correlate)
    assert correlate.last_error is None, correlate.last_error
    np.testing.assert_allclose(viewer.layers["scan_0"].scale, (2.5, 2.5, 2.5))
    assert canvas_overlay(viewer, "scale_bar").visible

    correct = _dock(viewer, CorrectWidget)
    assert (correct.reference.currentText(), correct.deformed.currentText()) == (
        "scan_0",
        "scan_1",
    )
    correct.max_passes.setValue(2)
    run_panel(correct)
    assert correct.last_error is None, correct.last_error
    # few layers: the two scans, and per field one quantity layer and its arrows
    plugin_layers = [x.name for x in viewer.layers if x.name not in ("scan_0", "scan_1")]
    assert len([n for n in plugin_layers if "preview" not in n]) == 4, plugin_layers
    assert not viewer.layers["|u| (uncorrected)"].visible  # toggled, not stacked
    assert viewer.layers["|u| (corrected)"].visible
    assert viewer.layers["|u| (corrected)"].colorbar.visible

    evaluate.n_phases.setValue(2)
    run_panel(evaluate)
    assert evaluate.last_error is None, evaluate.last_error
    assert "corrected" in evaluate.summary.text()

    export = _dock(viewer, ExportWidget)
    assert export.field.currentText() == "corrected"  # follows the latest result
    assert "self-corrected" in export.writes.text()
    corrected = fields_in(viewer.layers)["corrected"]
    for suffix in (".npz", ".h5"):
        export.set_format(suffix)
        path = export.path.text()
        assert path.endswith(f"dvc_corrected{suffix}")
        assert str(tmp_path) in path  # next to the scans, not the home folder
        run_panel(export)
        assert export.last_error is None, export.last_error
    npz = tmp_path / "dvc_corrected.npz"
    with np.load(npz, allow_pickle=False) as data:
        np.testing.assert_allclose(data["u"], corrected.u)
        provenance = json.loads(str(data["metadata_json"]))["provenance"]
    assert provenance["corrected"] is True and provenance["source"] == "corrected"
    assert provenance["passes_applied"] >= 1
    assert provenance["mean_gray_residual_after"] < provenance["mean_gray_residual_before"]
    assert provenance["params"]["subvolume"] == 11 and provenance["params"]["step"] == 8
    assert provenance["voxel_size"] == [2.5, 2.5, 2.5] and provenance["unit"] == "µm"
    with h5py.File(tmp_path / "dvc_corrected.h5", "r") as h5:
        np.testing.assert_allclose(h5["field/u"][()], corrected.u)
        np.testing.assert_allclose(h5["field"].attrs["voxel_size"], (2.5, 2.5, 2.5))
        metadata = json.loads(h5["field"].attrs["metadata"])
    assert metadata["provenance"]["corrected"] is True

    # the View panel switches the quantity of both fields and toggles before/after
    view = _dock(viewer, ViewWidget)
    view.set_quantity("εeq")
    qtbot.waitUntil(lambda: not view.busy, timeout=30_000)  # computed in a worker
    assert viewer.layers["εeq (corrected)"].visible
    assert "εeq" in view.caption.text() and "strain" in view.caption.text()
    assert view.before_after() == "uncorrected"
    assert viewer.layers["εeq (uncorrected)"].visible
    assert not viewer.layers["εeq (corrected)"].visible
    assert viewer.layers["εeq (uncorrected)"].colorbar.visible
    assert not viewer.layers["εeq (corrected)"].colorbar.visible
