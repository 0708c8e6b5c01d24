"""The shape functions' algebra: composing warp matrices is composing the warps, to second order."""

import numpy as np

from napari_dvc_correct.engine.correlation import shape_function


def test_warp_matrix_composition_matches_function_composition():
    rng = np.random.default_rng(2)
    p = rng.normal(0, 0.05, 30)
    q = rng.normal(0, 0.05, 30)
    mp = shape_function.warp_matrix(p, 10, shape_function.PRODUCT_TABLE, shape_function.QUAD_AXES)
    mq = shape_function.warp_matrix(q, 10, shape_function.PRODUCT_TABLE, shape_function.QUAD_AXES)
    composed = mp @ mq
    point = np.array([0.3, -0.2, 0.1])

    def apply(params, xi):
        b = np.array(
            [
                1,
                *xi,
                xi[0] ** 2,
                xi[1] ** 2,
                xi[2] ** 2,
                xi[0] * xi[1],
                xi[1] * xi[2],
                xi[0] * xi[2],
            ]
        )
        return xi + params.reshape(3, 10) @ b

    exact = apply(p, apply(q, point))
    b = np.array(
        [
            1,
            *point,
            point[0] ** 2,
            point[1] ** 2,
            point[2] ** 2,
            point[0] * point[1],
            point[1] * point[2],
            point[0] * point[2],
        ]
    )
    approx = (composed @ b)[1:4]
    # truncation at degree 2 only drops terms of degree 3 and 4 in small coordinates
    assert np.max(np.abs(approx - exact)) < 1e-3


def test_displacement_and_gradient_survive_the_parameters_of_either_order():
    u = np.array([[0.5, -1.25, 2.0], [0.0, 0.1, -0.2]])
    gradient = np.stack([np.eye(3) * 0.01, np.full((3, 3), -0.02)])
    for order in (1, 2):
        params = shape_function.displacement_to_params(u, gradient, order)
        assert params.shape == (2, 3 * shape_function.n_monomials(order))
        back_u, back_gradient = shape_function.params_to_displacement(params, order)
        np.testing.assert_allclose(back_u, u)
        np.testing.assert_allclose(back_gradient, gradient)
    assert [shape_function.n_monomials(k) for k in (1, 2)] == [4, 10]
