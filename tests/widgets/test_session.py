"""Sessions: save → close → reopen gives back the scans, the panels' settings and the fields."""

from __future__ import annotations

import numpy as np
import pytest
import tifffile

from napari_dvc_correct._sample_data import soil_pair
from napari_dvc_correct.layers import fields_in, plugin_metadata, quantity_layers, show_quantity
from napari_dvc_correct.widgets import CorrectWidget, CorrelateWidget, EvaluateWidget, ExportWidget


def _panels(viewer):
    panels = {}
    for name in ("Correlate", "Self-correct", "Evaluate", "Export"):
        _, panels[name] = viewer.window.add_plugin_dock_widget("napari-dvc-correct", name)
    return panels


def test_save_close_reopen(make_napari_viewer, run_panel, tmp_path, qtbot):
    reference, deformed, _ = soil_pair((40, 40, 40), slip=2.0)
    for name, volume in (("scan_0", reference), ("scan_1", deformed)):
        tifffile.imwrite(tmp_path / f"{name}.tif", volume.astype(np.float32))
    viewer = make_napari_viewer()
    panels = _panels(viewer)
    for name in ("scan_0", "scan_1"):
        viewer.open(str(tmp_path / f"{name}.tif"), plugin="napari-dvc-correct")
    correlate = panels["Correlate"]
    assert isinstance(correlate, CorrelateWidget)
    correlate.voxel_size.setValue(2.0)
    correlate.subvolume.setValue(11)
    correlate.step.setValue(8)
    correlate.region.set_kind("cylinder")
    correlate.region.radius.setValue(17.0)
    run_panel(correlate)
    assert correlate.last_error is None, correlate.last_error
    panels["Self-correct"].max_passes.setValue(2)
    evaluate = panels["Evaluate"]
    assert isinstance(evaluate, EvaluateWidget)
    evaluate.set_thresholds([float(np.median(reference))])
    thresholds = evaluate.thresholds()
    run_panel(evaluate)
    assert evaluate.last_error is None, evaluate.last_error
    summary = evaluate.summary.text()
    field = fields_in(viewer.layers)["uncorrected"]
    # the view: a quantity other than |u|, a slice, a camera
    show_quantity(next(x for x in quantity_layers(viewer) if x.visible), "uz")
    viewer.dims.set_current_step(0, 7)
    camera = viewer.scene.camera
    camera.zoom *= 1.7
    view = (tuple(viewer.dims.current_step), camera.zoom, tuple(camera.center))
    export = panels["Export"]
    assert isinstance(export, ExportWidget)
    written = export.session(tmp_path / "run")
    assert export.last_error is None, export.last_error
    assert written.name == "run.dvc-session.json" and written.is_file()
    assert (tmp_path / "run_fields" / "uncorrected.dvcfield").is_file()
    viewer.close()

    viewer = make_napari_viewer()
    panels = _panels(viewer)
    content = panels["Export"].session(tmp_path / "run.dvc-session.json", save=False)
    assert content is not None, panels["Export"].message.text()
    # the evaluation comes back (Evaluate runs again in its worker)
    worker = panels["Evaluate"].worker
    assert worker is not None
    with qtbot.waitSignal(worker.finished, timeout=300_000):
        pass
    assert panels["Evaluate"].last_error is None, panels["Evaluate"].last_error
    assert "residual volume (uncorrected)" in viewer.layers
    assert panels["Evaluate"].summary.text() == summary
    # the view comes back: the quantity, the slice, the camera; no preview over the fields
    shown = [x for x in quantity_layers(viewer) if x.visible]
    assert [plugin_metadata(x)["quantity"] for x in shown] == ["uz"]
    camera = viewer.scene.camera
    assert tuple(viewer.dims.current_step) == view[0]
    np.testing.assert_allclose(camera.zoom, view[1])
    np.testing.assert_allclose(camera.center, view[2])
    previews = [x for x in viewer.layers if (plugin_metadata(x) or {}).get("kind") == "preview"]
    assert not any(x.visible for x in previews)
    assert viewer.layers.extent.units is not None  # napari's "Inconsistent units" test
    assert [x.name for x in viewer.layers][:2] == ["scan_0", "scan_1"]
    np.testing.assert_allclose(viewer.layers["scan_0"].scale, (2.0, 2.0, 2.0))
    reopened = fields_in(viewer.layers)["uncorrected"]
    np.testing.assert_allclose(reopened.u, field.u)
    correlate = panels["Correlate"]
    assert (correlate.subvolume.value(), correlate.step.value()) == (11, 8)
    assert correlate.region.current_kind == "cylinder" and correlate.region.radius.value() == 17.0
    assert (correlate.reference.currentText(), correlate.deformed.currentText()) == (
        "scan_0",
        "scan_1",
    )
    assert isinstance(panels["Self-correct"], CorrectWidget)
    assert panels["Self-correct"].max_passes.value() == 2
    np.testing.assert_allclose(panels["Evaluate"].thresholds(), thresholds)


