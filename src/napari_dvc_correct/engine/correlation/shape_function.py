"""The shape functions of subvolume matching and their algebra (first and second order).

The warp of a subvolume maps local coordinates ``ξ`` (voxels, z, y, x) to ``ξ + Σ_j p[k, j] b_j(ξ)``
with the monomials ``b(ξ) = (1, ξz, ξy, ξx)`` (first order, 12 parameters) and
``(ξz², ξy², ξx², ξzξy, ξyξx, ξzξx)`` besides (second order, 30 parameters). Warps are composed and
inverted in the matrix that maps ``b(ξ)`` to ``b(W(ξ))`` (exact for the affine warp, truncated at
degree 2 for the quadratic one). Also: the small Cholesky solves of the Gauss–Newton steps, and
the split of parameters into displacement and gradient.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from .._numba_setup import KERNEL_OPTIONS

# Monomials: 0:1 1:z 2:y 3:x 4:zz 5:yy 6:xx 7:zy 8:yx 9:zx  (local coordinates, voxels)
QUAD_AXES_TABLE = np.array([[0, 0], [1, 1], [2, 2], [0, 1], [1, 2], [0, 2]], dtype=np.int64)


def n_monomials(order: int) -> int:
    return 4 if order == 1 else 10


def _product_table() -> np.ndarray:
    """``table[i, j]`` = index of monomial i × monomial j if its degree is ≤ 2, else -1."""
    exponents = np.zeros((10, 3), dtype=np.int64)
    for axis in range(3):
        exponents[1 + axis, axis] = 1
    for q, (a, b) in enumerate(QUAD_AXES_TABLE):
        exponents[4 + q, a] += 1
        exponents[4 + q, b] += 1
    table = -np.ones((10, 10), dtype=np.int64)
    for i in range(10):
        for j in range(10):
            e = exponents[i] + exponents[j]
            if e.sum() <= 2:
                table[i, j] = int(np.where((exponents == e).all(axis=1))[0][0])
    return table


PRODUCT_TABLE = _product_table()
QUAD_AXES = QUAD_AXES_TABLE


@njit(inline="always", **KERNEL_OPTIONS)
def monomials(z, y, x, nb, out):
    out[0] = 1.0
    out[1] = z
    out[2] = y
    out[3] = x
    if nb == 10:
        out[4] = z * z
        out[5] = y * y
        out[6] = x * x
        out[7] = z * y
        out[8] = y * x
        out[9] = z * x


@njit(**KERNEL_OPTIONS)
def warp_matrix(p, nb, product_table, quad_axes):
    """Matrix ``M`` (nb × nb) with ``b(W(ξ; p)) ≈ M b(ξ)`` (truncated at degree 2)."""
    m = np.zeros((nb, nb))
    m[0, 0] = 1.0
    for k in range(3):
        for j in range(nb):
            m[1 + k, j] = p[k * nb + j]
        m[1 + k, 1 + k] += 1.0
    if nb == 10:
        for q in range(6):
            a = quad_axes[q, 0]
            b = quad_axes[q, 1]
            row = 4 + q
            for i in range(nb):
                ci = m[1 + a, i]
                if ci == 0.0:
                    continue
                for j in range(nb):
                    target = product_table[i, j]
                    if target >= 0:
                        m[row, target] += ci * m[1 + b, j]
    return m


@njit(**KERNEL_OPTIONS)
def parameters_from_matrix(m, nb, p):
    for k in range(3):
        for j in range(nb):
            p[k * nb + j] = m[1 + k, j]
        p[k * nb + 1 + k] -= 1.0


@njit(**KERNEL_OPTIONS)
def compose_inverse(m_current, m_update, n):
    """``m_current @ inv(m_update)`` for small n×n warp matrices, without BLAS or LAPACK.

    Solves ``X · m_update = m_current`` by Gauss–Jordan elimination with partial pivoting on the
    transposed system. Calling BLAS/LAPACK here serialised the parallel POI loop (OpenBLAS takes a
    lock per call), so the few hundred flops are written out.
    """
    a = m_update.T.copy()
    rhs = m_current.T.copy()
    for col in range(n):
        pivot = col
        for r in range(col + 1, n):
            if abs(a[r, col]) > abs(a[pivot, col]):
                pivot = r
        if pivot != col:
            for c in range(n):
                a[col, c], a[pivot, c] = a[pivot, c], a[col, c]
                rhs[col, c], rhs[pivot, c] = rhs[pivot, c], rhs[col, c]
        d = a[col, col]
        for c in range(n):
            a[col, c] /= d
            rhs[col, c] /= d
        for r in range(n):
            if r != col:
                factor = a[r, col]
                if factor != 0.0:
                    for c in range(n):
                        a[r, c] -= factor * a[col, c]
                        rhs[r, c] -= factor * rhs[col, c]
    return rhs.T.copy()


@njit(**KERNEL_OPTIONS)
def inverse_rows(matrix, rows, n):
    """Rows ``rows`` of ``inv(matrix)`` (n×n), (len(rows), n): the same bits as
    ``compose_inverse(np.eye(n), matrix, n)[rows]`` at a third of its cost for 3 rows of 30.

    The same Gauss–Jordan elimination, keeping only the right-hand side's columns that give the
    wanted rows (each column is eliminated on its own) and only the columns of ``a`` that a later
    step still reads (those right of the pivot: the others are never read again). The
    uncertainty needs ``A⁻¹`` only at the three translations.
    """
    k = rows.shape[0]
    a = matrix.T.copy()
    rhs = np.zeros((n, k))
    for t in range(k):
        rhs[rows[t], t] = 1.0
    for col in range(n):
        pivot = col
        for r in range(col + 1, n):
            if abs(a[r, col]) > abs(a[pivot, col]):
                pivot = r
        if pivot != col:
            for c in range(col, n):
                a[col, c], a[pivot, c] = a[pivot, c], a[col, c]
            for c in range(k):
                rhs[col, c], rhs[pivot, c] = rhs[pivot, c], rhs[col, c]
        d = a[col, col]
        for c in range(col + 1, n):
            a[col, c] /= d
        for c in range(k):
            rhs[col, c] /= d
        for r in range(n):
            if r != col:
                factor = a[r, col]
                if factor != 0.0:
                    for c in range(col + 1, n):
                        a[r, c] -= factor * a[col, c]
                    for c in range(k):
                        rhs[r, c] -= factor * rhs[col, c]
    return rhs.T.copy()


@njit(**KERNEL_OPTIONS)
def cholesky_solve_setup(h, m):
    """In-place Cholesky factor of the m×m SPD matrix ``h``; returns False if not positive definite.

    Also fails when the smallest pivot is tiny relative to the largest (ill-conditioned Hessian).
    """
    low = np.zeros((m, m))
    largest = 0.0
    smallest = np.inf
    for j in range(m):
        s = h[j, j]
        for k in range(j):
            s -= low[j, k] * low[j, k]
        if not (s > 0.0):
            return False, low
        d = np.sqrt(s)
        low[j, j] = d
        largest = max(largest, s)
        smallest = min(smallest, s)
        for i in range(j + 1, m):
            t = h[i, j]
            for k in range(j):
                t -= low[i, k] * low[j, k]
            low[i, j] = t / d
    if smallest < 1e-12 * largest:
        return False, low
    return True, low


@njit(**KERNEL_OPTIONS)
def cholesky_solve(low, rhs, m, out):
    y = np.empty(m)
    for i in range(m):
        s = rhs[i]
        for k in range(i):
            s -= low[i, k] * y[k]
        y[i] = s / low[i, i]
    for i in range(m - 1, -1, -1):
        s = y[i]
        for k in range(i + 1, m):
            s -= low[k, i] * out[k]
        out[i] = s / low[i, i]


def params_to_displacement(params: np.ndarray, order: int) -> tuple[np.ndarray, np.ndarray]:
    """Split shape-function parameters (N, 3·nb) into displacement (N, 3) and gradient (N, 3, 3)."""
    nb = n_monomials(order)
    shaped = params.reshape(-1, 3, nb)
    return shaped[:, :, 0].copy(), shaped[:, :, 1:4].copy()


def displacement_to_params(
    displacement: np.ndarray, gradient: np.ndarray | None, order: int
) -> np.ndarray:
    """Shape-function parameters (N, 3·nb) from displacement (N, 3) and optional gradient."""
    nb = n_monomials(order)
    params = np.zeros((len(displacement), 3, nb))
    params[:, :, 0] = displacement
    if gradient is not None:
        params[:, :, 1:4] = gradient
    return params.reshape(len(displacement), 3 * nb)
