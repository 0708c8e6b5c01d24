"""The View dock: the quantity chooser, its colorbar and units, before/after, the line profile."""

from __future__ import annotations

import time

import numpy as np
import pytest

from napari_dvc_correct import layers as L
from napari_dvc_correct import viewer_layers as V
from napari_dvc_correct.engine.fields.field import DisplacementField
from napari_dvc_correct.widgets.view import ViewWidget

A = 0.02  # simple shear: u_x = A z, so εzx = A / 2, εeq = 2 (A/2) / sqrt(3)


def _shear(scale: float = 1.0) -> DisplacementField:
    shape = (8, 6, 6)
    z = 4.0 + 4.0 * np.arange(shape[0])
    u = np.zeros((*shape, 3))
    u[..., 2] = A * z[:, None, None]
    return DisplacementField(
        origin=(4, 4, 4),
        step=(4, 4, 4),
        u=scale * u,
        metadata={"voxel_size": [1.0, 1.0, 1.0], "offset": [0.0, 0.0, 0.0]},
    )


def delivered(worker) -> list:
    """A list that gets an entry once ``worker``'s ``finished`` signal reaches the main thread
    (its ``yielded`` and ``returned`` signals, emitted before, have been handled by then)."""
    done = []
    worker.finished.connect(lambda: done.append(True))
    return done


def settle(qtbot, view) -> None:
    """Wait for the View panel's workers (quantity and profile) to finish."""
    qtbot.waitUntil(lambda: not view.busy, timeout=30_000)


@pytest.fixture
def view(make_napari_viewer):
    viewer = make_napari_viewer()
    viewer.add_image(np.zeros((40, 32, 32), np.float32), name="scan")
    widget = ViewWidget(viewer)
    viewer.window.add_dock_widget(widget)
    V.show_field(viewer, L.field_layers(_shear(1.1), "uncorrected"))
    V.show_field(viewer, L.field_layers(_shear(1.0), "corrected"))
    return widget


def test_chooser_switches_every_field_with_one_range_and_a_colorbar(view, qtbot):
    viewer = view.viewer
    assert len(viewer.layers) == 5  # the scan, and two layers per field
    offered = [view.quantity.itemData(i) for i in range(view.quantity.count())]
    for key in ("|u|", "uz", "εzz", "εzx", "ε1", "ε3", "εvol", "γmax", "εeq", "ZNCC", "status"):
        assert key in offered
    view.set_quantity("εzx")
    settle(qtbot, view)
    corrected, uncorrected = viewer.layers["εzx (corrected)"], viewer.layers["εzx (uncorrected)"]
    inner = (slice(1, -1),) * 3
    np.testing.assert_allclose(corrected.data[inner], A / 2, rtol=1e-5)
    np.testing.assert_allclose(uncorrected.data[inner], 1.1 * A / 2, rtol=1e-5)
    assert list(corrected.contrast_limits) == list(uncorrected.contrast_limits)  # one range
    low, high = corrected.contrast_limits
    assert low == -high  # signed: centred on zero
    assert corrected.blending == "translucent" and corrected.opacity < 1
    # only the field on view has its colorbar; the caption names quantity and units
    assert corrected.visible and corrected.colorbar.visible
    assert not uncorrected.visible and not uncorrected.colorbar.visible
    assert "εzx" in view.caption.text() and "strain" in view.caption.text()
    # on the canvas, a short colorbar title that a narrow canvas does not cut off
    assert V.text_overlay(viewer).text == "εzx [strain, –] · corrected"
    assert len(V.text_overlay(viewer).text) < 40
    view.set_quantity("|u|")
    settle(qtbot, view)
    assert "[vx]" in view.caption.text()
    view.colorbar.setChecked(False)
    assert not viewer.layers["|u| (corrected)"].colorbar.visible
    # before/after toggles rather than stacks
    assert view.before_after() == "uncorrected"
    assert viewer.layers["|u| (uncorrected)"].visible
    assert not viewer.layers["|u| (corrected)"].visible
    assert not viewer.layers["displacement (corrected)"].visible
    view.show_source("all (overlaid)")
    assert viewer.layers["|u| (corrected)"].visible and viewer.layers["|u| (uncorrected)"].visible


def test_oblique_3d_view(view):
    view.oblique_3d()
    assert view.viewer.dims.ndisplay == 3
    np.testing.assert_allclose(view.viewer.scene.camera.angles, (-20.0, 30.0, 120.0))