def test_a_scan_that_is_not_a_file_is_refused(make_napari_viewer, tmp_path):
    viewer = make_napari_viewer()
    viewer.add_image(np.zeros((8, 8, 8), np.float32), name="made in memory")
    export = _panels(viewer)["Export"]
    assert export.session(tmp_path / "s") is None
    assert "not opened from a file" in export.message.text()
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("content", ["{}", "not json"])
def test_not_a_session_is_refused(make_napari_viewer, tmp_path, content):
    path = tmp_path / "x.dvc-session.json"
    path.write_text(content)
    export = _panels(make_napari_viewer())["Export"]
    assert export.session(path, save=False) is None
    assert "session file" in export.message.text()


def test_a_hand_edited_session_is_one_line_in_the_panel(make_napari_viewer, tmp_path):
    """Issue 27 item 8: settings a panel cannot take, a newer version, a field outside the
    folder: a message in the Export panel, never an exception on the main thread."""
    from napari_dvc_correct.widgets.session_model import FORMAT

    tifffile.imwrite(tmp_path / "ref.tif", np.zeros((8, 8, 8), np.float32))
    scan = {"name": "ref", "path": str(tmp_path / "ref.tif"), "scale": [1.0, 1.0, 1.0],
            "translate": [0.0, 0.0, 0.0]}  # fmt: skip
    export = _panels(make_napari_viewer())["Export"]
    cases = [
        ({"panels": {"Correlate": {"subvolume": [1, 2]}}}, "int()"),  # a TypeError in restore
        ({"version": 999}, "newer"),
        ({"fields": {"a": "../a.npz"}}, "outside the session"),
    ]
    for changes, message in cases:
        content = {"format": FORMAT, "version": 1, "scans": [scan], "panels": {}, "fields": {}}
        content.update(changes)
        path = tmp_path / "s.dvc-session.json"
        path.write_text(__import__("json").dumps(content))
        assert export.session(path, save=False) is None
        assert message in export.message.text()


# --- what a session records of the viewer -----------------------------------------------------------
def test_the_scans_are_the_user_s_images_with_their_placement():
    from napari.components import ViewerModel

    from napari_dvc_correct.layers import MARKER
    from napari_dvc_correct.widgets import session

    viewer = ViewerModel()
    viewer.add_image(np.zeros((4, 5, 6)), name="G", scale=(2, 2, 2), translate=(1, 0, 0))
    viewer.add_image(np.zeros((4, 5, 6)), name="|u| (f)", metadata={MARKER: {"kind": "quantity"}})
    (entry,) = session.scan_entries(viewer)
    assert entry["name"] == "G" and entry["path"] is None  # made in memory, not opened
    assert entry["scale"] == [2.0, 2.0, 2.0] and entry["translate"] == [1.0, 0.0, 0.0]
    assert session.session_fields(viewer) == {}


def test_the_view_comes_back_as_it_was_saved(make_napari_viewer):
    from napari_dvc_correct.widgets import session

    viewer = make_napari_viewer()
    viewer.add_image(np.random.default_rng(0).random((20, 30, 40)), name="G")
    viewer.dims.ndisplay = 3
    viewer.dims.set_current_step(0, 7)
    camera = viewer.scene.camera if hasattr(viewer, "scene") else viewer.camera
    camera.angles = (10.0, 20.0, 30.0)
    camera.zoom = 2.5
    saved = session.view_state(viewer)
    assert saved["ndisplay"] == 3 and saved["current_step"][0] == 7
    assert saved["source"] is None  # no field on view
    viewer.dims.ndisplay = 2
    viewer.dims.set_current_step(0, 0)
    camera.angles = (0.0, 0.0, 90.0)
    camera.zoom = 1.0
    session.restore_view(viewer, saved)
    assert viewer.dims.ndisplay == 3 and viewer.dims.current_step[0] == 7
    np.testing.assert_allclose(camera.angles, (10.0, 20.0, 30.0), atol=1e-6)
    assert camera.zoom == pytest.approx(2.5)  # the same canvas: the same zoom
    session.restore_view(viewer, {})  # nothing saved: nothing changes
    assert viewer.dims.ndisplay == 3
