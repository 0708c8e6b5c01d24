"""CT-style regions: cylinders and boxes along z, thresholds with holes filled, drawn shapes
extruded through z, and the POI count said before a run (a region that keeps none is refused)."""

from __future__ import annotations

import numpy as np
import pytest

from napari_dvc_correct.engine.field import Status
from napari_dvc_correct.engine.params import CorrelationParams
from napari_dvc_correct.layers import field_of
from napari_dvc_correct.widgets import CorrelateWidget
from napari_dvc_correct.widgets import regions_model as model
from napari_dvc_correct.widgets.correlate import PREVIEW_POINTS


def test_cylinder_and_box_stand_along_z():
    mask = model.cylinder_mask((10, 21, 21), (10, 10), 5, z_range=(2, 8))
    assert not mask[:2].any() and not mask[8:].any()
    assert mask[5, 10, 10] and mask[5, 10, 15] and not mask[5, 10, 16] and not mask[5, 4, 4]
    np.testing.assert_array_equal(mask[2], mask[7])  # the same disc in every slice
    box = model.box_mask((10, 20, 30), (0, 10), (5, 15), (0, 3))
    assert box.sum() == 10 * 10 * 3


def test_threshold_fills_closed_pores():
    volume = np.zeros((9, 20, 20))
    volume[:, 4:16, 4:16] = 100.0  # the specimen
    volume[:, 8:12, 8:12] = 0.0  # a pore through every slice, closed in each slice
    mask = model.threshold_mask(volume, 50.0)
    assert mask[4, 10, 10] and mask.sum() == 9 * 12 * 12
    assert not model.threshold_mask(volume, 50.0, fill_holes=False)[4, 10, 10]


@pytest.mark.parametrize("ndim", [2, 3])
def test_a_rectangle_drawn_on_one_slice_is_a_prism_through_z(ndim):
    from napari.layers import Shapes

    corners = np.array([[2, 3], [2, 9], [6, 9], [6, 3]], float)
    if ndim == 3:  # drawn on slice 4 of a 3-D Shapes layer
        corners = np.hstack([np.full((4, 1), 4.0), corners])
    layer = Shapes([corners], shape_type="rectangle")
    mask = model.layer_mask(layer, (12, 10, 12), z_range=(1, 11))
    assert not mask[0].any() and not mask[11].any()
    assert mask[1, 4, 6] and mask[10, 4, 6] and not mask[5, 8, 6]
    np.testing.assert_array_equal(mask[1], mask[10])


def test_kept_pois_follows_the_engine_rule():
    params = CorrelationParams(subvolume=11, step=8)
    shape = (40, 40, 40)
    assert model.kept_pois(np.ones(shape, bool), params).kept == 64  # 4 × 4 × 4 nodes
    half = np.zeros(shape, bool)
    half[:, :, :20] = True  # nodes at x = 5, 13 inside; 21 has 5/11 of its box inside
    kept = model.kept_pois(half, params)
    assert kept.kept == 32 and kept.total == 64 and "32 of 64" in kept.text()
    with pytest.raises(ValueError, match="keeps none"):
        model.check_kept(model.box_mask(shape, (0, 3)), params)


@pytest.fixture
def panel(viewer_pair, small):
    widget = CorrelateWidget(viewer_pair)
    viewer_pair.window.add_dock_widget(widget)
    widget.subvolume.setValue(small.subvolume)
    widget.step.setValue(small.step)
    return widget


def test_a_cylinder_keeps_the_pois_inside_it(panel, run_panel, small, qtbot):
    panel.region.set_kind("cylinder")
    panel.region.set_volume(small.shape)
    panel.region.radius.setValue(14.0)
    panel._update.flush()  # the mask is made in a worker, then the preview follows
    qtbot.waitUntil(lambda: "the region keeps" in panel.estimate_label.text(), timeout=20_000)
    kept = model.kept_pois(panel.region.mask(small.shape), panel.params())
    assert 0 < kept.kept < kept.total
    assert len(panel.viewer.layers[PREVIEW_POINTS].data) == kept.kept  # the preview shows them
    run_panel(panel)
    assert panel.last_error is None, panel.last_error
    field = field_of(panel.viewer.layers["|u| (uncorrected)"])
    points = field.points.reshape(*field.shape, 3)
    centre = (np.asarray(small.shape[1:]) - 1) / 2
    distance = np.linalg.norm(points[..., 1:] - centre, axis=-1)
    masked = field.status == Status.MASKED
    assert np.all(masked[distance > 14.0 + small.subvolume / 2])  # mostly outside
    assert not masked[distance < 14.0 - small.subvolume / 2].any()  # wholly inside
    assert (~masked).sum() > 0 and masked.sum() > 0


def test_a_threshold_mask_is_made_in_a_worker_then_kept(panel, small, qtbot):
    """The threshold region (pores filled: seconds on a large scan) is computed off the main
    thread; the preview then uses it, and the run takes the same mask without computing."""
    reference = panel.viewer.layers["reference"].data
    panel.region.set_kind("threshold")
    panel.region.threshold.setValue(135.0)
    panel._update.flush()
    assert panel.estimate_label.text() == "computing the region's mask…"
    assert panel.region.busy
    qtbot.waitUntil(lambda: "the region keeps" in panel.estimate_label.text(), timeout=20_000)
    stored = panel.region._cache[1]
    expected = model.threshold_mask(reference, 135.0, True)
    np.testing.assert_array_equal(stored, expected)
    assert panel.job().mask is stored  # no second computation for the run
    assert panel.region.pending(reference.shape, reference) is None
    # a quick second threshold supersedes the first: the kept mask is the last one's
    panel.region.threshold.setValue(120.0)
    panel.update_preview()
    panel.region.threshold.setValue(150.0)
    panel.update_preview()
    qtbot.waitUntil(lambda: not panel.region.busy, timeout=20_000)
    qtbot.waitUntil(lambda: "the region keeps" in panel.estimate_label.text(), timeout=20_000)
    np.testing.assert_array_equal(
        panel.region.mask(reference.shape, reference), model.threshold_mask(reference, 150.0, True)
    )


def test_a_region_that_keeps_no_poi_is_refused(panel, small):
    panel.region.set_kind("box")
    panel.region.set_volume(small.shape)
    panel.region.z_from.setValue(0)
    panel.region.z_to.setValue(4)  # thinner than half a subvolume
    count = len(panel.viewer.layers)
    assert panel.run() is None
    assert "keeps none" in panel.message.text()
    assert len(panel.viewer.layers) == count
