"""The sensitivity pass of the uncertainty estimate: the first-order fast path against the general one."""

import numpy as np
import pytest

from napari_dvc_correct.engine import icgn_uncertainty
from napari_dvc_correct.engine.interpolation import prefilter


@pytest.mark.parametrize("center", [(12, 12, 12), (4, 5, 19)])  # inside; taps past the border
def test_first_order_sensitivity_sums_equal_the_general_ones(center):
    rng = np.random.default_rng(1)
    coef = prefilter(rng.standard_normal((24, 24, 24)).astype(np.float32))
    half = 3
    axes = np.arange(-half, half + 1)
    xi = np.stack(np.meshgrid(axes, axes, axes, indexing="ij"), -1).reshape(-1, 3)
    xi = xi[rng.random(len(xi)) > 0.1].astype(np.float32)  # masked voxels: ragged rows
    g = rng.standard_normal(len(xi)).astype(np.float32)
    grad = rng.standard_normal((len(xi), 3)).astype(np.float32)
    p = np.zeros(12)
    p[[0, 4, 8]] = (0.37, -0.81, 1.26)
    p[[1, 2, 3, 5, 6, 7, 9, 10, 11]] = 0.01 * rng.standard_normal(9)
    cz, cy, cx = center
    fast = icgn_uncertainty._affine_sensitivity_sums(
        coef, g, grad, xi, len(g), float(g.mean()), cz, cy, cx, p
    )
    general = icgn_uncertainty._sensitivity_sums(
        coef, g, grad, xi, len(g), float(g.mean()), cz, cy, cx, p, 4
    )
    assert fast[3] == general[3] and fast[3] > 0  # voxels used
    for a, b in zip(fast[:3] + fast[4:], general[:3] + general[4:]):
        np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-9 * np.max(np.abs(b)))


@pytest.mark.parametrize("order", [1, 2])
def test_subvolume_moments_equal_the_full_statistics(order):
    """The noise stage's plain sums give the variance and gradient power of the full pass."""
    from napari_dvc_correct.engine import icgn_reference, shape_function

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


@pytest.mark.parametrize("center", [(12, 12, 12), (4, 5, 19)])  # inside; taps past the border
def test_second_order_sensitivity_sums_equal_the_general_ones(center):
    rng = np.random.default_rng(3)
    coef = prefilter(rng.standard_normal((24, 24, 24)).astype(np.float32))
    half = 4
    axes = np.arange(-half, half + 1)
    xi = np.stack(np.meshgrid(axes, axes, axes, indexing="ij"), -1).reshape(-1, 3)
    xi = xi[rng.random(len(xi)) > 0.1].astype(np.float32)  # masked voxels: ragged rows
    g = rng.standard_normal(len(xi)).astype(np.float32)
    grad = rng.standard_normal((len(xi), 3)).astype(np.float32)
    p = 0.005 * rng.standard_normal(30)
    p[[0, 10, 20]] = (0.37, -0.81, 1.26)
    cz, cy, cx = center
    fast = icgn_uncertainty._quadratic_sensitivity_sums(
        coef, g, grad, xi, len(g), float(g.mean()), cz, cy, cx, p
    )
    general = icgn_uncertainty._sensitivity_sums(
        coef, g, grad, xi, len(g), float(g.mean()), cz, cy, cx, p, 10
    )
    assert fast[3] == general[3] and fast[3] > 0  # voxels used
    for a, b in zip(fast[:3] + fast[4:], general[:3] + general[4:]):
        np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-9 * np.max(np.abs(b)))


def test_second_order_reference_terms_equal_the_general_ones():
    from napari_dvc_correct.engine import icgn_reference

    rng = np.random.default_rng(4)
    half = 4
    axes = np.arange(-half, half + 1)
    xi = np.stack(np.meshgrid(axes, axes, axes, indexing="ij"), -1).reshape(-1, 3)
    xi = xi[rng.random(len(xi)) > 0.1].astype(np.float32)  # masked voxels: ragged rows
    g = (50.0 + rng.standard_normal(len(xi))).astype(np.float32)
    grad = rng.standard_normal((len(xi), 3)).astype(np.float32)
    fast = icgn_uncertainty._quadratic_reference_terms(g, grad, xi, len(g))
    general = icgn_reference.reference_terms(g, grad, xi, len(g), 10)
    assert fast[2] and general[2]  # Cholesky succeeded in both
    for a, b in zip(fast[:2] + fast[3:], general[:2] + general[3:]):
        np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-9 * np.max(np.abs(b)))
