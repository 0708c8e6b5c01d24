"""The Correlate dock end to end on a small soil-like pair, under Xvfb."""

from __future__ import annotations

import time

import numpy as np
import pytest
from qtpy.QtCore import QTimer

from napari_dvc_correct._sample_data import true_field
from napari_dvc_correct.engine.fields.field import DisplacementField, Status, grid_for_volume
from napari_dvc_correct.layers import field_of, fields_in
from napari_dvc_correct.widgets import CorrelateWidget
from napari_dvc_correct.widgets.correlate import PREVIEW_BOX, PREVIEW_POINTS

FIELD_LAYERS = ["|u| (uncorrected)", "displacement (uncorrected)"]  # a quantity, and arrows


def test_run_adds_the_field_layers_aligned_with_the_volume(correlated, pair48, placement, small):
    viewer = correlated.viewer
    names = [layer.name for layer in viewer.layers]
    for name in FIELD_LAYERS:
        assert name in names
    field = field_of(viewer.layers["|u| (uncorrected)"])
    assert isinstance(field, DisplacementField)
    assert field.shape == grid_for_volume(small.shape, small.subvolume, small.step)[2]
    assert field.n_points >= 27
    scale, translate = placement(field)
    for name in FIELD_LAYERS:
        layer = viewer.layers[name]
        np.testing.assert_allclose(layer.scale, scale, err_msg=name)
        np.testing.assert_allclose(layer.translate, translate, err_msg=name)
    # the measured field is close to the known shear band (voxels)
    truth = true_field(pair48[2], field.origin, field.step, field.shape)
    error = np.linalg.norm(field.u - truth.u, axis=-1)[field.valid]
    assert field.valid.mean() > 0.9
    assert np.median(error) < 0.25
    # the vectors land on the nodes in world coordinates, with the true displacement
    vectors = viewer.layers["displacement (uncorrected)"]
    node = vectors.data[0, 0]
    world = vectors.data_to_world(node)
    expected = np.asarray(translate) + node * np.asarray(scale)
    np.testing.assert_allclose(world, expected)
    i, j, k = node.astype(int)
    np.testing.assert_allclose(vectors.data[0, 1] * field.step, field.u[i, j, k])
    # no preview over the result
    assert PREVIEW_POINTS not in viewer.layers or not viewer.layers[PREVIEW_POINTS].visible


def test_rerun_replaces_its_layers(correlated, run_panel, small):
    viewer = correlated.viewer
    count = len(viewer.layers)
    old = viewer.layers["|u| (uncorrected)"]
    correlated.step.setValue(10)
    run_panel(correlated)
    assert len(viewer.layers) == count
    new = viewer.layers["|u| (uncorrected)"]
    assert new is old  # updated in place: no new canvas visual, no garbage-collection pause
    assert field_of(new).step == (10.0, 10.0, 10.0)
    np.testing.assert_allclose(new.scale, np.asarray(field_of(new).step) * small.voxel_size)
    assert new.data.shape == field_of(new).shape
    arrows = viewer.layers["displacement (uncorrected)"]
    assert len(arrows.features["magnitude"]) == len(arrows.data)


def test_cancel_keeps_the_earlier_layers(correlated, qtbot):
    viewer = correlated.viewer
    before = {layer.name: layer for layer in viewer.layers}
    old_field = field_of(viewer.layers["|u| (uncorrected)"])
    correlated.step.setValue(6)
    worker = correlated.run(start=False)
    returned = []
    worker.returned.connect(returned.append)
    worker.yielded.connect(lambda value: correlated.cancel())  # cancel at the first report
    with qtbot.waitSignal(worker.finished, timeout=120_000):
        worker.start()
    assert not returned
    assert {layer.name: layer for layer in viewer.layers} == before
    assert field_of(viewer.layers["|u| (uncorrected)"]) is old_field
    assert "Cancelled" in correlated.message.text()
    assert correlated.run_button.isEnabled() and not correlated.cancel_button.isEnabled()


def test_preview_and_estimate_before_running(viewer_pair, small):
    widget = CorrelateWidget(viewer_pair)
    viewer_pair.window.add_dock_widget(widget)
    widget.subvolume.setValue(small.subvolume)
    widget.step.setValue(small.step)
    widget._update.flush()
    points = viewer_pair.layers[PREVIEW_POINTS]
    box = viewer_pair.layers[PREVIEW_BOX]
    origin, _, shape = grid_for_volume(small.shape, small.subvolume, small.step)
    assert len(points.data) == np.prod(shape)
    # the first POI of the grid the engine will use, in world units through the voxel size
    first = points.data_to_world(points.data[0])
    expected = np.asarray(small.offset) + np.asarray(origin) * np.asarray(small.voxel_size)
    np.testing.assert_allclose(first, expected)
    corners = np.concatenate(box.data)
    assert np.ptp(corners, axis=0).tolist() == [small.subvolume - 1] * 3
    assert f"{np.prod(shape)} POIs" in widget.estimate_label.text()
    assert "memory" in widget.estimate_label.text()
    # at the defaults the slice shown is a plane of POIs, so the preview is seen at once
    assert len(points._view_indices) == shape[1] * shape[2]
    widget.preview.setChecked(False)
    widget._update.flush()
    assert not points.visible


