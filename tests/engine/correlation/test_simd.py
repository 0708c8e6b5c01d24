"""The four-wide LLVM IR kernels (engine/correlation/simd.py) against the scalar sums they replace."""

import numpy as np
from numba import njit

from napari_dvc_correct.engine import synthetic
from napari_dvc_correct.engine.correlation.interpolation import sample_interior
from napari_dvc_correct.engine.correlation.simd_taps import sample_interior_vector
from napari_dvc_correct.engine.fields.field import DisplacementField
from napari_dvc_correct.engine.fields.field_spline import FieldSpline
from napari_dvc_correct.engine.fields.field_spline_kernels import (
    _eval_one_any,
    _eval_one_with_jacobian,
)


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


def test_field_value_and_jacobian_equal_the_scalar_spline():
    rng = np.random.default_rng(1)
    field = DisplacementField.zeros((4.0, 4.0, 4.0), (6.0, 7.0, 8.0), (5, 4, 6))
    band = synthetic.shear_band((14.0, 14.0, 24.0), width=6.0, slip=3.0, shift=(1.0, -0.5, 2.0))
    field.u[:] = synthetic.sample_displacement(band, field.points.reshape(5, 4, 6, 3))
    spline = FieldSpline.from_field(field)
    args = (spline.pad, spline.origin, spline.step, spline.trend_offset, spline.trend_matrix)
    value, jacobian, reference = np.empty(3), np.empty((3, 3)), np.empty(3)
    shifted = np.empty(3)
    h = 1e-5
    for point in rng.uniform(-6.0, 50.0, (300, 3)):  # inside, near and beyond the hull
        _eval_one_with_jacobian(spline.extended, *args, *point, value, jacobian)
        _eval_one_any(spline.coefficients, *args, *point, reference)
        assert np.abs(value - reference).max() < 1e-12
        for a in range(3):
            step = np.zeros(3)
            step[a] = h
            _eval_one_any(spline.coefficients, *args, *(point + step), shifted)
            _eval_one_any(spline.coefficients, *args, *(point - step), reference)
            assert np.abs(jacobian[:, a] - (shifted - reference) / (2 * h)).max() < 1e-6
