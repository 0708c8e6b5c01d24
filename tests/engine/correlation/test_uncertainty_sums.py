"""The uncertainty's per-voxel sums: the fast (row-folded) paths against the general one."""

import numpy as np
import pytest

from napari_dvc_correct.engine.correlation import uncertainty_sums
from napari_dvc_correct.engine.correlation.interpolation import prefilter


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
    fast = uncertainty_sums.affine_sensitivity_sums(
        coef, g, grad, xi, len(g), float(g.mean()), cz, cy, cx, p
    )
    general = uncertainty_sums.sensitivity_sums(
        coef, g, grad, xi, len(g), float(g.mean()), cz, cy, cx, p, 4
    )
    assert fast[3] == general[3] and fast[3] > 0  # voxels used
    # the fast paths sum interior taps four-wide in float32 (as IC-GN samples), the general one
    # in float64: agreement to float32 rounding
    for a, b in zip(fast[:3] + fast[4:], general[:3] + general[4:]):
        np.testing.assert_allclose(a, b, rtol=2e-6, atol=2e-6 * np.max(np.abs(b)))


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
    fast = uncertainty_sums.quadratic_sensitivity_sums(
        coef, g, grad, xi, len(g), float(g.mean()), cz, cy, cx, p
    )
    general = uncertainty_sums.sensitivity_sums(
        coef, g, grad, xi, len(g), float(g.mean()), cz, cy, cx, p, 10
    )
    assert fast[3] == general[3] and fast[3] > 0  # voxels used
    # the fast paths sum interior taps four-wide in float32 (as IC-GN samples), the general one
    # in float64: agreement to float32 rounding
    for a, b in zip(fast[:3] + fast[4:], general[:3] + general[4:]):
        np.testing.assert_allclose(a, b, rtol=2e-6, atol=2e-6 * np.max(np.abs(b)))