def test_line_profile_follows_the_field(view, qtbot):
    view.set_quantity("εzx")
    settle(qtbot, view)
    layer = view.start_line()
    assert layer.mode == "add_line"
    # a line along z through the column of nodes at y = x = 12 (world = voxels here)
    layer.add_lines(np.array([[6.0, 12.0, 12.0], [30.0, 12.0, 12.0]]))
    view.update_profile()
    settle(qtbot, view)
    displacement, strain = view.profile_groups
    assert [p.source for p in displacement] == ["uncorrected", "corrected"]
    corrected = displacement[1]
    z = 6.0 + corrected.distance
    np.testing.assert_allclose(corrected.values, A * z, rtol=1e-6)  # |u| = u_x = A z
    assert strain[1].quantity == "εzx"
    middle = (z > 9) & (z < 27)  # away from the one-sided edges of the gradient
    np.testing.assert_allclose(strain[1].values[middle], A / 2, rtol=1e-5)
    np.testing.assert_allclose(strain[0].values[middle], 1.1 * A / 2, rtol=1e-5)
    assert len(view.profile.axes[0].lines) == 2
    # the distance axis says its unit (voxels here: no voxel size)
    assert corrected.distance_unit == "vx"
    assert view.profile.axes[0].get_xlabel() == "distance along the line [vx]"


def _large(n: int = 64) -> DisplacementField:
    """A field of n³ nodes with a smooth, non-trivial strain (the eigenvalues cost ~0.3–1 s)."""
    z, y, x = np.meshgrid(*[np.arange(n, dtype=float)] * 3, indexing="ij")
    u = np.stack([0.01 * x * y / n, 0.02 * np.sin(z / 7.0) * n, 0.03 * z + 0.01 * x], axis=-1)
    return DisplacementField(
        origin=(4, 4, 4),
        step=(2, 2, 2),
        u=u,
        metadata={"voxel_size": [1.0, 1.0, 1.0], "offset": [0.0, 0.0, 0.0]},
    )


@pytest.fixture
def large_view(make_napari_viewer):
    viewer = make_napari_viewer()
    widget = ViewWidget(viewer)
    viewer.window.add_dock_widget(widget)
    field = _large()
    V.show_field(viewer, L.field_layers(field, "uncorrected"))
    return widget, field


def test_the_ui_stays_responsive_while_a_large_strain_computes(large_view, qtbot):
    """Largest gap between 10 ms timer ticks on the main thread while ε1 of 64³ nodes computes."""
    from qtpy.QtCore import QTimer

    view, field = large_view
    ticks = []
    timer = QTimer()
    timer.setInterval(10)
    timer.timeout.connect(lambda: ticks.append(time.perf_counter()))
    timer.start()
    qtbot.waitUntil(lambda: len(ticks) >= 3, timeout=5000)  # the timer ticks
    called = time.perf_counter()
    worker = view.set_quantity("ε1")
    returned = time.perf_counter()
    assert worker is not None, "nothing was computed in a worker"
    ended = []
    worker.finished.connect(lambda: ended.append(time.perf_counter()))
    settle(qtbot, view)
    qtbot.waitUntil(lambda: bool(ended), timeout=30_000)
    timer.stop()
    print(f"set_quantity held the main thread {1000 * (returned - called):.0f} ms")
    assert returned - called < 0.1  # the call only starts the worker
    during = np.asarray([t for t in ticks if called <= t <= ended[0]])
    assert ended[0] - called > 0.2, "the computation was too short to say anything"
    gaps = np.diff(during)
    assert len(gaps) > 10
    print(f"largest gap {gaps.max() * 1000:.0f} ms over {ended[0] - called:.2f} s")
    assert gaps.max() < 0.2, f"largest gap {gaps.max() * 1000:.0f} ms"
    layer = view.viewer.layers["ε1 (uncorrected)"]
    np.testing.assert_array_equal(layer.data, L.quantity_values(field, "ε1"))


def test_the_last_choice_wins_and_switching_back_is_instant(large_view, qtbot):
    view, field = large_view
    viewer = view.viewer
    first = view.set_quantity("ε1")
    first_delivered = delivered(first)
    second = view.set_quantity("εeq")  # before the first is done: it supersedes it
    assert first is not None and second is not None and first is not second
    assert "computing" in view.message.text()
    assert "|u| (uncorrected)" in viewer.layers  # the old quantity stays until the new is ready
    settle(qtbot, view)
    qtbot.waitUntil(lambda: first.is_running is False, timeout=30_000)
    qtbot.waitUntil(lambda: bool(first_delivered), timeout=30_000)  # its late signals, handled
    (layer,) = L.quantity_layers(viewer)
    assert L.plugin_metadata(layer)["quantity"] == "εeq"
    assert layer.name == "εeq (uncorrected)"
    np.testing.assert_array_equal(layer.data, L.quantity_values(field, "εeq"))
    assert view.message.text() == ""
    # both seen quantities are cached: switching back computes nothing, at once
    assert view.set_quantity("|u|") is None
    assert L.plugin_metadata(layer)["quantity"] == "|u|"
    np.testing.assert_array_equal(layer.data, L.quantity_values(field, "|u|"))
    assert view.set_quantity("εeq") is None
    np.testing.assert_array_equal(layer.data, L.quantity_values(field, "εeq"))
    low, high = layer.contrast_limits
    assert 0 <= low < high  # a positive strain's range came back with it


