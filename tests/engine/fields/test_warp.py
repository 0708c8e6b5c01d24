"""Warping volumes by a field (engine/fields/warp.py): pull-back and forward warp undo a known deformation."""

import numpy as np
import pytest

from napari_dvc_correct.engine import synthetic
from napari_dvc_correct.engine.evaluation import residual
from napari_dvc_correct.engine.fields import warp
from napari_dvc_correct.engine.fields.field import DisplacementField, grid_for_volume

GRADIENT = np.array([[0.05, 0.02, -0.01], [0.0, -0.03, 0.04], [0.02, 0.01, 0.06]])


def test_pull_back_and_forward_warp_undo_a_known_deformation(sheared_pair):
    reference, deformed, field = sheared_pair
    contrast = float(reference.std())
    core = (slice(8, 32),) * 3
    pulled = warp.pull_back(deformed, field)
    assert np.mean(np.abs(pulled - reference)[core]) < 0.01 * contrast
    assert np.mean(np.abs(deformed - reference)[core]) > 0.5 * contrast  # not vacuous
    moved = warp.warp_forward(reference, field, chunk_voxels=5000)
    assert np.mean(np.abs(moved - deformed)[core]) < 0.01 * contrast
    # chunking does not change the result
    assert np.array_equal(moved, warp.warp_forward(reference, field), equal_nan=True)


def test_forward_warp_with_residual_matches_the_separate_calls(sheared_pair):
    reference, deformed, field = sheared_pair
    moved, mean = warp.warp_forward_with_residual(reference, deformed, field, chunk_voxels=4000)
    assert np.array_equal(moved, warp.warp_forward(reference, field), equal_nan=True)
    expected = residual.mean_gray_residual(reference, deformed, field, "loaded")
    assert mean == pytest.approx(expected, rel=1e-6)


def test_forward_warp_with_the_lattice_inverse_equals_newton_at_every_voxel(sheared_pair):
    reference = sheared_pair[0]
    band = synthetic.shear_band((20.0, 20.0, 20.0), width=8.0, slip=4.0, shift=(1.5, -2.0, 2.5))
    origin, step, shape = grid_for_volume(reference.shape, 9, 8)  # node step 8: stride 4
    field = DisplacementField.zeros(origin, step, shape)
    field.u[:] = synthetic.sample_displacement(band, field.points.reshape(*shape, 3))
    fast = warp.warp_forward(reference, field)
    exact = warp.warp_forward(reference, field, accuracy=None)
    # X within the inverse's error of the volume's faces may fall on either side of them
    assert np.mean(np.isnan(fast) != np.isnan(exact)) < 1e-3
    difference = np.abs(fast - exact)[np.isfinite(exact) & np.isfinite(fast)]
    # positions within 1e-3 voxel (1e-2 beyond the hull) of Newton's, gray gradients below 1 / voxel
    assert difference.max() < 1e-2 * np.ptp(reference)
    assert difference.mean() < 1e-4 * np.ptp(reference)
    assert difference.max() > 0  # two different computations
