"""The field spline's numba kernels: four-lane value and Jacobian against the scalar spline."""

import numpy as np

from napari_dvc_correct.engine import synthetic
from napari_dvc_correct.engine.fields.field import DisplacementField
from napari_dvc_correct.engine.fields.field_spline import FieldSpline
from napari_dvc_correct.engine.fields.field_spline_kernels import (
    _eval_one_any,
    _eval_one_with_jacobian,
)


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
