"""Regions of interest without Qt: cylinder, box, threshold or drawn masks, whole or by block."""

from __future__ import annotations

import numpy as np
import pytest

from napari_dvc_correct.engine.correlation.params import CorrelationParams
from napari_dvc_correct.widgets import regions_model as model


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


# -- lazy regions: the mask of a scan larger than memory is never held whole ------------------
def _volume(seed: int, shape=(30, 33, 35)) -> np.ndarray:
    from scipy.ndimage import gaussian_filter

    return gaussian_filter(np.random.default_rng(seed).normal(size=shape), 1.5)


@pytest.mark.parametrize("seed", range(4))
def test_filling_pores_slice_by_slice_equals_filling_in_3d_first(seed):
    """The lazy threshold region fills each slice alone: the same mask as a 3-D fill followed
    by the slice fill (the rule before regions were read block by block)."""
    from scipy.ndimage import binary_fill_holes

    volume = _volume(seed)
    threshold = np.percentile(volume, 40)
    expected = binary_fill_holes(volume > threshold)
    for z in range(expected.shape[0]):
        expected[z] = binary_fill_holes(expected[z])
    mask = model.threshold_mask(volume, threshold)
    assert 0 < (mask & ~(volume > threshold)).sum()  # some pores were filled
    np.testing.assert_array_equal(mask, expected)


def _regions(volume):
    shape = volume.shape
    labels = (volume > np.percentile(volume, 30)).astype(np.uint8)
    return {
        "cylinder": model.cylinder_region(shape, (15, 17), 9.5, (5, 24)),
        "box": model.box_region(shape, (2, 20), (4, 30), (0, 12)),
        "threshold": model.ThresholdRegion(volume, np.percentile(volume, 40), True, (3, 27)),
        "labels": model.LabelsRegion(labels, (1, 29)),
    }


@pytest.mark.parametrize("kind", ["cylinder", "box", "threshold", "labels"])
def test_a_region_reads_any_block_as_its_whole_mask_does(kind):
    volume = _volume(7)
    region = _regions(volume)[kind]
    whole = np.asarray(region)
    assert whole.dtype == bool and whole.shape == volume.shape and 0 < whole.sum() < whole.size
    assert not whole[: region.z.start].any() and not whole[region.z.stop :].any()
    for block in [
        (slice(0, 4), slice(3, 20), slice(5, 35)),
        (slice(20, 30), slice(0, 33), slice(9, 10)),
    ]:
        np.testing.assert_array_equal(region.read_region(block), whole[block])
    assert region.any() and model.emptiness(region) is False


@pytest.mark.parametrize("kind", ["cylinder", "box", "threshold", "labels"])
def test_a_lazy_region_keeps_the_pois_its_whole_mask_keeps(kind):
    """Prisms are counted from their cross-section, other regions with a window of slices
    moving up the volume: both give the summed-volume table's counts of the whole mask."""
    volume = _volume(3)
    region = _regions(volume)[kind]
    whole = np.asarray(region).copy()
    for params in (CorrelationParams(subvolume=9, step=4), CorrelationParams(subvolume=7, step=9)):
        kept = model.kept_pois(region, params)
        assert kept == model.kept_pois(whole, params)
        assert 0 < kept.kept < kept.total
        rng = np.random.default_rng(1)
        points = rng.uniform(params.half, np.array(volume.shape) - 1 - params.half, (200, 3))
        np.testing.assert_array_equal(
            model.kept_at(region, params, points), model.kept_at(whole, params, points)
        )


def test_counting_a_lazy_region_reads_each_slice_at_most_twice():
    """The POI count of a lazy threshold region holds one window of slices, never the volume."""
    volume = _volume(5, (40, 20, 20))
    reads = np.zeros(volume.shape[0], int)

    class Counted:
        shape, dtype = volume.shape, volume.dtype

        def __getitem__(self, index):
            reads[index[0]] += 1
            return volume[index]

    region = model.ThresholdRegion(Counted(), np.percentile(volume, 40), True)
    params = CorrelationParams(subvolume=9, step=3)
    assert model.kept_pois(region, params).kept > 0
    assert reads.max() <= 2 and reads.sum() >= volume.shape[0] - 2 * params.half


def test_an_empty_region_is_known_empty_without_reading_only_when_it_is_a_prism():
    shape = (10, 12, 12)
    assert model.emptiness(model.cylinder_region(shape, (-50, -50), 3)) is True
    region = model.ThresholdRegion(np.zeros(shape), 1.0)
    assert model.emptiness(region) is None  # not read yet
    assert not region.any() and model.emptiness(region) is True
    assert model.emptiness(np.zeros(shape, bool)) is True