@pytest.mark.parametrize("problem", ["same layer", "2-D image", "missing mask", "empty mask"])
def test_bad_choices_show_a_message(viewer_pair, problem):
    widget = CorrelateWidget(viewer_pair)
    viewer_pair.window.add_dock_widget(widget)
    widget.subvolume.setValue(15)
    if problem == "same layer":
        widget.deformed.set_layer("reference")
        expected = "same layer"
    elif problem == "2-D image":
        viewer_pair.add_image(np.zeros((40, 40), np.float32), name="slice")
        widget.deformed.set_layer("slice")
        expected = "2-D"
    elif problem == "missing mask":
        widget.region.set_kind("layer")
        expected = "no mask is chosen"
    else:
        viewer_pair.add_labels(np.zeros((48, 48, 48), np.uint8), name="mask")
        widget.region.set_kind("layer")
        widget.region.layer.set_layer("mask")
        expected = "empty"
    count = len(viewer_pair.layers)
    assert widget.run() is None
    assert expected in widget.message.text()
    assert widget.last_error == widget.message.text()
    assert len(viewer_pair.layers) == count
    assert widget.run_button.isEnabled()


def test_mask_marks_outside_pois(viewer_pair, run_panel, small):
    mask = np.zeros(small.shape, np.uint8)
    mask[:, :, :26] = 1  # the left half only
    viewer_pair.add_labels(mask, name="material", scale=small.voxel_size, translate=small.offset)
    widget = CorrelateWidget(viewer_pair)
    viewer_pair.window.add_dock_widget(widget)
    widget.subvolume.setValue(small.subvolume)
    widget.step.setValue(small.step)
    widget.region.set_kind("layer")
    widget.region.layer.set_layer("material")
    run_panel(widget)
    field = field_of(viewer_pair.layers["|u| (uncorrected)"])
    x = field.axis_coordinates()[2]
    outside = x > 25.5  # more than half of the subvolume right of the mask's edge
    assert outside.any() and (~outside).any()
    assert np.all(field.status[:, :, outside] == Status.MASKED)
    assert field.valid[:, :, ~outside].all()


def test_ui_stays_responsive_during_a_run(viewer_pair, qtbot, small):
    """Largest gap between 10 ms timer ticks on the main thread while the engine runs."""
    from napari_dvc_correct.engine.correlation.correlate import correlate
    from napari_dvc_correct.engine.correlation.params import CorrelationParams

    reference = viewer_pair.layers["reference"].data
    deformed = viewer_pair.layers["deformed"].data
    correlate(reference, deformed, CorrelationParams(subvolume=15, step=12))  # JIT warm-up
    widget = CorrelateWidget(viewer_pair)
    viewer_pair.window.add_dock_widget(widget)
    widget.subvolume.setValue(small.subvolume)
    widget.step.setValue(4)  # ~1000 POIs: long enough to measure
    widget.preview.setChecked(False)
    # on a fast, quiet machine one run can be shorter than what a gap needs to mean something:
    # runs repeat (each measured from its own first tick to its end) until 0.5 s are covered
    gaps, covered = [], 0.0
    for _ in range(10):
        ticks = []
        timer = QTimer()
        timer.setInterval(10)
        timer.timeout.connect(lambda ticks=ticks: ticks.append(time.perf_counter()))
        worker = widget.run(start=False)
        ended = []
        worker.returned.connect(lambda result, ended=ended: ended.append(time.perf_counter()))
        timer.start()
        with qtbot.waitSignal(worker.finished, timeout=300_000):
            worker.start()
        timer.stop()
        during = np.asarray([t for t in ticks if t <= ended[0]])
        if len(during) > 1:
            gaps.extend(np.diff(during))
            covered += ended[0] - during[0]
        qtbot.waitUntil(lambda: not widget.running, timeout=60_000)
        if covered > 0.5:
            break
    assert covered > 0.3, "the runs were too short to say anything"
    gaps = np.asarray(gaps)
    assert len(gaps) > 10
    print(f"largest gap {gaps.max() * 1000:.0f} ms over {covered:.2f} s")
    assert gaps.max() < 0.2, f"largest gap {gaps.max() * 1000:.0f} ms"
    assert widget.last_error is None


@pytest.fixture(scope="module")
def series48():
    from napari_dvc_correct._sample_data import scan_series

    return scan_series((48, 48, 48), slips=(0.0, 1.5, 3.0))


