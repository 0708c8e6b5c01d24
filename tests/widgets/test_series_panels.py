"""A scan series through every panel: Correlate → Self-correct → Evaluate, per state, 4-D layers."""

from __future__ import annotations

import numpy as np
import pytest

from napari_dvc_correct._sample_data import scan_series, true_field
from napari_dvc_correct.layers import fields_in
from napari_dvc_correct.widgets import CorrectWidget, CorrelateWidget, EvaluateWidget


@pytest.fixture(scope="module")
def series40():
    return scan_series((40, 40, 40), slips=(0.0, 1.0, 2.0))


def _dock(viewer, cls):
    widget = cls(viewer)
    viewer.window.add_dock_widget(widget)
    return widget


def test_series_through_correct_and_evaluate(series40, make_napari_viewer, run_panel):
    volumes, truths = series40
    viewer = make_napari_viewer()
    viewer.add_image(volumes, name="scan")
    correlate = _dock(viewer, CorrelateWidget)
    correlate.mode.setCurrentIndex(correlate.mode.findData("series4d"))
    correlate.reference.set_layer("scan")
    correlate.subvolume.setValue(11)
    correlate.step.setValue(8)
    run_panel(correlate)
    assert correlate.last_error is None, correlate.last_error
    assert viewer.dims.axis_labels == ("state", "z", "y", "x")

    correct = _dock(viewer, CorrectWidget)
    assert correct.field.currentText() == "series (total)"
    assert not correct.reference.isEnabled()  # the series brings its own volumes
    correct.max_passes.setValue(1)
    run_panel(correct)
    assert correct.last_error is None, correct.last_error
    layer = viewer.layers["|u| (series (total, corrected))"]
    assert layer.data.shape[0] == 3 and layer.visible
    assert not viewer.layers["|u| (series (total))"].visible
    assert correct.table.rowCount() == 2 and correct.table.item(1, 0).text() == "state 2"
    fields = fields_in(viewer.layers)
    for k in (1, 2):
        corrected = fields[f"state {k} (total, corrected)"]
        truth = true_field(truths[k], corrected.origin, corrected.step, corrected.shape)
        error = np.linalg.norm(corrected.u - truth.u, axis=-1)[corrected.valid]
        assert np.median(error) < 0.35, (k, np.median(error))
        assert corrected.metadata["deformed_layer"] == f"scan[{k}]"
    # the state slider shows state k of the field over state k of the scan
    viewer.dims.set_current_step(0, 2)
    assert viewer.dims.current_step[0] == 2

    evaluate = _dock(viewer, EvaluateWidget)
    run_panel(evaluate)
    assert evaluate.last_error is None, evaluate.last_error
    labels = [label for label, _ in evaluate.evaluations]
    assert labels == ["state 1", "state 2"]
    text = evaluate.summary.text()
    assert "state 1 (total, corrected)" in text and "state 2 (total)" in text
    for _, evaluation in evaluate.evaluations:
        assert len(evaluation.fields) == 2  # uncorrected and corrected of that state
        for item in evaluation.fields:
            assert 0.5 < item.accuracy <= 1.0 + 1e-9
