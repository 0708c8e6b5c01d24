"""The Evaluate dock: histogram and thresholds, live phases, residual layers, plots, messages."""

from __future__ import annotations

import numpy as np
import pytest

from napari_dvc_correct.layers import plugin_metadata
from napari_dvc_correct.widgets.evaluate import EvaluateWidget


def _dock(viewer):
    widget = EvaluateWidget(viewer)
    viewer.window.add_dock_widget(widget)
    return widget


def test_thresholds_split_the_histogram_and_update_the_phases_live(viewer_pair, qtbot, small):
    widget = _dock(viewer_pair)
    reference = viewer_pair.layers["reference"].data
    # automatic thresholds: one between the two phase grays (100 and 170)
    (threshold,) = widget.thresholds()
    assert 110 < threshold < 160
    assert len(widget.histogram.lines) == 1
    assert widget.histogram.lines[0].get_xdata()[0] == pytest.approx(threshold)
    widget._live.flush()
    qtbot.waitUntil(lambda: not widget.phases_busy, timeout=10_000)  # computed in a worker
    assert "phase 1: mean gray" in widget.phase_label.text()
    assert "phases" not in viewer_pair.layers  # not before the user touches the thresholds
    widget.auto_button.click()
    widget._live.flush()
    qtbot.waitUntil(lambda: not widget.phases_busy, timeout=10_000)
    phases = viewer_pair.layers["phases"]
    np.testing.assert_allclose(phases.scale, small.voxel_size)
    np.testing.assert_allclose(phases.translate, small.offset)
    np.testing.assert_array_equal(phases.data, np.where(reference >= threshold, 2, 1))
    assert "phase 1: mean gray" in widget.phase_label.text()
    # moving the slider updates the label volume after the debounce delay, not at once
    before = phases.data.copy()
    widget.set_thresholds([150.0])
    assert np.array_equal(phases.data, before)
    qtbot.waitUntil(lambda: not np.array_equal(phases.data, before), timeout=3000)
    np.testing.assert_array_equal(phases.data, np.where(reference >= 150.0, 2, 1))
    # more phases on demand: two thresholds, three labels
    widget.n_phases.setValue(3)
    assert len(widget.thresholds()) == 3 - 1
    widget._live.flush()
    qtbot.waitUntil(lambda: not widget.phases_busy, timeout=10_000)
    assert set(np.unique(viewer_pair.layers["phases"].data)) == {1, 2, 3}


def test_the_latest_thresholds_win(viewer_pair, qtbot):
    """Phase labels of the whole volume come from a worker; a quick second choice supersedes
    the first, and the layer shows the labels of the last one."""
    widget = _dock(viewer_pair)
    reference = viewer_pair.layers["reference"].data
    widget.set_thresholds([120.0])
    first = widget.update_phases()
    widget.set_thresholds([150.0])
    second = widget.update_phases()
    assert first is not None and second is not None and first is not second
    qtbot.waitUntil(lambda: not widget.phases_busy, timeout=10_000)
    qtbot.waitUntil(lambda: not first.is_running, timeout=10_000)
    # and the debounced call the slider triggered
    qtbot.waitUntil(lambda: not widget._live.timer.isActive(), timeout=3000)
    qtbot.waitUntil(lambda: not widget.phases_busy, timeout=10_000)
    np.testing.assert_array_equal(
        viewer_pair.layers["phases"].data, np.where(reference >= 150.0, 2, 1)
    )
    widget.set_thresholds([150.0, 140.0], show=False)  # not increasing: said, nothing computed
    widget._live.flush()
    assert widget.update_phases() is None
    assert "strictly increasing" in widget.phase_label.text()


def test_evaluate_adds_residual_layers_and_plots(correlated, run_panel, small):
    viewer = correlated.viewer
    widget = _dock(viewer)
    assert widget.checked_fields() == ["uncorrected"]
    run_panel(widget)
    assert widget.last_error is None, widget.last_error
    residual = viewer.layers["residual volume (uncorrected)"]
    assert residual.data.shape == small.shape
    np.testing.assert_allclose(residual.scale, small.voxel_size)
    np.testing.assert_allclose(residual.translate, small.offset)
    report = plugin_metadata(residual)["report"]
    item = report["field: uncorrected"]
    # residual above the noise floor, accuracy index in a sensible range for a good field
    assert 0 < item["background residual r0"] <= item["mean gray residual"] + 1e-9
    assert 0.9 < item["accuracy index p"] <= 1.0 + 1e-9
    assert "accuracy index p" in widget.summary.text()
    # one stated residual, the pair's r0, the error estimate, left on the field for View
    text = widget.summary.text()
    assert "reference frame" in text and "error estimate median" in text and "r0 =" in text
    assert item["error estimate median (voxels)"] < 0.5
    from napari_dvc_correct.layers import fields_in
    from napari_dvc_correct.quantities import available_quantities

    assert "error estimate" in available_quantities(fields_in(viewer.layers)["uncorrected"])
    residual_axes, accuracy_axes = widget.curves.axes
    assert len(residual_axes.lines) == 1 and len(accuracy_axes.lines) == 1
    np.testing.assert_allclose(
        accuracy_axes.lines[0].get_ydata(), item["accuracy per strain bin"], equal_nan=True
    )


