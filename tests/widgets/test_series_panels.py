"""A scan series through every panel: Correlate → Self-correct → Evaluate, per state, 4-D layers."""

from __future__ import annotations

import numpy as np
import pytest
from qtpy.QtCore import Qt

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


def _correlate(viewer, volumes, run_panel):
    """The series as a 4-D layer "scan", correlated (total strategy) by a docked panel."""
    viewer.add_image(volumes, name="scan")
    correlate = _dock(viewer, CorrelateWidget)
    correlate.mode.setCurrentIndex(correlate.mode.findData("series4d"))
    correlate.reference.set_layer("scan")
    correlate.subvolume.setValue(11)
    correlate.step.setValue(8)
    run_panel(correlate)
    return correlate


def test_series_through_correct_and_evaluate(series40, make_napari_viewer, run_panel):
    volumes, truths = series40
    viewer = make_napari_viewer()
    correlate = _correlate(viewer, volumes, run_panel)
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


def test_a_corrected_series_shows_its_strain_computed_in_the_worker(
    series40, make_napari_viewer, run_panel, qtbot, strain_calls
):
    """Self-correcting a series makes its 4-D fields (state 0 first) in the worker, where the
    strain on view is computed for every state: the slot computes no strain tensor."""
    from napari_dvc_correct import layers as L
    from napari_dvc_correct.quantities import quantity_values
    from napari_dvc_correct.widgets import ViewWidget

    volumes, _ = series40
    viewer = make_napari_viewer()
    correlate = _correlate(viewer, volumes, run_panel)
    assert correlate.last_error is None, correlate.last_error
    view = _dock(viewer, ViewWidget)
    view.set_quantity("εvol")
    qtbot.waitUntil(lambda: not view.busy, timeout=30_000)
    correct = _dock(viewer, CorrectWidget)
    correct.max_passes.setValue(1)
    strain_calls.clear()
    run_panel(correct)
    assert correct.last_error is None, correct.last_error
    calls = list(strain_calls)
    assert len(calls) == 3 and not any(calls), calls  # states 0, 1, 2, none on the main thread
    layer = viewer.layers["εvol (series (total, corrected))"]
    states = L.series_of(layer)
    assert layer.visible and len(states) == 3 and not states[0].u.any()
    expected = np.stack([quantity_values(f.copy(), "εvol") for f in states])
    np.testing.assert_array_equal(layer.data, expected)
    assert correct.table.rowCount() == 2


def test_a_lazy_series_runs_out_of_core_as_in_memory(series40, make_napari_viewer, run_panel):
    """A Dask-backed 4-D series with 'out of core' ticked: every state read batch by batch
    (tiled.series), the same totals as the in-memory series."""
    import dask.array as da

    from napari_dvc_correct.engine.correlation.params import CorrelationParams
    from napari_dvc_correct.engine.series.strategies import series

    volumes, _ = series40
    viewer = make_napari_viewer()
    viewer.add_image(da.from_array(np.asarray(volumes), chunks=(1, 20, 40, 40)), name="scan")
    correlate = _dock(viewer, CorrelateWidget)
    correlate.mode.setCurrentIndex(correlate.mode.findData("series4d"))
    correlate.reference.set_layer("scan")
    correlate.subvolume.setValue(11)
    correlate.step.setValue(8)
    correlate.tiled.setChecked(True)
    job = correlate.job()
    assert job.tiled and job.strategy != "pair"
    run_panel(correlate)
    assert correlate.last_error is None, correlate.last_error
    fields = fields_in(viewer.layers)
    params = CorrelationParams(subvolume=11, step=8)
    expected = series(list(volumes), params, strategy=job.strategy)
    for k, total in enumerate(expected.totals, start=1):
        field = fields[f"state {k} ({job.strategy})"]
        np.testing.assert_array_equal(field.status, total.status)
        good = total.valid
        assert np.max(np.abs(field.u[good] - total.u[good])) < 1e-4
    # the Self-correct panel corrects every state out of core too (ticked by itself)
    from napari_dvc_correct.engine.correction.self_correction import correct

    correct_panel = _dock(viewer, CorrectWidget)
    assert correct_panel.field.currentText() == f"series ({job.strategy})"
    assert correct_panel.tiled.isChecked()
    correct_panel.max_passes.setValue(1)
    run_panel(correct_panel)
    assert correct_panel.last_error is None, correct_panel.last_error
    fields = fields_in(viewer.layers)
    for k in (1, 2):
        source = fields[f"state {k} ({job.strategy})"]
        expected = correct(volumes[0], volumes[k], source, max_passes=1)
        corrected = fields[f"state {k} ({job.strategy}, corrected)"]
        assert corrected.metadata["tiled"]
        np.testing.assert_array_equal(corrected.status, expected.status)
        good = expected.valid
        assert np.max(np.abs(corrected.u[good] - expected.u[good])) < 1e-4
    # and the Evaluate panel evaluates every state out of core: the in-memory numbers
    evaluate = _dock(viewer, EvaluateWidget)
    results = {}
    for tiled in (False, True):
        evaluate.tiled.setChecked(tiled)
        run_panel(evaluate)
        assert evaluate.last_error is None, evaluate.last_error
        results[tiled] = {
            (label, item.name): (item.accuracy, item.mean_residual)
            for label, evaluation in evaluate.evaluations
            for item in evaluation.fields
        }
        kept = [item.residual is not None for _, e in evaluate.evaluations for item in e.fields]
        assert not any(kept) if tiled else all(kept)  # out of core: the numbers only
    assert len(results[True]) == 4 and results[True].keys() == results[False].keys()
    for key, (accuracy, residual) in results[True].items():
        assert accuracy == pytest.approx(results[False][key][0], abs=1e-5)
        assert residual == pytest.approx(results[False][key][1], rel=1e-5)


