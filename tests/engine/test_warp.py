"""Warping volumes by a field (engine/warp.py): pull-back and forward warp undo a known deformation."""

import numpy as np
import pytest

from napari_dvc_correct.engine import residual, synthetic, warp
from napari_dvc_correct.engine.field import DisplacementField, grid_for_volume

GRADIENT = np.array([[0.05, 0.02, -0.01], [0.0, -0.03, 0.04], [0.02, 0.01, 0.06]])


@pytest.fixture(scope="module")
def pair():
    reference = synthetic.textured_volume((40, 40, 40), 2.0, seed=3)
    band = synthetic.shear_band((20.0, 20.0, 20.0), width=7.0, slip=6.0, shift=(1.5, -2.0, 2.5))
    deformed = synthetic.deform_volume(reference, band)
    origin, step, shape = grid_for_volume(reference.shape, 9, 3)
    field = DisplacementField.zeros(origin, step, shape)
    field.u[:] = synthetic.sample_displacement(band, field.points.reshape(*shape, 3))
    return reference, deformed, field


def test_pull_back_and_forward_warp_undo_a_known_deformation(pair):
    reference, deformed, field = pair
    contrast = float(reference.std())
    core = (slice(8, 32),) * 3
    pulled = warp.pull_back(deformed, field)
    assert np.mean(np.abs(pulled - reference)[core]) < 0.01 * contrast
    assert np.mean(np.abs(deformed - reference)[core]) > 0.5 * contrast  # not vacuous
    moved = warp.warp_forward(reference, field, chunk_voxels=5000)
    assert np.mean(np.abs(moved - deformed)[core]) < 0.01 * contrast
    # chunking does not change the result
    assert np.array_equal(moved, warp.warp_forward(reference, field), equal_nan=True)


def test_forward_warp_with_residual_matches_the_separate_calls(pair):
    reference, deformed, field = pair
    moved, mean = warp.warp_forward_with_residual(reference, deformed, field, chunk_voxels=4000)
    assert np.array_equal(moved, warp.warp_forward(reference, field), equal_nan=True)
    expected = residual.mean_gray_residual(reference, deformed, field, "loaded")
    assert mean == pytest.approx(expected, rel=1e-6)