def test_residual_layers_are_made_in_the_worker(correlated, qtbot):
    """The result slot only adds layers: the residual's contrast range (a percentile of the
    whole volume) and the report are computed in the worker (issue 28, item 3)."""
    from napari_dvc_correct.widgets.evaluate_model import ShownEvaluation

    widget = _dock(correlated.viewer)
    worker = widget.run(start=False)
    results = []
    worker.returned.connect(results.append)
    with qtbot.waitSignal(worker.finished, timeout=300_000):
        worker.start()
    (result,) = results
    assert isinstance(result, ShownEvaluation)
    ((data, kwargs, kind),) = result.layers
    assert kind == "image" and kwargs["contrast_limits"][1] > 0
    assert "report" in kwargs["metadata"]["dvc_correct"]
    assert "residual volume (uncorrected)" in correlated.viewer.layers


def test_same_layer_twice_a_message(correlated):
    from napari_dvc_correct.layers import fields_in

    # a field whose own volumes are open is evaluated on them whatever the panel's pair (a
    # series opened as separate layers, issue 26); without them, the panel's pair is checked
    for field in fields_in(correlated.viewer.layers).values():
        field.metadata.pop("deformed_layer", None)
    widget = _dock(correlated.viewer)
    widget.deformed.set_layer("reference")
    assert widget.run() is None
    assert "same layer" in widget.message.text()


def test_without_a_field_a_message(viewer_pair):
    widget = _dock(viewer_pair)
    assert widget.run() is None
    assert "run Correlate" in widget.message.text()


def test_2d_reference_a_message(make_napari_viewer):
    viewer = make_napari_viewer()
    viewer.add_image(np.random.default_rng(0).random((32, 32)), name="slice")
    widget = _dock(viewer)
    assert widget.run() is None
    assert "not a 3-D volume" in widget.message.text()


def test_a_specimen_region_limits_the_evaluation(correlated, run_panel, small):
    """The Correlate panel's regions in Evaluate (issue 26): a box, and only its voxels phase."""
    viewer = correlated.viewer
    widget = _dock(viewer)
    widget.region.set_kind("box")
    nz, ny, nx = small.shape
    widget.region.z_from.setValue(2)
    widget.region.z_to.setValue(nz - 2)
    widget.region.y_from.setValue(3)
    widget.region.y_to.setValue(ny - 3)
    run_panel(widget)
    assert widget.last_error is None, widget.last_error
    voxels = sum(s.voxels for s in widget.evaluation.phases_reference)
    assert voxels == (nz - 4) * (ny - 6) * nx
    assert widget.settings()["region"]["kind"] == "box"


def test_every_pair_of_a_series_of_layers_is_named_in_the_summary(make_napari_viewer):
    # states c0 → c1 ... c0 → c3 as separate layers, the panel's pair c0 → c3: the third block
    # of the summary was headed "—  —" (the panel's own pair had no label)
    from napari_dvc_correct.engine.fields.field import DisplacementField

    viewer = make_napari_viewer()
    for k in range(4):
        viewer.add_image(np.zeros((12, 12, 12), np.float32) + k, name=f"c{k}")
    widget = _dock(viewer)
    widget.reference.set_layer("c0")
    widget.deformed.set_layer("c3")
    chosen = {}
    for k in (1, 2, 3):
        field = DisplacementField.zeros((4.0, 4.0, 4.0), (4.0, 4.0, 4.0), (2, 2, 2))
        field.metadata.update(reference_layer="c0", deformed_layer=f"c{k}")
        chosen[f"state {k}"] = field
    labels = [group[0] for group in widget._groups(chosen)]
    assert labels == ["c0 → c1", "c0 → c2", "c0 → c3"]
