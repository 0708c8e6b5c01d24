"""The local residual and the local accuracy map (eq. 2 node by node) against known boxes."""

import numpy as np
import pytest

from napari_dvc_correct.engine.evaluation import local_accuracy as A
from napari_dvc_correct.engine.fields.field import DisplacementField


def _field(**params) -> DisplacementField:
    return DisplacementField.zeros((4.0, 4.0, 4.0), (4.0, 4.0, 4.0), (3, 3, 3)).replace(
        params=params
    )


def test_local_mean_residual_is_the_mean_of_each_node_s_box():
    residual = np.zeros((12, 12, 12), np.float32)
    residual[6:, :, :] = 3.0  # the upper half is badly explained
    residual[0:2, 0:2, 0:2] = np.nan  # undefined voxels do not count
    local = A.local_mean_residual(residual, _field(), half=1)
    # nodes at z = 4 see planes 3..5 (all 0); z = 8 planes 7..9 (all 3); z = 12 is clipped
    np.testing.assert_allclose(local[0], 0.0)
    np.testing.assert_allclose(local[1], 3.0)
    # the node at voxel (4, 4, 4) with half 3 sees planes 1..7, two of them at 3, a corner NaN
    wider = A.local_mean_residual(residual, _field(), half=3)
    box = residual[1:8, 1:8, 1:8]
    assert wider[0, 0, 0] == pytest.approx(np.nanmean(box.astype(np.float64)))


def test_local_accuracy_is_eq_2_per_node():
    local = np.array([2.0, 12.0, np.nan])
    p = A.local_accuracy_map(local, background=2.0, contrast=20.0)
    np.testing.assert_allclose(p[:2], [1.0, 0.5])
    assert np.isnan(p[2])
    with pytest.raises(ValueError, match="contrast must be > 0"):
        A.local_accuracy_map(local, 2.0, 0.0)


def test_region_half_is_the_subvolume_s_else_the_step():
    assert A.region_half(_field(subvolume=21)) == 10
    assert A.region_half(_field()) == 4


def test_honest_accuracy_counts_undefined_regions_as_failed():
    # clipped to [0, 1]: 1.2 counts 1, -0.5 counts 0; NaN counts 0
    assert A.honest_accuracy(np.array([1.2, 0.5, -0.5, np.nan])) == pytest.approx(1.5 / 4)
    assert np.isnan(A.honest_accuracy(np.array([])))


def _local_mean_as_before(residual, field, half):
    """local_mean_residual as it was written before NodeBoxMeans."""
    from napari_dvc_correct.engine.evaluation.binning import node_box_sums, node_voxels
    from napari_dvc_correct.engine.slabs import iter_slabs

    shape = residual.shape
    centers = node_voxels(field, shape)
    sums = np.zeros(field.shape)
    counts = np.zeros(field.shape, np.int64)
    for zs in iter_slabs(shape):
        box = (zs, slice(0, shape[1]), slice(0, shape[2]))
        node_box_sums(np.asarray(residual[zs], np.float32), box, centers, half).add_to(sums, counts)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(counts > 0, sums / np.maximum(counts, 1), np.nan)


def test_node_box_means_of_slabs_made_one_at_a_time_equal_the_whole_volume_s():
    """A volume of two default slabs (38 + 2 planes of 330 x 330): the slabs handed over one at
    a time give local_mean_residual's means to the bit, for two halves at once."""
    from napari_dvc_correct.engine.slabs import iter_slabs

    rng = np.random.default_rng(5)
    residual = (rng.random((40, 330, 330), np.float32) * 7.3).astype(np.float32)
    residual[rng.random(residual.shape) < 0.05] = np.nan
    field = DisplacementField.zeros((3.0, 5.0, 2.0), (6.0, 25.0, 30.0), (7, 13, 11))
    assert len(list(iter_slabs(residual.shape))) == 2
    means = A.NodeBoxMeans(field, residual.shape, (2, 9))
    for zs in iter_slabs(residual.shape):
        means.add(zs, np.array(residual[zs], np.float64))  # any float dtype, read as float32
    for half, values in zip((2, 9), means.means(), strict=True):
        before = _local_mean_as_before(residual, field, half)
        np.testing.assert_array_equal(values, before)
        np.testing.assert_array_equal(A.local_mean_residual(residual, field, half), before)
