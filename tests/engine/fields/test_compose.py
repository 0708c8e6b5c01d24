"""Composition of displacement fields (engine/fields/compose.py) against closed forms."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from napari_dvc_correct.engine import synthetic
from napari_dvc_correct.engine.fields.compose import compose
from napari_dvc_correct.engine.fields.field import DisplacementField, Provenance, Status

ORIGIN, STEP, SHAPE = (10.0, 10.0, 10.0), (6.0, 6.0, 6.0), (9, 9, 9)
A1 = np.array([[0.06, 0.02, -0.01], [0.01, -0.04, 0.03], [0.02, 0.015, 0.05]])
A2 = np.array([[-0.03, 0.01, 0.02], [0.04, 0.05, -0.02], [0.0, -0.03, 0.04]])
C1, S1 = np.array([30.0, 32.0, 28.0]), np.array([3.0, -2.0, 5.0])
C2, S2 = np.array([35.0, 30.0, 31.0]), np.array([-4.0, 6.0, 2.0])


def _grid_field(function, gradient=None):
    field = DisplacementField.zeros(ORIGIN, STEP, SHAPE)
    field.u[:] = synthetic.sample_displacement(function, field.points.reshape(*SHAPE, 3))
    if gradient is not None:
        field.gradient = np.broadcast_to(gradient, (*SHAPE, 3, 3)).copy()
    return field


def test_two_affine_steps_compose_to_their_product():
    first = _grid_field(synthetic.affine(A1, C1, S1), A1)
    second = _grid_field(synthetic.affine(A2, C2, S2), A2)
    total = compose(first, second)
    X = first.points
    # closed form: x = X + a(X); x' = x + b(x)
    x = X + S1 + (X - C1) @ A1.T
    expected = x + S2 + (x - C2) @ A2.T - X
    error = np.abs(total.displacement - expected).max()
    assert error < 1e-3
    assert error < 1e-8  # affine fields are exact in the spline, not just within 1e-3
    # the plain sum misses the cross term A2 @ a(X) by tenths of a voxel: the test tells them apart
    summed = compose(first, second, mode="sum")
    assert np.abs(summed.displacement - expected).max() > 0.3
    assert np.allclose(total.gradient, A1 + A2 @ (np.eye(3) + A1))
    assert np.allclose(summed.gradient, A1 + A2)


def test_sum_is_exact_for_a_uniform_second_step_and_needs_one_grid():
    first = _grid_field(synthetic.shear_band((34.0, 34.0, 34.0), width=8.0, slip=6.0))
    second = _grid_field(synthetic.translation((0.5, -1.0, 2.0)))
    assert np.allclose(compose(first, second).u, compose(first, second, mode="sum").u)
    other = DisplacementField.zeros((0.0, 0.0, 0.0), STEP, SHAPE)
    with pytest.raises(ValueError, match="same grid"):
        compose(first, other, mode="sum")
    with pytest.raises(ValueError, match="mode"):
        compose(first, second, mode="product")


def test_zero_fields_are_neutral():
    band = _grid_field(synthetic.shear_band((34.0, 34.0, 34.0), width=8.0, slip=6.0))
    zero = DisplacementField.zeros(ORIGIN, STEP, SHAPE)
    assert np.allclose(compose(band, zero).u, band.u)
    assert np.allclose(compose(zero, band).u, band.u)


@settings(max_examples=25, deadline=None)
@given(
    st.lists(st.floats(-10, 10), min_size=3, max_size=3),
    st.lists(st.floats(-10, 10), min_size=3, max_size=3),
)
def test_translations_add(first_shift, second_shift):
    first = _grid_field(synthetic.translation(first_shift))
    second = _grid_field(synthetic.translation(second_shift))
    assert np.allclose(compose(first, second).u, np.add(first_shift, second_shift), atol=1e-9)


def test_quality_arrays_keep_the_worst_news():
    first = _grid_field(synthetic.translation((1.0, 0.0, 0.0)))
    second = _grid_field(synthetic.translation((0.0, 1.0, 0.0)))
    first.zncc[:] = 0.9
    second.zncc[:] = 0.95
    first.status[0, 0, 0] = Status.DIVERGED
    first.provenance[0, 0, 0] = Provenance.REPLACED
    second.zncc[4, 4, 4] = 0.6
    second.provenance[4, 4, 4] = Provenance.CORRECTED
    total = compose(first, second)
    assert total.status[0, 0, 0] == Status.DIVERGED
    assert total.provenance[0, 0, 0] == Provenance.REPLACED
    assert total.zncc[1, 1, 1] == pytest.approx(0.9)
    # node (4, 4, 4) moves by one sixth of a step: second's node (4, 4, 4) is the nearest
    assert total.zncc[4, 4, 4] == pytest.approx(0.6)
    assert total.provenance[4, 4, 4] == Provenance.CORRECTED
    assert total.metadata["composition"]["mode"] == "exact"
    # a hole in the first field stays a hole, a hole in the second is refused
    first.u[1, 1, 1] = np.nan
    assert np.isnan(compose(first, second).u[1, 1, 1]).all()
    with pytest.raises(ValueError, match="clean"):
        compose(second, first)


def test_uncertainties_add_in_quadrature():
    first = _grid_field(synthetic.translation((1.0, 0.0, 0.0)))
    second = _grid_field(synthetic.translation((0.0, 0.5, 0.0)))
    assert compose(first, second).uncertainty is None
    first.uncertainty = np.full((*first.shape, 3), 0.03)
    second.uncertainty = np.full((*second.shape, 3), 0.04)
    for mode in ("exact", "sum"):
        np.testing.assert_allclose(compose(first, second, mode=mode).uncertainty, 0.05)
