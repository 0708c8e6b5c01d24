"""Warping volumes by a field (engine/warp.py): pull-back and forward warp undo a known deformation."""

import numpy as np
import pytest

from napari_dvc_correct.engine import residual, warp

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
