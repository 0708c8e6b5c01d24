"""The weighted reference pass equals the dense sums it folds, for both weights at once."""

import numpy as np
import pytest

from napari_dvc_correct.engine.correlation.icgn_weighted_moments import (
    weighted_reference_moments,
)
from napari_dvc_correct.engine.correlation.shape_function import monomials


def _box(half):
    xi = np.array(np.meshgrid(*[np.arange(-half, half + 1)] * 3, indexing="ij"), np.float32)
    return xi.reshape(3, -1).T.copy()


def _dense(g, grad, xi, w, nb):
    """The same quantities from the steepest-descent images written out (count × 3·nb)."""
    count = len(g)
    b = np.empty((count, 10))
    for i in range(count):
        monomials(float(xi[i, 0]), float(xi[i, 1]), float(xi[i, 2]), nb, b[i])
    jac = np.einsum("ik,ij->ikj", grad.astype(np.float64), b[:, :nb]).reshape(count, -1)
    g = g.astype(np.float64)
    mean_g = np.sum(w * g) / np.sum(w)
    dg = g - mean_g
    w2 = w * w
    power = np.sum(w[:, None] * grad.astype(np.float64) ** 2) / np.sum(w)
    return (
        mean_g, np.sum(w * dg**2), np.sum(w), np.sum(w2), np.sum(w2 * dg), np.sum(w2 * dg**2),
        power, jac.T @ (w[:, None] * jac), jac.T @ (w2[:, None] * jac), jac.T @ w,
        jac.T @ (w * dg), jac.T @ w2, jac.T @ (w2 * dg),
    )  # fmt: skip


@pytest.mark.parametrize("nb", [4, 10])
def test_one_pass_gives_both_hessians_and_the_squared_weight_sums(nb):
    """Random gray levels, gradients and weights on a 7³ box: every return equals the dense
    sum to float64 rounding (1e-10 relative; the folded moments only reorder the sums)."""
    rng = np.random.default_rng(1)
    xi = _box(3)
    count = len(xi)
    g = rng.random(count).astype(np.float32)
    grad = rng.normal(size=(count, 3)).astype(np.float32)
    w = rng.random(count)
    found = weighted_reference_moments(g, grad, xi, w, count, nb)
    for got, want in zip(found, _dense(g, grad, xi, w, nb), strict=True):
        np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-10)


def test_the_squared_weight_terms_of_unit_weights():
    """``W₂ = n``, ``Σ w² (g − ḡ) = 0``, ``H₂ = H₁`` and the power is the plain mean for unit
    weights."""
    rng = np.random.default_rng(1)
    xi = _box(1)
    count = len(xi)
    g = rng.random(count).astype(np.float32)
    grad = rng.random((count, 3)).astype(np.float32)
    mean_g = float(np.mean(g.astype(np.float64)))
    found = weighted_reference_moments(g, grad, xi, np.ones(count), count, 4)
    _, _, _, total2, w2d, w2dd, power, h1, h2, _, _, s2j, _ = found
    assert total2 == count and abs(w2d) < 1e-12
    np.testing.assert_array_equal(h2, h1)
    np.testing.assert_allclose(w2dd, np.sum((g - mean_g) ** 2), rtol=1e-6)
    np.testing.assert_allclose(s2j[[0, 4, 8]], grad.astype(np.float64).sum(axis=0), rtol=1e-12)
    np.testing.assert_allclose(power, np.mean(np.sum(grad.astype(np.float64) ** 2, 1)))


def test_weights_outside_the_row_order_are_summed_row_by_row():
    """A subvolume cut to scattered voxels (rows of unequal length, as after dropping voxels
    that left ``F``) still gives the dense sums."""
    rng = np.random.default_rng(2)
    xi = _box(3)
    keep = rng.random(len(xi)) < 0.6
    xi = xi[keep].copy()
    count = len(xi)
    g = rng.random(count).astype(np.float32)
    grad = rng.normal(size=(count, 3)).astype(np.float32)
    w = rng.random(count)
    found = weighted_reference_moments(g, grad, xi, w, count, 10)
    for got, want in zip(found, _dense(g, grad, xi, w, 10), strict=True):
        np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-10)
