"""Gray residuals (engine/evaluation/residual.py): small for the true field, NaN where undefined, one warp for both."""

import numpy as np
import pytest

from napari_dvc_correct.engine.evaluation import residual
from napari_dvc_correct.engine.fields import field_spline, warp

GRADIENT = np.array([[0.05, 0.02, -0.01], [0.0, -0.03, 0.04], [0.02, 0.01, 0.06]])


def test_gray_residual_is_small_for_the_true_field_and_nan_where_undefined(sheared_pair):
    reference, deformed, field = sheared_pair
    contrast = float(reference.std())
    zero = field.replace(u=np.zeros_like(field.u))
    for mode in ("reference", "loaded"):
        volume = residual.gray_residual(reference, deformed, field, mode)
        assert volume.dtype == np.float32 and volume.shape == reference.shape
        z, y, x = field_spline.FieldSpline.from_field(field).hull_slices(reference.shape)
        outside = np.ones(reference.shape, bool)
        outside[z, y, x] = False
        if mode == "reference":
            assert np.all(np.isnan(volume[outside]))
        mean = residual.mean_gray_residual(reference, deformed, field, mode, chunk_voxels=3000)
        assert mean == pytest.approx(float(np.nanmean(volume)), rel=1e-5)
        wrong = residual.mean_gray_residual(reference, deformed, zero, mode)
        assert mean < 0.02 * wrong
    in_hull = residual.gray_residual(reference, deformed, field)
    everywhere = residual.gray_residual(reference, deformed, field, region="volume")
    assert np.isfinite(everywhere).mean() > np.isfinite(in_hull).mean() + 0.2
    assert np.nanmean(everywhere) < 0.05 * contrast
    with pytest.raises(ValueError, match="mode"):
        residual.gray_residual(reference, deformed, field, mode="sideways")


@pytest.mark.parametrize("mode", ["reference", "loaded"])
def test_moved_and_residual_equal_the_separate_warp_and_residual(sheared_pair, mode):
    reference, deformed, field = sheared_pair
    moved, residual_volume = residual.moved_and_residual(
        reference, deformed, field, mode, chunk_voxels=5000
    )
    if mode == "reference":
        expected_moved = warp.pull_back(deformed, field, outside="nan")
    else:
        expected_moved = warp.warp_forward(reference, field, outside="nan")
    assert np.array_equal(moved, expected_moved, equal_nan=True)
    expected = residual.gray_residual(reference, deformed, field, mode)
    assert np.array_equal(residual_volume, expected, equal_nan=True)
    assert np.isfinite(residual_volume).mean() > 0.25  # the grid's hull, a third of this volume
