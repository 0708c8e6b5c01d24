"""The uncertainty estimate's noise-stage kernel against the full pass."""

import numpy as np
import pytest

from napari_dvc_correct.engine.correlation import icgn_uncertainty
from napari_dvc_correct.engine.correlation.interpolation import prefilter


@pytest.mark.parametrize("order", [1, 2])
def test_subvolume_moments_equal_the_full_statistics(order):
    """The noise stage's plain sums give the variance and gradient power of the full pass."""
    from napari_dvc_correct.engine.correlation import icgn_reference, shape_function

    rng = np.random.default_rng(2)
    reference = (100.0 + 10.0 * rng.standard_normal((20, 20, 20))).astype(np.float32)
    gradient = icgn_reference.gradient_volume(prefilter(reference))
    mask = rng.random(reference.shape) > 0.2  # masked voxels left out of both
    mask[:, :, :7] = False  # a POI with too few voxels: NaN in both
    nb = shape_function.n_monomials(order)
    half = 3
    centers = np.array([[10, 10, 10], [5, 14, 12], [14, 5, 8], [10, 10, 3]], np.int64)
    n = len(centers)
    variance, power = np.empty(n), np.empty(n)
    icgn_uncertainty.subvolume_moments(
        reference, gradient, mask, True, centers, half, nb, variance, power
    )
    full = (np.empty(n), np.empty(n), np.empty((n, 3)))
    icgn_uncertainty.subvolume_statistics(
        reference,
        gradient,
        prefilter(reference),
        mask,
        True,
        centers,
        half,
        nb,
        np.zeros((n, 3 * nb)),
        np.full(n, 0.9),
        np.zeros(n, bool),
        *full,
    )
    assert np.all(np.isnan(variance[3:])) and np.all(np.isnan(full[0][3:]))
    assert np.all(np.isnan(power[3:]))
    # the same sums up to float64 rounding (first order: summed by rows there)
    np.testing.assert_allclose(variance[:3], full[0][:3], rtol=1e-12)
    np.testing.assert_allclose(power[:3], full[1][:3], rtol=1e-12)  # there: diag of L Lᵀ
    window = reference[
        5 - half : 5 + half + 1, 14 - half : 14 + half + 1, 12 - half : 12 + half + 1
    ]
    inside = mask[5 - half : 5 + half + 1, 14 - half : 14 + half + 1, 12 - half : 12 + half + 1]
    np.testing.assert_allclose(variance[1], np.var(window[inside].astype(np.float64)), rtol=1e-12)
