"""Strain on the grid: known answers for eq. 3, affine fields, invalid nodes, anisotropic steps."""

import numpy as np
import pytest

from napari_dvc_correct.engine.evaluation.strain import (
    displacement_gradient,
    equivalent_strain,
    equivalent_strain_field,
    green_lagrange_strain,
    principal_strains,
    small_strain,
    strain_tensor,
)
from napari_dvc_correct.engine.fields.field import DisplacementField, Status
from napari_dvc_correct.engine.synthetic import affine, sample_displacement

GRADIENT = np.array(
    [
        [0.012, -0.004, 0.007],
        [0.003, -0.020, 0.010],
        [-0.006, 0.015, 0.005],
    ]
)


def field_from(function, origin=(4.0, 6.0, 5.0), step=(4.0, 3.0, 5.0), shape=(6, 7, 5)):
    grid = DisplacementField.zeros(origin, step, shape)
    return grid.replace(u=sample_displacement(function, grid.points).reshape((*shape, 3)))


# --- eq. 3 against hand-computed values ---------------------------------------------------------
def test_equivalent_strain_uniaxial_is_two_thirds():
    tensor = np.diag([0.03, 0.0, 0.0])
    assert equivalent_strain(tensor) == pytest.approx(0.02, abs=1e-15)


def test_equivalent_strain_pure_tensor_shear():
    # tensor shear exy = 0.05 (engineering shear 0.1): sqrt(2/9 * 6 * 0.05^2) = 0.1 / sqrt(3)
    tensor = np.zeros((3, 3))
    tensor[1, 2] = tensor[2, 1] = 0.05
    assert equivalent_strain(tensor) == pytest.approx(0.1 / np.sqrt(3.0), abs=1e-15)


def test_equivalent_strain_general_hand_computed():
    # (z, y, x) order: ezz = 0.01, eyy = -0.02, exx = 0.04, ezy = 0.003, eyx = -0.005, ezx = 0.002
    tensor = np.array([[0.01, 0.003, 0.002], [0.003, -0.02, -0.005], [0.002, -0.005, 0.04]])
    # by hand: (exx-eyy)^2 = 0.0036, (eyy-ezz)^2 = 0.0009, (ezz-exx)^2 = 0.0009,
    # 6 (exy^2 + eyz^2 + ezx^2) = 6 (25 + 9 + 4) e-6 = 0.000228; sum = 0.005628
    expected = np.sqrt(2.0 / 9.0 * 0.005628)
    assert equivalent_strain(tensor) == pytest.approx(expected, rel=1e-12)
    assert expected == pytest.approx(0.03536477, rel=1e-6)


def test_equivalent_strain_ignores_volumetric_part_and_keeps_nan():
    tensors = np.stack([0.07 * np.eye(3), np.full((3, 3), np.nan)])
    values = equivalent_strain(tensors)
    assert values[0] == pytest.approx(0.0, abs=1e-15)
    assert np.isnan(values[1])


def test_tensors_and_principal_strains():
    h = np.array([[0.0, 0.2, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.1]])
    eps = small_strain(h)
    assert np.allclose(eps, [[0, 0.1, 0], [0.1, 0, 0], [0, 0, 0.1]])
    e = green_lagrange_strain(h)
    # E = (H + H^T + H^T H)/2; H^T H has (1,1) = 0.04 and (2,2) = 0.01
    assert np.allclose(e, [[0, 0.1, 0], [0.1, 0.02, 0], [0, 0, 0.105]])
    assert np.allclose(principal_strains(eps), [0.1, 0.1, -0.1])
    assert np.isnan(principal_strains(np.full((3, 3), np.nan))).all()
    with pytest.raises(ValueError, match=r"\(\.\.\., 3, 3\)"):
        small_strain(np.zeros((3, 2)))


# --- affine fields are recovered exactly ----------------------------------------------------------
@pytest.mark.parametrize("method", ["central", "least-squares"])
def test_affine_gradient_recovered_with_anisotropic_step(method):
    field = field_from(affine(GRADIENT, center=(10.0, 12.0, 9.0), shift=(1.5, -2.0, 0.5)))
    gradient = displacement_gradient(field, method=method, window=3)
    assert gradient.shape == (6, 7, 5, 3, 3)
    assert np.max(np.abs(gradient - GRADIENT)) < 1e-4
    tensor = strain_tensor(field, measure="green-lagrange", method=method, window=5)
    assert np.max(np.abs(tensor - green_lagrange_strain(GRADIENT))) < 1e-4
    eq = equivalent_strain_field(field, method=method)
    assert np.max(np.abs(eq - equivalent_strain(small_strain(GRADIENT)))) < 1e-4


@pytest.mark.parametrize("method", ["central", "least-squares"])
def test_invalid_nodes_are_nan_and_not_used(method):
    field = field_from(affine(GRADIENT, center=(10.0, 12.0, 9.0)))
    broken = field.u.copy()
    status = field.status.copy()
    for node in [(2, 3, 2), (0, 0, 0), (5, 6, 4), (3, 3, 2)]:
        broken[node] = 1e3  # garbage that must not leak into the neighbours' gradients
        status[node] = Status.DIVERGED
    field = field.replace(u=broken, status=status)
    gradient = displacement_gradient(field, method=method, window=3)
    bad = ~field.valid
    assert np.isnan(gradient[bad]).all()
    assert np.max(np.abs(gradient[~bad] - GRADIENT)) < 1e-4


def test_central_differences_need_two_nodes_along_each_axis():
    field = field_from(affine(GRADIENT, center=(0.0, 0.0, 0.0)), shape=(1, 4, 4))
    gradient = displacement_gradient(field, method="central")
    assert np.isnan(gradient[..., :, 0]).all()  # no z neighbours: d/dz unknown
    assert np.allclose(gradient[..., :, 1:], GRADIENT[:, 1:])


def test_least_squares_smooths_noise_better_than_central_differences():
    rng = np.random.default_rng(3)
    field = field_from(affine(GRADIENT, center=(10.0, 12.0, 9.0)), step=(3, 3, 3), shape=(9, 9, 9))
    noisy = field.replace(u=field.u + rng.normal(0.0, 0.05, field.u.shape))
    error_central = np.nanstd(displacement_gradient(noisy, "central") - GRADIENT)
    error_lsq = np.nanstd(displacement_gradient(noisy, "least-squares", window=5) - GRADIENT)
    assert error_lsq < 0.5 * error_central


def test_shape_function_gradient_and_errors():
    field = field_from(affine(GRADIENT, center=(0.0, 0.0, 0.0)))
    with pytest.raises(ValueError, match="no shape-function gradient"):
        displacement_gradient(field, method="shape-function")
    given = np.broadcast_to(GRADIENT, (*field.shape, 3, 3)).copy()
    status = field.status.copy()
    status[1, 1, 1] = Status.OUT_OF_BOUNDS
    with_gradient = field.replace(gradient=given, status=status)
    out = displacement_gradient(with_gradient, method="shape-function")
    assert np.isnan(out[1, 1, 1]).all() and np.allclose(out[0, 0, 0], GRADIENT)
    with pytest.raises(ValueError, match="unknown gradient method"):
        displacement_gradient(field, method="spline")
    with pytest.raises(ValueError, match="odd number of nodes"):
        displacement_gradient(field, method="least-squares", window=4)
    with pytest.raises(ValueError, match="unknown strain measure"):
        strain_tensor(field, measure="log")
