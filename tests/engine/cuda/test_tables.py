"""The index tables that let the GPU build IC-GN's reference terms, checked with numpy."""

import numpy as np
import pytest

from napari_dvc_correct.engine.correlation import shape_function
from napari_dvc_correct.engine.cuda.tables import (
    MAX_TERMS,
    monomial_exponents,
    reference_sums_numpy,
    reference_tables,
)


@pytest.mark.parametrize("nb", [4, 10])
def test_tables_rebuild_the_hessian_and_the_reference_sums(nb):
    rng = np.random.default_rng(nb)
    r = np.arange(-3, 4)
    xi = np.stack(np.meshgrid(r, r, r, indexing="ij"), -1).reshape(-1, 3).astype(float)
    g = rng.normal(5.0, 1.0, len(xi))
    grad = rng.normal(size=(len(xi), 3))
    tables = reference_tables(nb)
    sums = reference_sums_numpy(g, grad, xi, tables)
    b = np.empty(10)
    jac = np.empty((len(xi), 3 * nb))
    for i in range(len(xi)):
        shape_function.monomials(*xi[i], nb, b)
        for k in range(3):
            jac[i, k * nb : (k + 1) * nb] = grad[i, k] * b[:nb]
    dg = g - g.mean()
    np.testing.assert_allclose(sums[tables.hess_map], jac.T @ jac, rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(sums[tables.jsum_map], jac.sum(0), atol=1e-9)
    np.testing.assert_allclose(sums[tables.jgsum_map], (jac * dg[:, None]).sum(0), atol=1e-9)
    assert sums[tables.ssg_index] == pytest.approx(np.sum(dg**2))
    assert np.all(tables.pass_count <= MAX_TERMS)


def test_monomials_start_like_the_cpu_shape_function():
    exps = monomial_exponents(4)
    assert len(exps) == 35 and len({tuple(e) for e in exps}) == 35
    b = np.empty(10)
    shape_function.monomials(2.0, 3.0, 5.0, 10, b)
    np.testing.assert_array_equal(np.prod([2.0, 3.0, 5.0] ** exps[:10], axis=1), b)
