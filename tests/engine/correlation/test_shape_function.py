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


def test_inverse_rows_are_compose_inverse_rows_to_the_bit():
    """The uncertainty's rows of ``A⁻¹`` equal ``compose_inverse(I, A)``'s bit for bit, and
    are the inverse's rows (a pivoting, non-symmetric, an SPD and a nearly singular
    matrix)."""
    rng = np.random.default_rng(3)
    n = 30
    spd = rng.normal(size=(n, n))
    spd = spd @ spd.T + n * np.eye(n)
    general = rng.normal(size=(n, n))  # pivots on most columns
    permuted = np.eye(n)[rng.permutation(n)] * rng.uniform(0.5, 2.0, n)
    near_singular = spd.copy()  # (an exactly zero pivot raises in both, as numba divides)
    near_singular[5] = near_singular[7] * (1.0 + 1e-12)
    rows = np.array([0, 10, 20])
    for matrix in (spd, general, permuted, near_singular):
        full = shape_function.compose_inverse(np.eye(n), matrix, n)
        part = shape_function.inverse_rows(matrix, rows, n)
        assert part.shape == (3, n)
        assert np.array_equal(part, full[rows], equal_nan=True)
    for matrix in (spd, general, permuted):
        exact = np.linalg.inv(matrix)[rows]
        np.testing.assert_allclose(
            shape_function.inverse_rows(matrix, rows, n), exact, rtol=1e-9, atol=1e-12
        )
    small = rng.normal(size=(12, 12))
    assert np.array_equal(
        shape_function.inverse_rows(small, np.array([0, 4, 8]), 12),
        shape_function.compose_inverse(np.eye(12), small, 12)[[0, 4, 8]],
    )
