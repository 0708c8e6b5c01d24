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
