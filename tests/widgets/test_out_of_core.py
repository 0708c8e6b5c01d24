"""Out-of-core runs from the panels: Dask-backed scans tick 'out of core' by themselves, and
the tiled Correlate and Self-correct runs give the in-memory results."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from napari_dvc_correct import layers as L
from napari_dvc_correct.widgets import CorrelateWidget


def test_a_lazy_pair_runs_out_of_core_and_gives_the_in_memory_field(
    make_napari_viewer, pair48, run_panel, small
):
    """Dask-backed scans tick 'out of core' by themselves; the tiled run's field is the
    in-memory one (the tiled engine's promise, ~1e-7 voxel)."""
    import dask.array as da

    from napari_dvc_correct.engine.correlation.correlate import correlate
    from napari_dvc_correct.engine.correlation.params import CorrelationParams

    reference, deformed, _ = pair48
    viewer = make_napari_viewer()
    for name, data in (("reference", reference), ("deformed", deformed)):
        viewer.add_image(da.from_array(data, chunks=24), name=name, scale=small.voxel_size)
    widget = CorrelateWidget(viewer)
    viewer.window.add_dock_widget(widget)
    widget.subvolume.setValue(small.subvolume)
    widget.step.setValue(small.step)
    assert widget.tiled.isChecked()
    widget.max_memory.setText("lots")
    assert widget.run() is None and "lots" in widget.message.text()
    widget.max_memory.setText("1GB")
    assert widget.job().tiled and widget.job().max_memory == "1GB"
    run_panel(widget)
    assert widget.last_error is None, widget.last_error
    field = L.field_of(viewer.layers["|u| (uncorrected)"])
    params = CorrelationParams(subvolume=small.subvolume, step=small.step)
    memory = correlate(reference, deformed, params)
    np.testing.assert_array_equal(field.status, memory.status)
    good = memory.valid
    assert np.max(np.abs(field.u[good] - memory.u[good])) < 1e-4
    assert widget.settings()["tiled"] is True


def test_a_lazy_pair_self_corrects_out_of_core(lazy_panel, pair48, run_panel, small):
    """The Self-correct panel ticks 'out of core' for Dask-backed scans; the tiled correction
    gives the in-memory correction of the same field."""
    from napari_dvc_correct.engine.correction.self_correction import correct_iter
    from napari_dvc_correct.engine.progress import run_to_completion
    from napari_dvc_correct.widgets import CorrectWidget

    reference, deformed, _ = pair48
    correlate, viewer = lazy_panel, lazy_panel.viewer
    run_panel(correlate)
    field = L.field_of(viewer.layers["|u| (uncorrected)"])
    correct = CorrectWidget(viewer)
    viewer.window.add_dock_widget(correct)
    assert correct.tiled.isChecked()
    correct.max_passes.setValue(1)
    run_panel(correct)
    assert correct.last_error is None, correct.last_error
    tiled = L.field_of(viewer.layers["|u| (corrected)"])
    assert "tiled" in tiled.metadata["correction"]  # it did run out of core
    options = {"frame": correct.frame.currentData(), "update": correct.update_rule.currentData()}
    memory = run_to_completion(correct_iter(reference, deformed, field, max_passes=1, **options))
    np.testing.assert_array_equal(tiled.status, memory.status)
    good = memory.valid
    assert np.max(np.abs(tiled.u[good] - memory.u[good])) < 1e-4


def test_a_lazy_pair_evaluates_out_of_core(lazy_panel, pair48, run_panel, small):
    """The Evaluate panel ticks 'out of core' for Dask-backed scans; the residual comes back as
    a lazy Zarr layer and the accuracy is the in-memory one."""
    from napari_dvc_correct.engine.evaluation.accuracy import evaluate_iter
    from napari_dvc_correct.engine.progress import run_to_completion
    from napari_dvc_correct.widgets import EvaluateWidget
    from napari_dvc_correct.widgets.evaluate_model import ready_for_evaluation

    reference, deformed, _ = pair48
    correlate, viewer = lazy_panel, lazy_panel.viewer
    run_panel(correlate)
    field = L.field_of(viewer.layers["|u| (uncorrected)"])
    evaluate = EvaluateWidget(viewer)
    viewer.window.add_dock_widget(evaluate)
    assert evaluate.tiled.isChecked()
    run_panel(evaluate)
    assert evaluate.last_error is None, evaluate.last_error
    layer = viewer.layers["residual volume (uncorrected)"]
    assert not isinstance(layer.data, np.ndarray)  # read lazily from its Zarr file
    assert layer.data.shape == reference.shape
    memory = run_to_completion(
        evaluate_iter(
            reference,
            deformed,
            {"uncorrected": ready_for_evaluation(field)},
            phases=evaluate.thresholds(),
            keep_volumes=True,
        )
    )
    (tiled_item,), (memory_item,) = evaluate.evaluation.fields, memory.fields
    assert abs(tiled_item.accuracy - memory_item.accuracy) < 1e-9
    assert abs(tiled_item.mean_residual - memory_item.mean_residual) < 1e-6
    np.testing.assert_allclose(np.asarray(layer.data), memory_item.residual, atol=1e-4)
    # the residual's temporary folder stays while its layer reads it, and no longer
    from napari_dvc_correct.widgets.evaluate import TEMPORARY_KEY

    def folder_of(name):
        return Path(viewer.layers[name].metadata[L.MARKER][TEMPORARY_KEY])

    first = folder_of("residual volume (uncorrected)")
    assert first.is_dir() and first.name.startswith("dvc-evaluate-")
    run_panel(evaluate)  # again: the new layers replace the old, whose folder goes
    assert evaluate.last_error is None, evaluate.last_error
    second = folder_of("residual volume (uncorrected)")
    assert second != first and second.is_dir() and not first.exists()
    assert np.isfinite(np.asarray(viewer.layers["residual volume (uncorrected)"].data)).any()
    viewer.layers.remove("residual volume (uncorrected)")
    assert not second.exists()


def test_a_threshold_region_over_a_lazy_pair_is_read_by_the_tiled_run(
    lazy_panel, pair48, run_panel, small
):
    """The region's mask over a Dask-backed scan stays lazy: the tiled run reads it batch by
    batch and gives the in-memory field with the whole mask."""
    from napari_dvc_correct.engine.correlation.correlate import correlate
    from napari_dvc_correct.engine.correlation.params import CorrelationParams
    from napari_dvc_correct.engine.fields.field import Status
    from napari_dvc_correct.widgets import regions_model

    reference, deformed, _ = pair48
    widget, viewer = lazy_panel, lazy_panel.viewer
    widget.region.set_kind("threshold")
    widget.region.threshold.setValue(float(np.percentile(reference, 30)))
    widget.region.z_from.setValue(10)
    assert widget.tiled.isChecked()
    assert isinstance(widget.job().mask, regions_model.ThresholdRegion)
    run_panel(widget)
    assert widget.last_error is None, widget.last_error
    field = L.field_of(viewer.layers["|u| (uncorrected)"])
    mask = np.asarray(widget.job().mask)
    params = CorrelationParams(subvolume=small.subvolume, step=small.step)
    memory = correlate(reference, deformed, params, mask=mask)
    np.testing.assert_array_equal(field.status, memory.status)
    assert (memory.status == Status.MASKED).any()
    good = memory.valid
    assert np.max(np.abs(field.u[good] - memory.u[good])) < 1e-4
