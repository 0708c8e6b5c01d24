"""The Correlate dock with points of interest from a napari Points layer, and their result layers."""

from __future__ import annotations

import numpy as np

from napari_dvc_correct import layers as L
from napari_dvc_correct import viewer_layers as V
from napari_dvc_correct.engine.synthetic import sample_displacement, shear_band
from napari_dvc_correct.widgets import ViewWidget


def _world(small, voxels):
    return voxels * np.asarray(small.voxel_size) + np.asarray(small.offset)


def test_points_layer_run_gives_readable_point_layers(
    points_panel, run_panel, small, pair48, point_voxels
):
    from napari_dvc_correct.engine.correlation.correlate_points import correlate_points
    from napari_dvc_correct.engine.correlation.params import CorrelationParams

    voxels = point_voxels
    widget, viewer = points_panel, points_panel.viewer
    assert widget.points.currentText() == "my points"  # the new Points layer is chosen
    assert widget.points.isEnabled()
    widget._update.flush()
    assert "4 points of interest from 'my points'" in widget.estimate_label.text()
    run_panel(widget)
    assert widget.last_error is None, widget.last_error
    layer = viewer.layers["|u| (points)"]
    arrows = viewer.layers["displacement (points)"]
    # placed like the scans: the points sit where the user put them
    np.testing.assert_allclose(layer.scale, small.voxel_size)
    np.testing.assert_allclose(layer.translate, small.offset)
    np.testing.assert_allclose(layer.data, voxels)
    np.testing.assert_allclose(
        np.asarray(layer.data_to_world(layer.data[2])), _world(small, voxels)[2]
    )
    field = L.plugin_metadata(layer)["points_field"]
    reference, deformed, truth = pair48
    direct = correlate_points(
        reference, deformed, voxels, CorrelationParams(subvolume=small.subvolume, step=small.step)
    )
    np.testing.assert_allclose(field.u, direct.u, atol=1e-9)  # what the engine gives
    expected = sample_displacement(shear_band(**truth), voxels)
    assert np.median(np.abs(field.u - expected)) < 0.15  # and the known shear band
    # every quantity is a feature (in world units); the colours follow |u|
    features = layer.features
    vs = np.asarray(small.voxel_size)
    np.testing.assert_allclose(features["|u|"], np.linalg.norm(field.u * vs, axis=1))
    np.testing.assert_allclose(features["ux"], field.u[:, 2] * vs[2])
    for key in ("εeq", "εzx", "ZNCC", "status"):
        assert key in features.columns
    low, high = layer.face_contrast_limits
    assert low == 0.0 and high > 0.0 and layer.face_colormap.name == "viridis"
    # arrows from each point along its displacement (true length in world units, or scaled)
    np.testing.assert_allclose(arrows.data[:, 0], voxels[field.valid])
    np.testing.assert_allclose(arrows.data[:, 1], field.u[field.valid])
    np.testing.assert_allclose(arrows.scale, small.voxel_size)
    assert "Done: 4 points" in widget.message.text()
    counts = field.node_counts()  # the usable count and the counts by status, one definition
    assert f"usable {counts.usable} of 4 points ({counts.usable_fraction:.3f})" in (
        widget.message.text()
    )
    caption = V.text_overlay(viewer).text
    assert caption.startswith("|u| [scale units] at the points")  # not [vx]: a voxel size
    assert "viridis 0 to" in caption
    # the View panel recolours the points with the chosen quantity
    view = ViewWidget(viewer)
    viewer.window.add_dock_widget(view)
    view.set_quantity("ZNCC")
    assert layer.name == "ZNCC (points)"
    assert layer.face_colormap.name == "magma"
    assert "ZNCC" in view.caption.text() and "at the points" in view.caption.text()
    assert V.text_overlay(viewer).text.startswith("ZNCC [–] at the points")  # what is shown
    # the Correlate panel's line does not name the quantity the points were first coloured by
    assert "|u|" not in widget.message.text() and "ZNCC" not in widget.message.text()
    assert "canvas caption" in widget.message.text()
    view.set_quantity("εzx")
    low, high = layer.face_contrast_limits
    assert low == -high  # signed: centred on zero


def test_points_run_out_of_core_as_in_memory(points_panel, run_panel, small, pair48, point_voxels):
    """'Out of core' with points of interest: the guide in batches and the points in groups,
    each reading its region of the scans; the points get the in-memory result."""
    from napari_dvc_correct.engine.correlation.correlate_points import correlate_points
    from napari_dvc_correct.engine.correlation.params import CorrelationParams

    widget = points_panel
    widget.tiled.setChecked(True)
    widget.max_memory.setText("2GB")
    assert widget.job().tiled
    run_panel(widget)
    assert widget.last_error is None, widget.last_error
    field = L.plugin_metadata(widget.viewer.layers["|u| (points)"])["points_field"]
    assert field.metadata["tiled"]["groups"] >= 1
    reference, deformed, _ = pair48
    params = CorrelationParams(subvolume=small.subvolume, step=small.step)
    direct = correlate_points(reference, deformed, point_voxels, params)
    np.testing.assert_array_equal(field.status, direct.status)
    np.testing.assert_allclose(field.u, direct.u, atol=1e-3)


def test_points_outside_or_near_the_border_are_refused(points_panel, small):
    widget, viewer = points_panel, points_panel.viewer
    bad = np.array([[24.0, 24.0, 24.0], [24.0, 24.0, 60.0], [3.0, 24.0, 24.0]])
    viewer.layers["my points"].data = _world(small, bad)
    assert widget.run() is None
    text = widget.message.text()
    assert "1 outside the volume (48, 48, 48)" in text
    assert "1 closer than 7 voxels to its border" in text
    assert "smaller subvolume" in text
    widget.update_preview()  # the estimate line says it too, before a run
    assert "outside the volume" in widget.estimate_label.text()
    assert "|u| (points)" not in viewer.layers


def test_points_need_a_pair_and_a_points_layer(points_panel):
    widget, viewer = points_panel, points_panel.viewer
    widget.mode.setCurrentIndex(widget.mode.findData("series4d"))
    widget.reference.set_layer("reference")
    assert widget.run() is None
    assert "4-D" in widget.message.text() or "pair" in widget.message.text()
    widget.mode.setCurrentIndex(widget.mode.findData("pair"))
    widget.reference.set_layer("reference")
    widget.deformed.set_layer("deformed")
    viewer.layers.remove("my points")
    assert widget.run() is None
    assert "choose the Points layer" in widget.message.text()
    # the settings travel with a session
    assert widget.settings()["placement"] == "points"
