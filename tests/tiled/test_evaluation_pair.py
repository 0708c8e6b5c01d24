"""The pair's map and r0 block by block (tiled/evaluation_pair.py); the whole evaluation's
equality with the in-memory one is tested in test_evaluation.py."""

from __future__ import annotations

import numpy as np
import pytest

from napari_dvc_correct.tiled.evaluation_pair import region_block


class _Lazy:
    def __init__(self, values):
        self.values = values

    def read_region(self, block):
        return self.values[block]


def test_the_region_of_a_block_is_read_from_an_array_or_a_lazy_volume():
    region = np.zeros((4, 5, 6), np.uint8)
    region[1:3, 2:4, :] = 1
    block = (slice(1, 4), slice(0, 5), slice(2, 6))
    expected = region[block] != 0
    assert region_block(None, block) is None
    assert np.array_equal(region_block(region, block), expected)
    assert np.array_equal(region_block(_Lazy(region), block), expected)
    assert region_block(region, block).dtype == bool


def test_the_noise_correlation_and_the_estimate_block_by_block_equal_in_memory():
    """Correlated noise (white noise smoothed by 0.8 voxel): the pair's measured correlation, its
    window factors and the error estimate with its resolution are the in-memory ones (to the
    float32 prefilter's rounding, test_evaluation.py)."""
    from scipy import ndimage

    from napari_dvc_correct.engine.evaluation.accuracy import evaluate_fields
    from napari_dvc_correct.engine.fields.field import DisplacementField, grid_for_volume
    from napari_dvc_correct.engine.synthetic import (
        affine,
        deform_volume,
        sample_displacement,
        two_phase_volume,
    )
    from napari_dvc_correct.tiled.evaluation import evaluate_tiled

    shape = (40, 44, 48)

    def noise(seed):
        n = ndimage.gaussian_filter(np.random.default_rng(seed).standard_normal(shape), 0.8)
        return (3.0 * n / n.std()).astype(np.float32)

    clean = two_phase_volume(shape, seed=4)
    truth = affine(np.zeros((3, 3)), center=(20.0, 22.0, 24.0), shift=(1.3, -0.7, 2.1))
    reference = (clean + noise(5)).astype(np.float32)
    deformed = (deform_volume(clean, truth) + noise(6)).astype(np.float32)
    origin, step, grid = grid_for_volume(shape, 11, 6)
    base = DisplacementField.zeros(origin, step, grid)
    fields = {"exact": base.replace(u=sample_displacement(truth, base.points).reshape((*grid, 3)))}
    memory = evaluate_fields(reference, deformed, fields)
    tiled = evaluate_tiled(reference, deformed, fields, block_shape=(16, 24, 20))
    ours, theirs = memory.pair.noise_correlation, tiled.pair.noise_correlation
    assert ours.along(0)[0] > 0.4  # measured correlated
    np.testing.assert_allclose(theirs.rho, ours.rho, atol=1e-6)
    assert theirs.factors == pytest.approx(ours.factors, rel=1e-6)
    for x, y in zip(memory.fields, tiled.fields):
        np.testing.assert_allclose(y.error_estimate, x.error_estimate, rtol=1e-5, atol=1e-7)
        np.testing.assert_allclose(y.error_resolution, x.error_resolution, rtol=1e-5, atol=1e-7)
