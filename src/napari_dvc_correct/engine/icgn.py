"""Subvolume matching by the inverse-compositional Gauss–Newton (IC-GN) algorithm.

For a POI at reference position ``c`` and local coordinates ``ξ`` in the subvolume ``[-M, M]³``,
the shape function maps ``ξ`` to the deformed position ``c + W(ξ; p)`` with

``W_k(ξ; p) = ξ_k + Σ_j p[k, j] · b_j(ξ)``,

where ``b(ξ)`` are monomials of the local coordinates: ``(1, ξz, ξy, ξx)`` for the first-order
(affine, 12 parameters) shape function and additionally ``(ξz², ξy², ξx², ξzξy, ξyξx, ξzξx)`` for the
second-order one (30 parameters). So ``p[k, 0]`` is the displacement ``u_k`` at the POI and
``p[k, 1 + l] = ∂u_k/∂X_l``.

The criterion is ZNSSD (reported as ZNCC = 1 − ZNSSD/2). IC-GN precomputes the reference-side
steepest-descent images ``J = ∇G · ∂W/∂p`` and the Hessian ``H = Σ JᵀJ`` once per POI; each
iteration samples the deformed volume at the current warp (tricubic B-spline), solves
``H Δp = -Σ Jᵀ [(G − Ḡ) − (ΔG/ΔF)(F − F̄)]`` and updates ``W(p) ← W(p) ∘ W(Δp)⁻¹``. Warps are
composed and inverted in the matrix representation that maps the monomial vector ``b(ξ)`` to
``b(W(ξ))`` (exact for the affine warp, truncated at degree 2 for the quadratic one).

Iterations stop when the incremental warp moves every subvolume corner by less than the tolerance.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit, prange

from ._numba_setup import FAST_KERNEL_OPTIONS, KERNEL_OPTIONS
from .field import Status
from .interpolation import (
    gradient_at_voxel,
    in_interior,
    sample_interior,
    sample_mirrored,
    sample_with_gradient_point,
)

_CONVERGED = int(Status.CONVERGED)
_DIVERGED = int(Status.DIVERGED)
_LOW_TEXTURE = int(Status.LOW_TEXTURE)
_MASKED = int(Status.MASKED)
_MAX_ITERATIONS = int(Status.MAX_ITERATIONS)
_OUT_OF_BOUNDS = int(Status.OUT_OF_BOUNDS)
_SINGULAR = int(Status.SINGULAR)

# Monomials: 0:1 1:z 2:y 3:x 4:zz 5:yy 6:xx 7:zy 8:yx 9:zx  (local coordinates, voxels)
_QUAD_AXES = np.array([[0, 0], [1, 1], [2, 2], [0, 1], [1, 2], [0, 2]], dtype=np.int64)


def n_monomials(order: int) -> int:
    return 4 if order == 1 else 10


def _product_table() -> np.ndarray:
    """``table[i, j]`` = index of monomial i × monomial j if its degree is ≤ 2, else -1."""
    exponents = np.zeros((10, 3), dtype=np.int64)
    for axis in range(3):
        exponents[1 + axis, axis] = 1
    for q, (a, b) in enumerate(_QUAD_AXES):
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
QUAD_AXES = _QUAD_AXES


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
def _compose_inverse(m_current, m_update, n):
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
def _cholesky_solve_setup(h, m):
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
def _cholesky_solve(low, rhs, m, out):
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


@njit(parallel=True, **KERNEL_OPTIONS)
def gradient_volume(coefficients):
    """Gradient of the B-spline interpolant at every voxel, shape (3, nz, ny, nx), float32."""
    nz, ny, nx = coefficients.shape
    out = np.empty((3, nz, ny, nx), np.float32)
    for iz in prange(nz):
        for iy in range(ny):
            for ix in range(nx):
                gz, gy, gx = gradient_at_voxel(coefficients, iz, iy, ix)
                out[0, iz, iy, ix] = gz
                out[1, iz, iy, ix] = gy
                out[2, iz, iy, ix] = gx
    return out


_PAIR = np.array([[0, 3, 5], [3, 1, 4], [5, 4, 2]], dtype=np.int64)  # (k, k') -> QUAD_AXES row


@njit(**KERNEL_OPTIONS)
def _affine_hessian(grad, xi, count):
    """Σ JᵀJ for the affine shape function through second moments of ∇G ⊗ ∇G.

    ``H[(k, j), (k', j')] = Σ g_k g_k' b_j b_j'`` and ``b_j b_j'`` is one of the 10 monomials of
    degree ≤ 2, so 6 × 10 moments suffice. Voxels come in (z, y, x) row order: sums along each x-row
    of ``g_k g_k' · (1, x, x²)`` are folded into the moments once per row.
    """
    moments = np.zeros((6, 10))
    row0 = np.zeros(6)
    row1 = np.zeros(6)
    row2 = np.zeros(6)
    current_z = xi[0, 0] if count else 0.0
    current_y = xi[0, 1] if count else 0.0
    for i in range(count + 1):
        if i == count or xi[i, 0] != current_z or xi[i, 1] != current_y:
            z = current_z
            y = current_y
            for q in range(6):
                s0 = row0[q]
                s1 = row1[q]
                moments[q, 0] += s0
                moments[q, 1] += z * s0
                moments[q, 2] += y * s0
                moments[q, 3] += s1
                moments[q, 4] += z * z * s0
                moments[q, 5] += y * y * s0
                moments[q, 6] += row2[q]
                moments[q, 7] += z * y * s0
                moments[q, 8] += y * s1
                moments[q, 9] += z * s1
                row0[q] = 0.0
                row1[q] = 0.0
                row2[q] = 0.0
            if i == count:
                break
            current_z = xi[i, 0]
            current_y = xi[i, 1]
        gz = grad[i, 0]
        gy = grad[i, 1]
        gx = grad[i, 2]
        x = xi[i, 2]
        products = (gz * gz, gy * gy, gx * gx, gz * gy, gy * gx, gz * gx)
        for q in range(6):
            value = products[q]
            row0[q] += value
            row1[q] += value * x
            row2[q] += value * x * x
    hessian = np.empty((12, 12))
    for k in range(3):
        for j in range(4):
            for k2 in range(3):
                for j2 in range(4):
                    hessian[k * 4 + j, k2 * 4 + j2] = moments[_PAIR[k, k2], PRODUCT_TABLE[j, j2]]
    return hessian


@njit(**KERNEL_OPTIONS)
def _reference_terms(g, grad, xi, count, nb):
    """Mean and norm of the reference subvolume, Cholesky factor of H = Σ JᵀJ, Σ J, Σ J (g − ḡ)."""
    m_par = 3 * nb
    mean_g = 0.0
    for i in range(count):
        mean_g += g[i]
    mean_g /= max(count, 1)
    ss_g = 0.0
    for i in range(count):
        d = g[i] - mean_g
        ss_g += d * d
    delta_g = np.sqrt(ss_g)
    sum_j = np.zeros(m_par)
    sum_jg = np.zeros(m_par)
    b = np.empty(10)
    if nb == 4:
        hessian = _affine_hessian(grad, xi, count)
        for i in range(count):
            monomials(xi[i, 0], xi[i, 1], xi[i, 2], nb, b)
            dg = g[i] - mean_g
            for k in range(3):
                for j in range(4):
                    jr = grad[i, k] * b[j]
                    sum_j[k * 4 + j] += jr
                    sum_jg[k * 4 + j] += jr * dg
    else:
        hessian = np.zeros((m_par, m_par))
        jac = np.empty(m_par)
        for i in range(count):
            monomials(xi[i, 0], xi[i, 1], xi[i, 2], nb, b)
            for k in range(3):
                for j in range(nb):
                    jac[k * nb + j] = grad[i, k] * b[j]
            dg = g[i] - mean_g
            for r in range(m_par):
                jr = jac[r]
                sum_j[r] += jr
                sum_jg[r] += jr * dg
                for c in range(r + 1):
                    hessian[r, c] += jr * jac[c]
        for r in range(m_par):
            for c in range(r):
                hessian[c, r] = hessian[r, c]
    ok, low = _cholesky_solve_setup(hessian, m_par)
    return mean_g, delta_g, ok, low, sum_j, sum_jg


@njit(**FAST_KERNEL_OPTIONS)
def _sample_pass(coef, g, grad, xi, count, mean_g, cz, cy, cx, p, nb, outside, sum_jf):
    """One pass over the subvolume at warp ``p``.

    Samples ``F`` at every warped voxel and returns ``(Σf, Σf², Σ(g − ḡ)f, voxels outside)``,
    filling ``sum_jf = Σ J f``. Voxels whose warped position leaves ``F`` are flagged in
    ``outside``. (The in-volume test is written out in both branches: moving it into a helper
    that returns ``(value, inside)`` measured 18% slower.)
    """
    nz, ny, nx = coef.shape
    sum_f = 0.0
    sum_ff = 0.0
    sum_gf = 0.0
    n_outside = 0
    if nb == 4:
        # affine warp written out: 12 accumulators stay in registers
        t0 = cz + p[0]
        t1 = cy + p[4]
        t2 = cx + p[8]
        a00 = 1.0 + p[1]
        a01 = p[2]
        a02 = p[3]
        a10 = p[5]
        a11 = 1.0 + p[6]
        a12 = p[7]
        a20 = p[9]
        a21 = p[10]
        a22 = 1.0 + p[11]
        s00 = s01 = s02 = s03 = 0.0
        s10 = s11 = s12 = s13 = 0.0
        s20 = s21 = s22 = s23 = 0.0
        for i in range(count):
            z = xi[i, 0]
            y = xi[i, 1]
            x = xi[i, 2]
            wz = t0 + a00 * z + a01 * y + a02 * x
            wy = t1 + a10 * z + a11 * y + a12 * x
            wx = t2 + a20 * z + a21 * y + a22 * x
            if in_interior(coef, wz, wy, wx):
                f = sample_interior(coef, wz, wy, wx)
            elif 0.0 <= wz <= nz - 1 and 0.0 <= wy <= ny - 1 and 0.0 <= wx <= nx - 1:
                f = sample_mirrored(coef, wz, wy, wx)
            else:
                outside[i] = True
                n_outside += 1
                continue
            sum_f += f
            sum_ff += f * f
            sum_gf += (g[i] - mean_g) * f
            f0 = grad[i, 0] * f
            f1 = grad[i, 1] * f
            f2 = grad[i, 2] * f
            s00 += f0
            s01 += f0 * z
            s02 += f0 * y
            s03 += f0 * x
            s10 += f1
            s11 += f1 * z
            s12 += f1 * y
            s13 += f1 * x
            s20 += f2
            s21 += f2 * z
            s22 += f2 * y
            s23 += f2 * x
        sum_jf[0] = s00
        sum_jf[1] = s01
        sum_jf[2] = s02
        sum_jf[3] = s03
        sum_jf[4] = s10
        sum_jf[5] = s11
        sum_jf[6] = s12
        sum_jf[7] = s13
        sum_jf[8] = s20
        sum_jf[9] = s21
        sum_jf[10] = s22
        sum_jf[11] = s23
        return sum_f, sum_ff, sum_gf, n_outside
    b = np.empty(10)
    for r in range(3 * nb):
        sum_jf[r] = 0.0
    for i in range(count):
        monomials(xi[i, 0], xi[i, 1], xi[i, 2], nb, b)
        wz = cz + xi[i, 0]
        wy = cy + xi[i, 1]
        wx = cx + xi[i, 2]
        for j in range(nb):
            wz += p[j] * b[j]
            wy += p[nb + j] * b[j]
            wx += p[2 * nb + j] * b[j]
        if in_interior(coef, wz, wy, wx):
            f = sample_interior(coef, wz, wy, wx)
        elif 0.0 <= wz <= nz - 1 and 0.0 <= wy <= ny - 1 and 0.0 <= wx <= nx - 1:
            f = sample_mirrored(coef, wz, wy, wx)
        else:
            outside[i] = True
            n_outside += 1
            continue
        sum_f += f
        sum_ff += f * f
        sum_gf += (g[i] - mean_g) * f
        for k in range(3):
            gf = grad[i, k] * f
            for j in range(nb):
                sum_jf[k * nb + j] += gf * b[j]
    return sum_f, sum_ff, sum_gf, n_outside


@njit(**KERNEL_OPTIONS)
def _translation_h_inverse(low, m_par, nb, out):
    """Diagonal of ``H⁻¹`` at the three translations, from the Cholesky factor of ``H``."""
    unit = np.zeros(m_par)
    column = np.empty(m_par)
    for k in range(3):
        unit[:] = 0.0
        unit[k * nb] = 1.0
        _cholesky_solve(low, unit, m_par, column)
        out[k] = column[k * nb]


#: The noise stop applies to matches whose ZNCC is below this (residual variance above 0.1 % of
#: the subvolume's): noise-free scans converge to ``tolerance`` as before.
NOISE_STOP_MAX_ZNCC = 0.999


@njit(**KERNEL_OPTIONS)
def _noise_converged(dp, nb, h_inv, delta_g, zncc, count, previous, noise_fraction):
    """Noise stop: True when the remaining translation error is below ``noise_fraction`` of its noise.

    With noise on the reference, ``H = Σ J_GᵀJ_G`` holds the gradient of that noise, which the
    deformed scan does not share, so IC-GN steps are too short and converge linearly: each step is
    ``ρ`` times the last and ``ρ / (1 − ρ)`` times the step is still to go. With
    ``d = max_k |Δu_k| / σ_k`` (``σ_k² = σ_r² (H⁻¹)_kk``, the residual variance per voxel
    ``σ_r² = 2 Σ(g − ḡ)² (1 − ZNCC) / (n − 3·nb − 2)``) and the true noise uncertainty about
    ``σ_k / (1 − ρ)``, the remaining error is below ``noise_fraction`` of it when ``d · ρ`` is:
    the rule is ``d < 1`` and ``d · min(ρ, 1) < noise_fraction``, ``ρ = d / d_previous``.
    The rule applies only where ``ZNCC < NOISE_STOP_MAX_ZNCC``: on noise-free scans the usual
    tolerance decides, exactly as without it.

    Returns ``(stop, d)``.
    """
    if not (zncc < NOISE_STOP_MAX_ZNCC):
        return False, np.inf
    m_par = 3 * nb
    residual = 2.0 * delta_g * delta_g * max(1.0 - zncc, 0.0) / max(count - m_par - 2, 1)
    d = 0.0
    for k in range(3):
        scale = np.sqrt(residual * h_inv[k])
        if not (scale > 0.0):
            return False, np.inf
        d = max(d, abs(dp[k * nb]) / scale)
    if d < 1.0 and np.isfinite(previous):
        rho = min(d / previous, 1.0) if previous > 0.0 else 0.0
        if d * rho < noise_fraction:
            return True, d
    return False, d


@njit(**KERNEL_OPTIONS)
def match_one(
    reference,
    gradient,
    coef_deformed,
    mask,
    use_mask,
    cz,
    cy,
    cx,
    half,
    nb,
    p,
    max_iterations,
    tolerance,
    min_std,
    min_mask_fraction,
    max_update,
    product_table,
    quad_axes,
    noise_fraction=0.0,
):
    """Match one subvolume by IC-GN; ``p`` (3·nb) is the initial guess in and the result out.

    Returns ``(zncc, status, iterations)``. Kernels assume valid input: the reference subvolume
    lies inside the reference volume. ``noise_fraction`` > 0 adds the noise stop of
    :func:`_noise_converged`.
    """
    m_par = 3 * nb
    edge = 2 * half + 1
    n_total = edge * edge * edge
    g = np.empty(n_total)
    grad = np.empty((n_total, 3))
    xi = np.empty((n_total, 3))
    count = 0
    for dz in range(-half, half + 1):
        z = cz + dz
        for dy in range(-half, half + 1):
            y = cy + dy
            for dx in range(-half, half + 1):
                x = cx + dx
                if use_mask and not mask[z, y, x]:
                    continue
                g[count] = reference[z, y, x]
                grad[count, 0] = gradient[0, z, y, x]
                grad[count, 1] = gradient[1, z, y, x]
                grad[count, 2] = gradient[2, z, y, x]
                xi[count, 0] = dz
                xi[count, 1] = dy
                xi[count, 2] = dx
                count += 1
    if count < min_mask_fraction * n_total or count < m_par + 1:
        return np.nan, _MASKED, 0

    mean_g, delta_g, ok, low, sum_j, sum_jg = _reference_terms(g, grad, xi, count, nb)
    if delta_g <= min_std * np.sqrt(count) or delta_g == 0.0:
        return np.nan, _LOW_TEXTURE, 0
    if not ok:
        return np.nan, _SINGULAR, 0

    start = np.empty(3)
    for k in range(3):
        start[k] = p[k * nb]
    h_inv = np.empty(3)
    _translation_h_inverse(low, m_par, nb, h_inv)
    previous = np.inf
    sum_jf = np.empty(m_par)
    rhs = np.empty(m_par)
    dp = np.empty(m_par)
    corner = np.empty(10)
    zncc = np.nan
    outside = np.zeros(count, np.bool_)
    for iteration in range(1, max_iterations + 1):
        sum_f, sum_ff, sum_gf, n_outside = _sample_pass(
            coef_deformed, g, grad, xi, count, mean_g, cz, cy, cx, p, nb, outside, sum_jf
        )
        if n_outside > 0:
            # Part of the deformed subvolume left the volume: drop those voxels, rebuild the
            # reference-side terms on the rest and iterate again from the same warp.
            kept = 0
            for i in range(count):
                if not outside[i]:
                    g[kept] = g[i]
                    grad[kept, 0] = grad[i, 0]
                    grad[kept, 1] = grad[i, 1]
                    grad[kept, 2] = grad[i, 2]
                    xi[kept, 0] = xi[i, 0]
                    xi[kept, 1] = xi[i, 1]
                    xi[kept, 2] = xi[i, 2]
                    kept += 1
                outside[i] = False
            count = kept
            if count < min_mask_fraction * n_total or count < m_par + 1:
                return zncc, _OUT_OF_BOUNDS, iteration
            mean_g, delta_g, ok, low, sum_j, sum_jg = _reference_terms(g, grad, xi, count, nb)
            if not ok or delta_g == 0.0:
                return zncc, _OUT_OF_BOUNDS, iteration
            _translation_h_inverse(low, m_par, nb, h_inv)
            previous = np.inf
            continue
        mean_f = sum_f / count
        ss_f = sum_ff - count * mean_f * mean_f
        if not (ss_f > 0.0):
            return np.nan, _DIVERGED, iteration
        delta_f = np.sqrt(ss_f)
        zncc = sum_gf / (delta_g * delta_f)
        ratio = delta_g / delta_f
        for r in range(m_par):
            rhs[r] = -(sum_jg[r] - ratio * (sum_jf[r] - mean_f * sum_j[r]))
        _cholesky_solve(low, rhs, m_par, dp)

        # W(p) <- W(p) o W(dp)^-1
        m_current = warp_matrix(p, nb, product_table, quad_axes)
        m_update = warp_matrix(dp, nb, product_table, quad_axes)
        m_new = _compose_inverse(m_current, m_update, nb)
        parameters_from_matrix(m_new, nb, p)

        largest = 0.0
        for sz in (-half, half):
            for sy in (-half, half):
                for sx in (-half, half):
                    monomials(float(sz), float(sy), float(sx), nb, corner)
                    norm2 = 0.0
                    for k in range(3):
                        moved = 0.0
                        for j in range(nb):
                            moved += dp[k * nb + j] * corner[j]
                        norm2 += moved * moved
                    largest = max(largest, norm2)
        finite = True
        for r in range(m_par):
            if not np.isfinite(p[r]):
                finite = False
        moved_far = False
        for k in range(3):
            if abs(p[k * nb] - start[k]) > max_update:
                moved_far = True
        if not finite or moved_far:
            return zncc, _DIVERGED, iteration
        if np.sqrt(largest) < tolerance:
            return zncc, _CONVERGED, iteration
        if noise_fraction > 0.0:
            stop, previous = _noise_converged(
                dp, nb, h_inv, delta_g, zncc, count, previous, noise_fraction
            )
            if stop:
                return zncc, _CONVERGED, iteration
    return zncc, _MAX_ITERATIONS, max_iterations


class MatchInputs(NamedTuple):
    """Everything the IC-GN kernels need besides the POIs and their outputs.

    One bundle for :func:`match_many` and :func:`.cuda.match_many_cuda` (built by
    ``correlate.PyramidLevel.inputs``).

    Attributes
    ----------
    reference : ndarray (nz, ny, nx) float32
        Reference gray values G.
    gradient : ndarray (3, nz, ny, nx) float32
        Gradient of G's B-spline interpolant, ``(d/dz, d/dy, d/dx)``, gray levels per voxel.
    coef_deformed : ndarray (nz, ny, nx) float32
        B-spline coefficients of F.
    mask : ndarray of bool (nz, ny, nx), or any bool array when ``use_mask`` is False
    use_mask : bool
    half : int
        Subvolume half size M (edge 2M + 1), voxels.
    nb : {4, 10}
        Monomials of the shape function (first / second order).
    max_iterations : int
    tolerance : float
        Convergence threshold (voxels) on the largest corner motion of the incremental warp.
    min_std : float
        Subvolumes whose gray standard deviation is at most this are ``LOW_TEXTURE``.
    min_mask_fraction : float
    max_update : float
        Largest translation change (voxels) from the guess before ``DIVERGED``.
    noise_fraction : float
        The noise stop (:func:`_noise_converged`); 0 turns it off.
    product_table, quad_axes : ndarray int64
        :data:`PRODUCT_TABLE`, :data:`QUAD_AXES`.
    """

    reference: np.ndarray
    gradient: np.ndarray
    coef_deformed: np.ndarray
    mask: np.ndarray
    use_mask: bool
    half: int
    nb: int
    max_iterations: int
    tolerance: float
    min_std: float
    min_mask_fraction: float
    max_update: float
    noise_fraction: float = 0.0
    product_table: np.ndarray = PRODUCT_TABLE
    quad_axes: np.ndarray = QUAD_AXES


@njit(parallel=True, **KERNEL_OPTIONS)
def match_many(inputs, centers, params, zncc, status, iterations):
    """IC-GN for many POIs in parallel (:class:`MatchInputs`).

    ``centers`` (N, 3) int64 POI positions (each subvolume inside the volume); ``params``
    (N, 3·nb) holds guesses in, results out; ``zncc`` (N,) float64, ``status`` and
    ``iterations`` (N,) int64 are outputs.
    """
    for i in prange(centers.shape[0]):
        p = params[i].copy()
        value, code, its = match_one(
            inputs.reference,
            inputs.gradient,
            inputs.coef_deformed,
            inputs.mask,
            inputs.use_mask,
            centers[i, 0],
            centers[i, 1],
            centers[i, 2],
            inputs.half,
            inputs.nb,
            p,
            inputs.max_iterations,
            inputs.tolerance,
            inputs.min_std,
            inputs.min_mask_fraction,
            inputs.max_update,
            inputs.product_table,
            inputs.quad_axes,
            inputs.noise_fraction,
        )
        params[i, :] = p
        zncc[i] = value
        status[i] = code
        iterations[i] = its


@njit(parallel=True, **KERNEL_OPTIONS)
def subvolume_statistics(
    reference,
    gradient,
    coef_deformed,
    mask,
    use_mask,
    centers,
    half,
    nb,
    params,
    zncc,
    sensitivity,
    variance,
    gradient_power,
    sigma,
):
    """Gray variance of each POI's reference subvolume and the uncertainty of its translation.

    The match solves ``Φ(p) = Σ J_Gᵀ r(p) = 0`` with ``r = (g − ḡ) − (Δg/Δf)(f(W(ξ; p)) − f̄)``
    and ``J_G = ∇G · ∂W/∂p``. Noise moves the solution by ``δp = −A⁻¹ Φ`` with the sensitivity
    ``A = (Δg/Δf) Σ J_G⊥ᵀ (∇F(W) ⊗ b)``, so

    ``Cov p = A⁻¹ (Cov Φ) A⁻ᵀ``,   ``Cov Φ = σ_r² (H⊥ + sym A) / 2``,
    ``σ_r² = 2 Σ(g − ḡ)² (1 − ZNCC) / (n − 3·nb − 2)``.

    ``Cov Φ``: ``J_G`` holds the gradient of the reference's noise ``n_G`` and ``r`` holds
    ``n_G`` itself; their pairings at neighbouring voxels cancel ``σ_G²`` of the ``σ_r²`` that
    multiplies the noise part ``H − A`` of ``H``: ``Cov Φ = σ_r² H − σ_G² (H − A)``. With the
    same noise on both scans (``σ_G² = σ_r² / 2``) that is ``σ_r² (H + A) / 2``; with noise on
    the deformed scan only, ``A = H`` and it is ``σ_r² H``.

    ``⊥`` marks steepest-descent images made orthogonal to the gray offset and scale that ZNSSD
    ignores (``H⊥ = H − ΣJ ΣJᵀ/n − ΣJg ΣJgᵀ/Σ(g − ḡ)²``). ``A`` is taken with the gradient of
    the *deformed* volume at the warped voxels, whose noise is independent of the reference's: on
    noisy scans ``H = Σ J_GᵀJ_G`` is inflated by the gradient of the reference's noise while ``A``
    is not, and ``σ_r² H⁻¹`` alone would be several times too small (measured: 5× at 6 % noise).

    Where the reference's noise adds little to ``H`` (``sensitivity`` False), ``A = H⊥`` and the
    estimate is ``σ_r² (H⊥⁻¹)_kk``, without the pass over the deformed volume.

    Parameters
    ----------
    reference, gradient, coef_deformed, mask, use_mask, centers, half, nb
        As in :func:`match_many` (``centers`` (N, 3) int64, subvolumes inside the volume).
    params : ndarray (N, 3·nb) float64
        Final shape-function parameters of each POI.
    zncc : ndarray (N,) float64
        ZNCC of each POI's final match; NaN where none (then ``sigma`` is NaN).
    sensitivity : ndarray (N,) bool
        Where to measure ``A`` from the deformed volume (noisy scans).
    variance : ndarray (N,) float64, out
        Gray variance of the subvolume (masked voxels left out); NaN where fewer than
        ``3·nb + 3`` voxels are usable.
    gradient_power : ndarray (N,) float64, out
        Mean of ``|∇G|²`` over the subvolume (gray²/voxel²).
    sigma : ndarray (N, 3) float64, out
        Standard deviation of ``(uz, uy, ux)`` in voxels; ``inf`` where ``A`` is singular.
    """
    m_par = 3 * nb
    edge = 2 * half + 1
    n_total = edge * edge * edge
    nz, ny, nx = coef_deformed.shape
    for n in prange(centers.shape[0]):
        cz = centers[n, 0]
        cy = centers[n, 1]
        cx = centers[n, 2]
        g = np.empty(n_total)
        grad = np.empty((n_total, 3))
        xi = np.empty((n_total, 3))
        count = 0
        for dz in range(-half, half + 1):
            for dy in range(-half, half + 1):
                for dx in range(-half, half + 1):
                    z = cz + dz
                    y = cy + dy
                    x = cx + dx
                    if use_mask and not mask[z, y, x]:
                        continue
                    g[count] = reference[z, y, x]
                    for k in range(3):
                        grad[count, k] = gradient[k, z, y, x]
                    xi[count, 0] = dz
                    xi[count, 1] = dy
                    xi[count, 2] = dx
                    count += 1
        for k in range(3):
            sigma[n, k] = np.nan
        variance[n] = np.nan
        gradient_power[n] = np.nan
        if count < m_par + 3:
            continue
        mean_g, delta_g, ok, low, sum_j, sum_jg = _reference_terms(g, grad, xi, count, nb)
        variance[n] = delta_g * delta_g / count
        power = 0.0
        for k in range(3):
            for j in range(k * nb + 1):
                power += low[k * nb, j] * low[k * nb, j]
        gradient_power[n] = power / count
        if not ok or delta_g == 0.0 or not np.isfinite(zncc[n]):
            continue
        # H⊥ from the Cholesky factor
        ss_g = delta_g * delta_g
        h_perp = np.empty((m_par, m_par))
        for r in range(m_par):
            for c in range(r + 1):
                v = 0.0
                for k in range(c + 1):
                    v += low[r, k] * low[c, k]
                v -= sum_j[r] * sum_j[c] / count + sum_jg[r] * sum_jg[c] / ss_g
                h_perp[r, c] = v
                h_perp[c, r] = v
        residual = 2.0 * ss_g * max(1.0 - zncc[n], 0.0) / max(count - m_par - 2, 1)
        if not sensitivity[n]:
            ok_perp, low_perp = _cholesky_solve_setup(h_perp, m_par)
            h_inv = np.empty(3)
            if ok_perp:
                _translation_h_inverse(low_perp, m_par, nb, h_inv)
            for k in range(3):
                sigma[n, k] = np.sqrt(residual * h_inv[k]) if ok_perp else np.inf
            continue
        # A from the deformed volume's gradient at the warped voxels
        # Σ g_k f_l b_j b_j' for j <= j' (the products are symmetric in j, j')
        moments = np.zeros((9, nb, nb))
        sum_jf = np.zeros(m_par)
        sum_jfg = np.zeros(m_par)
        gf = np.empty(9)
        b = np.empty(10)
        used = 0
        sum_f = 0.0
        sum_ff = 0.0
        for i in range(count):
            monomials(xi[i, 0], xi[i, 1], xi[i, 2], nb, b)
            wz = cz + xi[i, 0]
            wy = cy + xi[i, 1]
            wx = cx + xi[i, 2]
            for j in range(nb):
                wz += params[n, j] * b[j]
                wy += params[n, nb + j] * b[j]
                wx += params[n, 2 * nb + j] * b[j]
            if not (0.0 <= wz <= nz - 1 and 0.0 <= wy <= ny - 1 and 0.0 <= wx <= nx - 1):
                continue
            f, fz, fy, fx = sample_with_gradient_point(coef_deformed, wz, wy, wx)
            used += 1
            sum_f += f
            sum_ff += f * f
            dg = g[i] - mean_g
            for k in range(3):
                gk = grad[i, k]
                gf[3 * k] = gk * fz
                gf[3 * k + 1] = gk * fy
                gf[3 * k + 2] = gk * fx
            for j in range(nb):
                bj = b[j]
                sum_jf[j] += fz * bj
                sum_jf[nb + j] += fy * bj
                sum_jf[2 * nb + j] += fx * bj
                sum_jfg[j] += fz * bj * dg
                sum_jfg[nb + j] += fy * bj * dg
                sum_jfg[2 * nb + j] += fx * bj * dg
                for j2 in range(j, nb):
                    bb = bj * b[j2]
                    for q in range(9):
                        moments[q, j, j2] += gf[q] * bb
        cross = np.empty((m_par, m_par))
        for k in range(3):
            for l in range(3):
                q = 3 * k + l
                for j in range(nb):
                    for j2 in range(nb):
                        value = moments[q, j, j2] if j <= j2 else moments[q, j2, j]
                        cross[k * nb + j, l * nb + j2] = value
        if used < m_par + 3:
            continue
        ss_f = sum_ff - sum_f * sum_f / used
        if not (ss_f > 0.0):
            continue
        ratio = delta_g / np.sqrt(ss_f)
        identity = np.eye(m_par)
        for r in range(m_par):
            for c in range(m_par):
                cross[r, c] = ratio * (
                    cross[r, c] - sum_j[r] * sum_jf[c] / count - sum_jg[r] * sum_jfg[c] / ss_g
                )
        inverse = _compose_inverse(identity, cross, m_par)
        # Cov Φ = σ_r² (H⊥ + sym A) / 2: see the docstring
        for r in range(m_par):
            for c in range(m_par):
                h_perp[r, c] = 0.5 * h_perp[r, c] + 0.25 * (cross[r, c] + cross[c, r])
        for k in range(3):
            row = k * nb
            quad = 0.0
            for r in range(m_par):
                t = 0.0
                for c in range(m_par):
                    t += h_perp[r, c] * inverse[row, c]
                quad += inverse[row, r] * t
            value = np.sqrt(residual * max(quad, 0.0))
            sigma[n, k] = value if np.isfinite(value) else np.inf


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
