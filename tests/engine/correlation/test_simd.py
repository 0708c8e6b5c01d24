"""The four-wide LLVM IR kernels (engine/correlation/simd.py) against the scalar sums they replace."""

import numpy as np
from numba import njit

from napari_dvc_correct.engine.correlation.interpolation import sample_interior
from napari_dvc_correct.engine.correlation.simd import field_taps, field_taps_with_gradient
from napari_dvc_correct.engine.correlation.simd_taps import sample_interior_vector


@njit
def _both_samplers(coefficients, points):
    flat = coefficients.reshape(-1)
    ny, nx = coefficients.shape[1], coefficients.shape[2]
    out = np.empty((points.shape[0], 2), np.float32)
    for i in range(points.shape[0]):
        z, y, x = points[i, 0], points[i, 1], points[i, 2]
        out[i, 0] = sample_interior_vector(flat, ny * nx, nx, z, y, x)
        out[i, 1] = sample_interior(coefficients, z, y, x)
    return out


def test_bspline_value_equals_the_scalar_sample_to_float32_rounding():
    rng = np.random.default_rng(0)
    coefficients = (100.0 + rng.standard_normal((12, 13, 14))).astype(np.float32)
    points = rng.uniform(1.0, 9.999, (2000, 3))  # interior: all 64 taps inside
    out = _both_samplers(coefficients, points)
    assert np.abs(out[:, 0] - out[:, 1]).max() < 1e-6 * 100.0 * 4
    # a tap's coefficient moved moves the sample by its weight: every tap is read
    base = _both_samplers(coefficients, np.array([[5.25, 6.5, 7.75]]))[0, 0]
    changed = coefficients.copy()
    changed[4 + 3, 5 + 3, 6 + 3] += 1.0  # the last tap of (5.25, 6.5, 7.75)
    moved = _both_samplers(changed, np.array([[5.25, 6.5, 7.75]]))[0, 0]
    expected = (0.25**3 / 6) * (0.5**3 / 6) * (0.75**3 / 6)
    assert abs((moved - base) - expected) < 2e-5


# --- the field spline's four-wide tap sums (simd.field_taps), against einsum ---------------------
@njit
def _field_sums(coefficients, z0, y0, x0, wz, wy, wx, dz, dy, dx):
    _, nz, ny, nx = coefficients.shape
    row, plane, component = np.uint64(nx), np.uint64(ny * nx), np.uint64(nz * ny * nx)
    first = np.uint64((z0 * ny + y0) * nx + x0)
    values = field_taps(coefficients, first, row, plane, component, wz, wy, wx)
    both = field_taps_with_gradient(
        coefficients, first, row, plane, component, wz, wy, wx, dz, dy, dx
    )
    return values, both


def test_field_taps_are_the_weighted_sums_of_the_4x4x4_taps_of_each_component():
    rng = np.random.default_rng(5)
    coefficients = rng.standard_normal((3, 7, 8, 9))
    wz, wy, wx, dz, dy, dx = (tuple(rng.uniform(-1, 1, 4)) for _ in range(6))
    values, both = _field_sums(coefficients, 2, 1, 3, wz, wy, wx, dz, dy, dx)
    taps = coefficients[:, 2:6, 1:5, 3:7]

    def weighted(a, b, c):
        return np.einsum("kabc,a,b,c->k", taps, np.array(a), np.array(b), np.array(c))

    np.testing.assert_allclose(values, weighted(wz, wy, wx), rtol=1e-12)
    np.testing.assert_allclose(both[:3], values, rtol=1e-12)
    np.testing.assert_allclose(both[3:6], weighted(dz, wy, wx), rtol=1e-12)  # d/dz
    np.testing.assert_allclose(both[6:9], weighted(wz, dy, wx), rtol=1e-12)  # d/dy
    np.testing.assert_allclose(both[9:12], weighted(wz, wy, dx), rtol=1e-12)  # d/dx