def test_a_series_as_separate_layers_is_evaluated_state_by_state(
    series40, make_napari_viewer, run_panel
):
    """Three states opened as three layers, a field per state: each state against its own pair,
    and a field's r0 and p the same whether it is ticked alone or with the others (issue 26)."""
    from napari_dvc_correct import layers as L
    from napari_dvc_correct import viewer_layers as V
    from napari_dvc_correct.engine.evaluation.accuracy import evaluate_fields
    from napari_dvc_correct.engine.fields.field import grid_for_volume

    volumes, truths = series40
    viewer = make_napari_viewer()
    for k in range(3):
        viewer.add_image(volumes[k], name=f"scan{k}")
    origin, step, shape = grid_for_volume(volumes[0].shape, 11, 8)
    fields = {}
    for k in (1, 2):
        field = true_field(truths[k], origin, step, shape)
        field.metadata.update(reference_layer="scan0", deformed_layer=f"scan{k}")
        fields[f"state {k}"] = field
        V.show_layers(viewer, L.field_layers(field, f"state {k}"))
    evaluate = _dock(viewer, EvaluateWidget)
    evaluate.reference.set_layer("scan0")
    evaluate.deformed.set_layer("scan1")
    run_panel(evaluate)
    assert evaluate.last_error is None, evaluate.last_error
    labels = [label for label, _ in evaluate.evaluations]
    # state 1 is the panel's pair (named too: its block was headed "—  —"), state 2 its own
    assert labels == ["scan0 → scan1", "scan0 → scan2"]
    thresholds = evaluate.thresholds()
    for (_, evaluation), k in zip(evaluate.evaluations, (1, 2)):
        alone = evaluate_fields(
            volumes[0], volumes[k], {f"state {k}": fields[f"state {k}"]}, phases=thresholds
        )
        item = evaluation[f"state {k}"]
        # its own pair: the exact field explains it down to the noise
        assert item.mean_residual == pytest.approx(alone[f"state {k}"].mean_residual, rel=1e-6)
        assert item.accuracy == pytest.approx(alone[f"state {k}"].accuracy, abs=1e-9)
    # ticked alone: the same r0 and p as ticked with the other
    first = evaluate.evaluations[1][1]["state 2"]
    evaluate.fields.item(0).setCheckState(Qt.CheckState.Unchecked)
    run_panel(evaluate)
    assert [label for label, _ in evaluate.evaluations] == [""]
    again = evaluate.evaluation["state 2"]
    assert again.background_used == pytest.approx(first.background_used, rel=1e-9)
    assert again.accuracy == pytest.approx(first.accuracy, abs=1e-12)


def test_series_plots_against_the_load_state(series40, make_napari_viewer, run_panel):
    """Three states as three layers: the Evaluate panel plots each state's mean residual, p and
    error estimate, every state ticked (by its volume), then at the loads the user types."""
    from napari_dvc_correct import layers as L
    from napari_dvc_correct import viewer_layers as V
    from napari_dvc_correct.engine.fields.field import grid_for_volume

    volumes, truths = series40
    viewer = make_napari_viewer()
    for k in range(3):
        viewer.add_image(volumes[k], name=f"scan{k}")
    origin, step, shape = grid_for_volume(volumes[0].shape, 11, 8)
    for k in (1, 2):
        field = true_field(truths[k], origin, step, shape)
        field.metadata.update(reference_layer="scan0", deformed_layer=f"scan{k}")
        V.show_layers(viewer, L.field_layers(field, f"state {k}"))
    evaluate = _dock(viewer, EvaluateWidget)
    evaluate.reference.set_layer("scan0")
    evaluate.deformed.set_layer("scan1")
    assert not evaluate.series_plot.isVisibleTo(evaluate)  # a series shows it, a pair not
    run_panel(evaluate)
    assert evaluate.last_error is None, evaluate.last_error
    assert evaluate.series_plot.isVisibleTo(evaluate) and evaluate.loads.isVisibleTo(evaluate)
    items = [evaluation["state 1" if k == 0 else "state 2"] for k, (_, evaluation) in
             enumerate(evaluate.evaluations)]  # fmt: skip
    expected = {
        0: [item.mean_residual for item in items],
        1: [item.accuracy for item in items],
        2: [item.error["median"] for item in items],
    }
    for index, axes in enumerate(evaluate.series_plot.axes):
        assert [t.get_text() for t in axes.get_xticklabels()] == ["scan1", "scan2"]
        (line,) = [line for line in axes.get_lines() if line.get_label() == "field"]
        np.testing.assert_allclose(line.get_xdata(), [1, 2])
        np.testing.assert_allclose(line.get_ydata(), expected[index])
    # exact fields: a good p and a small error at both states
    assert all(p > 0.85 for p in expected[1]) and all(e < 0.3 for e in expected[2])
    # the user's load values move the states along x, still ticked
    evaluate.loads.setText("0.5, 2")
    evaluate.loads.editingFinished.emit()
    axes = evaluate.series_plot.axes[1]
    np.testing.assert_allclose(axes.get_xticks(), [0.5, 2.0])
    assert axes.get_xlabel() == "load"
    np.testing.assert_allclose(axes.get_lines()[0].get_xdata(), [0.5, 2.0])
    # a session keeps the load values
    settings = evaluate.settings()
    evaluate.loads.clear()
    evaluate.restore(settings)
    assert settings["loads"] == "0.5, 2" and evaluate.loads.text() == "0.5, 2"
    # a wrong count is said in one line, the plot kept
    evaluate.loads.setText("1")
    evaluate.loads.editingFinished.emit()
    assert "one load value per deformed state" in evaluate.message.text()
    np.testing.assert_allclose(axes.get_xticks(), [0.5, 2.0])
