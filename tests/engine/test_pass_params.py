"""How the correcting matches are parametrised (engine/pass_params.py), on fields with a known curvature."""

import numpy as np
import pytest

from napari_dvc_correct.engine import synthetic
from napari_dvc_correct.engine.field import DisplacementField, grid_for_volume
from napari_dvc_correct.engine.params import CorrelationParams
from napari_dvc_correct.engine.pass_params import (
    MIN_PASS_SUBVOLUME,
    correction_params,
    field_curvature,
    pass_order,
)


def test_second_order_passes_where_the_field_bends_inside_a_subvolume():
    params = CorrelationParams(subvolume=21, step=6)
    origin, step, shape = grid_for_volume((64, 64, 64), 21, 6)
    field = DisplacementField.zeros(origin, step, shape)
    points = field.points.reshape(*shape, 3)
    gradient = np.array([[0.02, 0.01, 0.0], [0.0, -0.015, 0.01], [0.01, 0.0, 0.02]])
    field.u[:] = synthetic.sample_displacement(synthetic.affine(gradient, (32,) * 3), points)
    assert field_curvature(field, params.half) < 1e-9
    assert pass_order(field, params) == 1
    # u_z = a x^2: u'' = 2a, so a first-order subvolume misses a M^2 (0.2 voxel here)
    a = 0.002
    field.u[..., 0] += a * (points[..., 2] - 32.0) ** 2
    assert field_curvature(field, params.half) == pytest.approx(a * params.half**2, rel=0.15)
    assert pass_order(field, params) == 2
    assert pass_order(field.copy(), params.replace(order=2)) == 2


def test_bending_fields_are_corrected_with_smaller_second_order_subvolumes():
    params = CorrelationParams(subvolume=21, step=6)
    origin, step, shape = grid_for_volume((64, 64, 64), 21, 6)
    field = DisplacementField.zeros(origin, step, shape)
    assert correction_params(field, params) == params  # a flat field: the paper's rule
    points = field.points.reshape(*shape, 3)
    field.u[..., 0] = 0.004 * (points[..., 2] - 32.0) ** 2
    chosen = correction_params(field, params)
    assert chosen.order == 2 and chosen.subvolume == 15  # 2/3 of the half-size, odd
    small = correction_params(field, CorrelationParams(subvolume=11, step=6))
    assert small.subvolume == MIN_PASS_SUBVOLUME == 11