def test_a_switch_during_a_computation_to_a_cached_quantity_wins(large_view, qtbot):
    view, field = large_view
    worker = view.set_quantity("εzx")
    worker_delivered = delivered(worker)
    assert view.set_quantity("|u|") is None  # cached (what the layer showed first)
    (layer,) = L.quantity_layers(view.viewer)
    assert L.plugin_metadata(layer)["quantity"] == "|u|"
    qtbot.waitUntil(lambda: worker.is_running is False, timeout=30_000)
    qtbot.waitUntil(lambda: bool(worker_delivered), timeout=30_000)  # its late signals, handled
    assert L.plugin_metadata(layer)["quantity"] == "|u|"  # the late εzx did not come back
    np.testing.assert_array_equal(layer.data, L.quantity_values(field, "|u|"))


@pytest.mark.parametrize("error", [ValueError, TypeError])
def test_a_worker_error_shows_as_a_message(view, qtbot, monkeypatch, error):
    """A bad choice (ValueError, per field) and a bug (any other error: the worker's errored
    handler) both end as one line in the panel, the layers unchanged."""

    def broken(*args, **kwargs):
        raise error("the strain cannot be computed here")

    monkeypatch.setattr(L, "quantity_update", broken)
    view.set_quantity("εvol")
    settle(qtbot, view)
    assert "cannot be computed" in view.message.text()
    assert L.plugin_metadata(L.quantity_layers(view.viewer)[0])["quantity"] == "|u|"


def test_a_new_result_shows_the_quantity_on_view_and_the_chooser_says_so(view, qtbot):
    """A new field comes on view with the quantity looked at; the chooser names what is shown
    (it said |u| before, while the layers showed εeq)."""
    view.set_quantity("εeq")
    settle(qtbot, view)
    V.show_field(view.viewer, L.field_layers(_shear(1.2), "corrected"))
    (shown,) = [x for x in L.quantity_layers(view.viewer) if x.visible]
    assert L.plugin_metadata(shown)["quantity"] == "εeq"
    assert view.quantity.currentData() == "εeq"
    # a choice the fields cannot show is said, and the chooser comes back to what is shown
    view.set_quantity("residual")
    settle(qtbot, view)
    assert "run Evaluate first" in view.message.text()
    assert view.quantity.currentData() == "εeq"


def test_a_new_result_brings_its_strain_computed_in_the_worker(correlated, run_panel, qtbot):
    """The run's worker computes the quantity on view for the new field: showing it on the
    main thread computes no strain tensor."""
    import threading

    from napari_dvc_correct import quantities

    viewer = correlated.viewer
    view = ViewWidget(viewer)
    viewer.window.add_dock_widget(view)
    view.set_quantity("εeq")
    settle(qtbot, view)
    calls = []
    original = quantities.physical_strain

    def recording(field):
        calls.append(threading.current_thread() is threading.main_thread())
        return original(field)

    quantities.physical_strain = recording
    try:
        run_panel(correlated)
    finally:
        quantities.physical_strain = original
    layer = viewer.layers["εeq (uncorrected)"]
    assert layer.visible and view.quantity.currentData() == "εeq"
    assert calls and not any(calls), calls  # computed, and never on the main thread
    np.testing.assert_array_equal(layer.data, L.quantity_values(L.field_of(layer), "εeq"))


def test_the_last_field_opened_from_a_file_is_on_view(make_napari_viewer):
    """Fields opened from files (our reader's layers, added by napari) come on view one at a time,
    the newest shown, as a new result does (user audit, item 3)."""
    from napari.layers import Layer

    viewer = make_napari_viewer()
    view = ViewWidget(viewer)
    viewer.window.add_dock_widget(view)
    for scale, stem in ((1.0, "ldic"), (1.1, "aldvc"), (1.2, "snow48")):
        for data, kwargs, layer_type in L.field_layers(_shear(scale), stem):
            viewer.add_layer(Layer.create(data, kwargs, layer_type))
    assert view.shown.currentText() == "snow48"
    on_view = [x.name for x in viewer.layers if x.visible]
    assert on_view == ["|u| (snow48)", "displacement (snow48)"]
    assert viewer.layers["|u| (snow48)"].colorbar.visible
    assert not viewer.layers["|u| (aldvc)"].colorbar.visible
    view.show_source("all (overlaid)")  # still there when asked for
    assert all(x.visible for x in viewer.layers)


def test_choosing_a_quantity_hides_the_phase_labels_over_the_field(view, qtbot):
    """After Evaluate, its phase labels (opacity 0.4) lay over the field: View's uz was read
    through their colours. Choosing a quantity puts the field alone on view."""
    viewer = view.viewer
    V.show_layers(viewer, [L.phase_layer(np.ones((40, 32, 32), np.uint8))])
    assert viewer.layers["phases"].visible
    view.set_quantity("uz")
    settle(qtbot, view)
    assert not viewer.layers["phases"].visible and viewer.layers["uz (corrected)"].visible