@pytest.mark.parametrize("mode", ["series4d", "series"])
def test_scan_series(mode, series48, make_napari_viewer, run_panel, small):
    volumes, truths = series48
    viewer = make_napari_viewer()
    widget = CorrelateWidget(viewer)
    viewer.window.add_dock_widget(widget)
    if mode == "series4d":
        viewer.add_image(volumes, name="scan", scale=(1.0, *small.voxel_size))
        widget.mode.setCurrentIndex(widget.mode.findData("series4d"))
        widget.reference.set_layer("scan")
        strategy = "total"
    else:
        for k, volume in enumerate(volumes):
            viewer.add_image(volume, name=f"state{k}", scale=small.voxel_size)
        widget.mode.setCurrentIndex(widget.mode.findData("series"))
        widget.set_series_layers(["state0", "state1", "state2"])
        strategy = "incremental"
    widget.strategy.setCurrentIndex(widget.strategy.findData(strategy))
    widget.subvolume.setValue(small.subvolume)
    widget.step.setValue(small.step)
    run_panel(widget)
    assert widget.last_error is None, widget.last_error
    # one 4-D field (state, z, y, x) that follows the state slider, state 0 not moving
    layer = viewer.layers[f"|u| (series ({strategy}))"]
    assert layer.data.shape[0] == 3 and layer.visible
    assert f"displacement (series ({strategy}))" in viewer.layers
    np.testing.assert_allclose(layer.scale[1:], np.asarray(field_of(layer).step) * small.voxel_size)
    fields = fields_in(viewer.layers)
    assert list(fields) == [f"state 1 ({strategy})", f"state 2 ({strategy})"]
    for k in (1, 2):
        field = fields[f"state {k} ({strategy})"]
        truth = true_field(truths[k], field.origin, field.step, field.shape)
        error = np.linalg.norm(field.u - truth.u, axis=-1)[field.valid]
        assert np.median(error) < 0.3, (k, np.median(error))
    assert "state 1" in widget.message.text() and "state 2" in widget.message.text()


def test_series_bad_choices(viewer_pair):
    widget = CorrelateWidget(viewer_pair)
    viewer_pair.window.add_dock_widget(widget)
    widget.mode.setCurrentIndex(widget.mode.findData("series4d"))
    widget.reference.set_layer("reference")
    assert widget.run() is None
    assert "4-D mode needs" in widget.message.text()
    widget.mode.setCurrentIndex(widget.mode.findData("series"))
    widget.set_series_layers(["reference"])
    assert widget.run() is None
    assert "at least two" in widget.message.text()


def test_new_layers_do_not_bring_the_preview_back(correlated):
    viewer = correlated.viewer
    correlated.update_preview()
    correlated._set_preview_visible(False)
    viewer.add_points(np.zeros((1, 3)), name="annotations")  # not an input of the panel
    assert not correlated._update.timer.isActive()
    assert correlated.reference.currentText() == "reference"
    assert correlated.deformed.currentText() == "deformed"


def test_a_new_series_shows_its_strain_computed_in_the_worker(
    series48, make_napari_viewer, run_panel, qtbot, small, strain_calls
):
    """A series' state 0 (no displacement) is made with the result in the worker, and its
    strain computed there too: showing the 4-D field on the main thread computes no strain
    tensor (the worker computes the states' strain; before, the slot computed state 0's)."""
    from napari_dvc_correct import layers as L
    from napari_dvc_correct import quantities
    from napari_dvc_correct import viewer_layers as V
    from napari_dvc_correct.widgets import ViewWidget

    volumes, _ = series48
    viewer = make_napari_viewer()
    viewer.add_image(volumes, name="scan")
    view = ViewWidget(viewer)
    viewer.window.add_dock_widget(view)
    V.show_field(viewer, L.field_layers(_zero_field(small), "earlier"))
    view.set_quantity("εeq")
    qtbot.waitUntil(lambda: not view.busy, timeout=30_000)
    widget = CorrelateWidget(viewer)
    viewer.window.add_dock_widget(widget)
    widget.mode.setCurrentIndex(widget.mode.findData("series4d"))
    widget.reference.set_layer("scan")
    widget.subvolume.setValue(small.subvolume)
    widget.step.setValue(small.step)
    strain_calls.clear()
    run_panel(widget)
    assert widget.last_error is None, widget.last_error
    layer = viewer.layers["εeq (series (total))"]
    assert layer.visible and layer.data.shape[0] == 3
    calls = list(strain_calls)
    assert len(calls) == 3 and not any(calls), calls  # states 0, 1, 2, none on the main thread
    states = L.series_of(layer)
    assert not states[0].u.any()  # state 0: no displacement
    expected = np.stack([quantities.quantity_values(f.copy(), "εeq") for f in states])
    np.testing.assert_array_equal(layer.data, expected)  # as the slot used to compute it


def _zero_field(small):
    origin, step, shape = grid_for_volume(small.shape, small.subvolume, small.step)
    return DisplacementField(origin=origin, step=step, u=np.zeros((*shape, 3)))
