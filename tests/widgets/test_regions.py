"""CT-style regions: cylinders and boxes along z, thresholds with holes filled, drawn shapes
extruded through z, and the POI count said before a run (a region that keeps none is refused)."""

from __future__ import annotations

import numpy as np
import pytest

from napari_dvc_correct.engine.fields.field import Status
from napari_dvc_correct.layers import field_of
from napari_dvc_correct.widgets import CorrelateWidget
from napari_dvc_correct.widgets import regions_model as model
from napari_dvc_correct.widgets.correlate import PREVIEW_POINTS


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


def test_a_region_over_a_lazy_scan_stays_lazy_in_the_panel(lazy_panel, pair48, qtbot):
    """Over a Dask-backed scan the panel's cylinder and threshold regions are lazy masks: the
    cylinder's POIs are still counted before the run, the threshold's by the run itself."""
    reference = pair48[0]
    widget = lazy_panel
    widget.region.set_kind("cylinder")
    job = widget.job()
    assert isinstance(job.mask, model.PrismRegion)
    assert job.kept == model.kept_pois(np.asarray(job.mask), job.params)
    widget.region.set_kind("threshold")
    widget.region.threshold.setValue(135.0)
    widget._update.flush()
    qtbot.waitUntil(
        lambda: "marks the POIs outside" in widget.estimate_label.text(), timeout=20_000
    )
    job = widget.job()
    assert isinstance(job.mask, model.ThresholdRegion) and job.kept is None
    np.testing.assert_array_equal(np.asarray(job.mask), model.threshold_mask(reference, 135.0))


# --- the Region box alone ---------------------------------------------------------------------------
def test_the_region_box_s_masks_are_the_model_s(make_napari_viewer):
    from napari_dvc_correct.widgets import regions

    box = regions.RegionBox(make_napari_viewer())
    shape = (10, 21, 21)
    box.set_volume(shape)  # defaults: full ranges, a centred cylinder of 0.45 the section
    assert (box.z_to.value(), box.y_to.value(), box.x_to.value()) == (10, 21, 21)
    assert (box.centre_y.value(), box.centre_x.value()) == (10.0, 10.0)
    assert box.radius.value() == pytest.approx(0.45 * 21, abs=0.05)  # to a tenth of a voxel
    box.set_kind("all")
    assert box.mask(shape) is None  # the whole volume: no mask
    box.set_kind("cylinder")
    box.radius.setValue(5.0)
    box.z_from.setValue(2)
    box.z_to.setValue(8)
    expected = model.cylinder_mask(shape, (10.0, 10.0), 5.0, z_range=(2, 8))
    np.testing.assert_array_equal(np.asarray(box.mask(shape)), expected)
    box.set_kind("box")
    box.y_from.setValue(5)
    box.y_to.setValue(15)
    box.x_to.setValue(3)
    np.testing.assert_array_equal(
        np.asarray(box.mask(shape)), model.box_mask(shape, (2, 8), (5, 15), (0, 3))
    )
    box.x_from.setValue(3)  # an empty box is refused, the axis named
    with pytest.raises(ValueError, match=r"the x range \(3, 3\) selects no voxel of the 21"):
        box.mask(shape)
    # the settings a session saves come back
    saved = box.settings()
    other = regions.RegionBox(box.viewer)
    other.restore(saved)
    assert other.settings() == saved and other.current_kind == "box"
