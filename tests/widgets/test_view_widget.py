"""The View dock: the quantity chooser, its colorbar and units, before/after, the line profile."""

from __future__ import annotations

import numpy as np
import pytest

from napari_dvc_correct import layers as L
from napari_dvc_correct.engine.field import DisplacementField
from napari_dvc_correct.widgets import ViewWidget

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


@pytest.fixture
def view(make_napari_viewer):
    viewer = make_napari_viewer()
    viewer.add_image(np.zeros((40, 32, 32), np.float32), name="scan")
    widget = ViewWidget(viewer)
    viewer.window.add_dock_widget(widget)
    L.show_field(viewer, L.field_layers(_shear(1.1), "uncorrected"))
    L.show_field(viewer, L.field_layers(_shear(1.0), "corrected"))
    return widget


def test_chooser_switches_every_field_with_one_range_and_a_colorbar(view):
    viewer = view.viewer
    assert len(viewer.layers) == 5  # the scan, and two layers per field
    offered = [view.quantity.itemData(i) for i in range(view.quantity.count())]
    for key in ("|u|", "uz", "εzz", "εzx", "ε1", "ε3", "εvol", "γmax", "εeq", "ZNCC", "status"):
        assert key in offered
    view.set_quantity("εzx")
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
    assert L.text_overlay(viewer).text == view.caption.text()
    view.set_quantity("|u|")
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


def test_line_profile_follows_the_field(view):
    view.set_quantity("εzx")
    layer = view.start_line()
    assert layer.mode == "add_line"
    # a line along z through the column of nodes at y = x = 12 (world = voxels here)
    layer.add_lines(np.array([[6.0, 12.0, 12.0], [30.0, 12.0, 12.0]]))
    displacement, strain = view.update_profile()
    assert [p.source for p in displacement] == ["uncorrected", "corrected"]
    corrected = displacement[1]
    z = 6.0 + corrected.distance
    np.testing.assert_allclose(corrected.values, A * z, rtol=1e-6)  # |u| = u_x = A z
    assert strain[1].quantity == "εzx"
    middle = (z > 9) & (z < 27)  # away from the one-sided edges of the gradient
    np.testing.assert_allclose(strain[1].values[middle], A / 2, rtol=1e-5)
    np.testing.assert_allclose(strain[0].values[middle], 1.1 * A / 2, rtol=1e-5)
    assert len(view.profile.axes[0].lines) == 2
