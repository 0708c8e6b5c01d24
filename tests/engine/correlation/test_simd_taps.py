"""The tricubic tap sum as four-lane vector code against the scalar path and finite differences."""

import numpy as np
import pytest
from numba import njit
from scipy import ndimage

from napari_dvc_correct.engine.correlation.interpolation import (
    prefilter,
    sample_interior,
    sample_with_gradient_point,
)
from napari_dvc_correct.engine.correlation.simd_taps import (
    sample_interior_vector,
    sample_with_gradient_interior_vector,
)
from napari_dvc_correct.engine.synthetic import textured_volume


@pytest.fixture(scope="module")
def volume():
    return textured_volume((20, 23, 26), feature_size=1.5, seed=3)


def test_vector_tap_sum_equals_the_scalar_path_to_float32_rounding(volume):
    """The 4-lane tap sum of the IC-GN pass against the scalar 64-tap sum and scipy."""
    coefficients = prefilter(volume)
    rng = np.random.default_rng(2)
    upper = np.array(volume.shape) - 2.0 - 1e-9
    points = 1.0 + rng.uniform(0, 1, (5000, 3)) * (upper - 1.0)
    points[:20] = np.floor(points[:20])  # integer positions: t = 0 exactly
    points[20] = upper  # the last interior position on every axis
    out = np.empty((len(points), 2))
    _interior_both_ways(coefficients, points, out)
    scale = np.abs(volume).max()
    # float32 sums of 64 terms: a few units of float32 rounding of the volume's magnitude
    assert np.max(np.abs(out[:, 1] - out[:, 0])) < 4e-6 * scale
    expected = ndimage.map_coordinates(volume.astype(np.float64), points.T, order=3, mode="mirror")
    assert np.max(np.abs(out[:, 1] - expected)) < 1e-5 * max(scale, 1.0)
    assert np.max(np.abs(out[:20, 1] - volume[tuple(points[:20].astype(int).T)])) < 1e-5 * scale


def test_vector_value_and_gradient_equal_the_scalar_path_and_finite_differences(volume):
    coefficients = prefilter(volume)
    rng = np.random.default_rng(7)
    upper = np.array(volume.shape) - 2.0 - 1e-9
    points = 1.0 + rng.uniform(0, 1, (3000, 3)) * (upper - 1.0)
    points[:10] = np.floor(points[:10])
    out = np.empty((len(points), 8))
    _gradient_both_ways(coefficients, points, out)
    scale = np.abs(out[:, :4]).max(axis=0)
    for k in range(4):  # value, d/dz, d/dy, d/dx
        assert np.max(np.abs(out[:, 4 + k] - out[:, k])) < 4e-6 * scale[k], k
    h = 1e-4
    for axis in range(3):  # the known answer: scipy's cubic spline, central differences
        step = np.zeros(3)
        step[axis] = h
        up, down = (
            ndimage.map_coordinates(
                volume.astype(np.float64), (points + s * step).T, order=3, mode="mirror"
            )  # fmt: skip
            for s in (1.0, -1.0)
        )
        numeric = (up - down) / (2 * h)
        assert np.max(np.abs(out[:, 5 + axis] - numeric)) < 1e-4 * scale[1 + axis], axis


@njit
def _interior_both_ways(coefficients, points, out):
    flat = coefficients.reshape(coefficients.size)
    _, ny, nx = coefficients.shape
    for i in range(points.shape[0]):
        z, y, x = points[i, 0], points[i, 1], points[i, 2]
        out[i, 0] = sample_interior(coefficients, z, y, x)
        out[i, 1] = sample_interior_vector(flat, ny * nx, nx, z, y, x)


@njit
def _gradient_both_ways(coefficients, points, out):
    flat = coefficients.reshape(coefficients.size)
    ny, nx = coefficients.shape[1], coefficients.shape[2]
    for i in range(points.shape[0]):
        z, y, x = points[i, 0], points[i, 1], points[i, 2]
        scalar = sample_with_gradient_point(coefficients, z, y, x)
        vector = sample_with_gradient_interior_vector(flat, ny * nx, nx, z, y, x)
        for k in range(4):
            out[i, k] = scalar[k]
            out[i, 4 + k] = vector[k]
