"""Per-POI uncertainty of a match from the images alone (SPEC §7): the sandwich estimate.

After IC-GN has converged, one more pass over each subvolume gives the gray variance of the
reference subvolume and the standard deviation of the three translations, in voxels, from the
sensitivity of the match to the imaging noise (see :func:`subvolume_statistics`).
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from ._numba_setup import KERNEL_OPTIONS
from .icgn_reference import fold_row, reference_terms, translation_h_inverse
from .interpolation import (
    bspline_derivative_weights,
    bspline_weights,
    sample_with_gradient_point,
)
from .shape_function import PRODUCT_TABLE, cholesky_solve_setup, compose_inverse, monomials


@njit(inline="always", **KERNEL_OPTIONS)
def _value_and_gradient(coefficients, z, y, x):
    """:func:`.sample_with_gradient_point` with direct indexing where all 64 taps are inside."""
    nz, ny, nx = coefficients.shape
    if not (1.0 <= z < nz - 2.0 and 1.0 <= y < ny - 2.0 and 1.0 <= x < nx - 2.0):
        return sample_with_gradient_point(coefficients, z, y, x)
    iz = int(z)
    iy = int(y)
    ix = int(x)
    wz = bspline_weights(z - iz)
    wy = bspline_weights(y - iy)
    wx = bspline_weights(x - ix)
    dz = bspline_derivative_weights(z - iz)
    dy = bspline_derivative_weights(y - iy)
    dx = bspline_derivative_weights(x - ix)
    v = 0.0
    gz = 0.0
    gy = 0.0
    gx = 0.0
    for a in range(4):
        plane_v = 0.0
        plane_dy = 0.0
        plane_dx = 0.0
        for b in range(4):
            row = coefficients[iz - 1 + a, iy - 1 + b]
            c0 = row[ix - 1]
            c1 = row[ix]
            c2 = row[ix + 1]
            c3 = row[ix + 2]
            row_v = wx[0] * c0 + wx[1] * c1 + wx[2] * c2 + wx[3] * c3
            row_d = dx[0] * c0 + dx[1] * c1 + dx[2] * c2 + dx[3] * c3
            plane_v += wy[b] * row_v
            plane_dy += dy[b] * row_v
            plane_dx += wy[b] * row_d
        v += wz[a] * plane_v
        gz += dz[a] * plane_v
        gy += wz[a] * plane_dy
        gx += wz[a] * plane_dx
    return v, gz, gy, gx


@njit(**KERNEL_OPTIONS)
def _affine_sensitivity_sums(coef, g, grad, xi, count, mean_g, cz, cy, cx, p):
    """First order: ``Σ J_G ⊗ ∇F(W) b bᵀ`` (as 9 × 10 moments), ``Σ J_F``, ``Σ J_F (g − ḡ)``, ``Σf``,
    ``Σf²`` and the voxels used, in one pass with x-row sums folded into the moments (as in
    :func:`.icgn_reference.affine_terms`)."""
    nz, ny, nx = coef.shape
    moments = np.zeros((9, 10))
    row0 = np.zeros(9)
    row1 = np.zeros(9)
    row2 = np.zeros(9)
    gf = np.empty(9)
    sum_jf = np.zeros(12)
    sum_jfg = np.zeros(12)
    used = 0
    sum_f = 0.0
    sum_ff = 0.0
    current_z = np.float64(xi[0, 0]) if count else 0.0
    current_y = np.float64(xi[0, 1]) if count else 0.0
    for i in range(count + 1):
        if i == count or xi[i, 0] != current_z or xi[i, 1] != current_y:
            z = current_z
            y = current_y
            fold_row(moments, row0, row1, row2, z, y, 9)
            if i == count:
                break
            current_z = np.float64(xi[i, 0])
            current_y = np.float64(xi[i, 1])
        z = current_z
        y = current_y
        x = np.float64(xi[i, 2])
        wz = cz + p[0] + (1.0 + p[1]) * z + p[2] * y + p[3] * x
        wy = cy + p[4] + p[5] * z + (1.0 + p[6]) * y + p[7] * x
        wx = cx + p[8] + p[9] * z + p[10] * y + (1.0 + p[11]) * x
        if not (0.0 <= wz <= nz - 1 and 0.0 <= wy <= ny - 1 and 0.0 <= wx <= nx - 1):
            continue
        f, fz, fy, fx = _value_and_gradient(coef, wz, wy, wx)
        used += 1
        sum_f += f
        sum_ff += f * f
        dg = g[i] - mean_g
        for k in range(3):
            gk = np.float64(grad[i, k])
            gf[3 * k] = gk * fz
            gf[3 * k + 1] = gk * fy
            gf[3 * k + 2] = gk * fx
        for q in range(9):
            value = gf[q]
            row0[q] += value
            row1[q] += value * x
            row2[q] += value * x * x
        for l in range(3):
            fl = fz if l == 0 else (fy if l == 1 else fx)
            sum_jf[4 * l] += fl
            sum_jf[4 * l + 1] += fl * z
            sum_jf[4 * l + 2] += fl * y
            sum_jf[4 * l + 3] += fl * x
            sum_jfg[4 * l] += fl * dg
            sum_jfg[4 * l + 1] += fl * z * dg
            sum_jfg[4 * l + 2] += fl * y * dg
            sum_jfg[4 * l + 3] += fl * x * dg
    cross = np.empty((12, 12))
    for k in range(3):
        for l in range(3):
            q = 3 * k + l
            for j in range(4):
                for j2 in range(4):
                    cross[k * 4 + j, l * 4 + j2] = moments[q, PRODUCT_TABLE[j, j2]]
    return cross, sum_jf, sum_jfg, used, sum_f, sum_ff


def _quartic_tables():
    """Exponents ``(a, b, c)`` of the 35 monomials ``z^a y^b x^c`` of degree ≤ 4, and for the
    second-order shape function's monomials ``b_j`` (:func:`.shape_function.monomials`) the
    index of ``b_j`` and of ``b_j b_j'`` among them."""
    powers = [(a, b, c) for a in range(5) for b in range(5 - a) for c in range(5 - a - b)]
    index = {e: i for i, e in enumerate(powers)}
    basis = [(0, 0, 0), (1, 0, 0), (0, 1, 0), (0, 0, 1), (2, 0, 0), (0, 2, 0), (0, 0, 2)]
    basis += [(1, 1, 0), (0, 1, 1), (1, 0, 1)]
    single = np.array([index[e] for e in basis], np.int64)
    product = np.array(
        [[index[tuple(u + v for u, v in zip(e, f))] for f in basis] for e in basis], np.int64
    )
    return np.array(powers, np.int64), single, product


_QUARTIC_POWERS, _QUADRATIC_INDEX, _QUADRATIC_PRODUCT = _quartic_tables()


_PAIR = np.array([[0, 3, 5], [3, 1, 4], [5, 4, 2]], np.int64)  # (k, k') -> g_k g_k' below


@njit(**KERNEL_OPTIONS)
def _quadratic_reference_terms(g, grad, xi, count):
    """Second order: :func:`.icgn_reference.reference_terms` (same returns) with ``H``, ``Σ J``
    and ``Σ J (g − ḡ)`` from the 12 per-voxel quantities ``g_k g_k'``, ``g_k``, ``g_k (g − ḡ)``
    summed along each x-row times ``1 … x⁴`` and folded into the 35 quartic moments per row."""
    nb = 10
    m_par = 30
    n_mom = _QUARTIC_POWERS.shape[0]
    mean_g = 0.0
    for i in range(count):
        mean_g += g[i]
    mean_g /= max(count, 1)
    ss_g = 0.0
    for i in range(count):
        d = g[i] - mean_g
        ss_g += d * d
    moments = np.zeros((12, n_mom))
    rows = np.zeros((5, 12))
    values = np.empty(12)
    zp = np.empty(5)
    yp = np.empty(5)
    current_z = np.float64(xi[0, 0]) if count else 0.0
    current_y = np.float64(xi[0, 1]) if count else 0.0
    for i in range(count + 1):
        if i == count or xi[i, 0] != current_z or xi[i, 1] != current_y:
            zp[0] = 1.0
            yp[0] = 1.0
            for e in range(1, 5):
                zp[e] = zp[e - 1] * current_z
                yp[e] = yp[e - 1] * current_y
            for m in range(n_mom):
                factor = zp[_QUARTIC_POWERS[m, 0]] * yp[_QUARTIC_POWERS[m, 1]]
                c = _QUARTIC_POWERS[m, 2]
                for q in range(12):
                    moments[q, m] += factor * rows[c, q]
            rows[:] = 0.0
            if i == count:
                break
            current_z = np.float64(xi[i, 0])
            current_y = np.float64(xi[i, 1])
        x = np.float64(xi[i, 2])
        gz = np.float64(grad[i, 0])
        gy = np.float64(grad[i, 1])
        gx = np.float64(grad[i, 2])
        dg = g[i] - mean_g
        values[0] = gz * gz
        values[1] = gy * gy
        values[2] = gx * gx
        values[3] = gz * gy
        values[4] = gy * gx
        values[5] = gz * gx
        values[6] = gz
        values[7] = gy
        values[8] = gx
        values[9] = gz * dg
        values[10] = gy * dg
        values[11] = gx * dg
        xc = 1.0
        for c in range(5):
            for q in range(12):
                rows[c, q] += values[q] * xc
            xc *= x
    hessian = np.empty((m_par, m_par))
    sum_j = np.empty(m_par)
    sum_jg = np.empty(m_par)
    for k in range(3):
        for j in range(nb):
            sum_j[k * nb + j] = moments[6 + k, _QUADRATIC_INDEX[j]]
            sum_jg[k * nb + j] = moments[9 + k, _QUADRATIC_INDEX[j]]
            for k2 in range(3):
                for j2 in range(nb):
                    value = moments[_PAIR[k, k2], _QUADRATIC_PRODUCT[j, j2]]
                    hessian[k * nb + j, k2 * nb + j2] = value
    delta_g = np.sqrt(ss_g)
    ok, low = cholesky_solve_setup(hessian, m_par)
    return mean_g, delta_g, ok, low, sum_j, sum_jg


@njit(**KERNEL_OPTIONS)
def _quadratic_sensitivity_sums(coef, g, grad, xi, count, mean_g, cz, cy, cx, p):
    """Second order: :func:`_sensitivity_sums` with the 15 per-voxel quantities (``g_k f_l``,
    ``f_l``, ``f_l (g − ḡ)``) summed along each x-row times ``1 … x⁴`` and folded into the 35
    moments ``z^a y^b x^c`` (degree ≤ 4) once per row, as :func:`_affine_sensitivity_sums`."""
    nb = 10
    m_par = 30
    nz, ny, nx = coef.shape
    n_mom = _QUARTIC_POWERS.shape[0]
    moments = np.zeros((15, n_mom))
    rows = np.zeros((5, 15))
    values = np.empty(15)
    b = np.empty(10)
    used = 0
    sum_f = 0.0
    sum_ff = 0.0
    zp = np.empty(5)
    yp = np.empty(5)
    current_z = np.float64(xi[0, 0]) if count else 0.0
    current_y = np.float64(xi[0, 1]) if count else 0.0
    for i in range(count + 1):
        if i == count or xi[i, 0] != current_z or xi[i, 1] != current_y:
            zp[0] = 1.0
            yp[0] = 1.0
            for e in range(1, 5):
                zp[e] = zp[e - 1] * current_z
                yp[e] = yp[e - 1] * current_y
            for m in range(n_mom):
                factor = zp[_QUARTIC_POWERS[m, 0]] * yp[_QUARTIC_POWERS[m, 1]]
                c = _QUARTIC_POWERS[m, 2]
                for q in range(15):
                    moments[q, m] += factor * rows[c, q]
            rows[:] = 0.0
            if i == count:
                break
            current_z = np.float64(xi[i, 0])
            current_y = np.float64(xi[i, 1])
        z = current_z
        y = current_y
        x = np.float64(xi[i, 2])
        monomials(z, y, x, nb, b)
        wz = cz + z
        wy = cy + y
        wx = cx + x
        for j in range(nb):
            wz += p[j] * b[j]
            wy += p[nb + j] * b[j]
            wx += p[2 * nb + j] * b[j]
        if not (0.0 <= wz <= nz - 1 and 0.0 <= wy <= ny - 1 and 0.0 <= wx <= nx - 1):
            continue
        f, fz, fy, fx = _value_and_gradient(coef, wz, wy, wx)
        used += 1
        sum_f += f
        sum_ff += f * f
        dg = g[i] - mean_g
        for k in range(3):
            gk = np.float64(grad[i, k])
            values[3 * k] = gk * fz
            values[3 * k + 1] = gk * fy
            values[3 * k + 2] = gk * fx
        values[9] = fz
        values[10] = fy
        values[11] = fx
        values[12] = fz * dg
        values[13] = fy * dg
        values[14] = fx * dg
        xc = 1.0
        for c in range(5):
            for q in range(15):
                rows[c, q] += values[q] * xc
            xc *= x
    cross = np.empty((m_par, m_par))
    for k in range(3):
        for l in range(3):
            q = 3 * k + l
            for j in range(nb):
                for j2 in range(nb):
                    cross[k * nb + j, l * nb + j2] = moments[q, _QUADRATIC_PRODUCT[j, j2]]
    sum_jf = np.empty(m_par)
    sum_jfg = np.empty(m_par)
    for l in range(3):
        for j in range(nb):
            sum_jf[l * nb + j] = moments[9 + l, _QUADRATIC_INDEX[j]]
            sum_jfg[l * nb + j] = moments[12 + l, _QUADRATIC_INDEX[j]]
    return cross, sum_jf, sum_jfg, used, sum_f, sum_ff


@njit(**KERNEL_OPTIONS)
def _sensitivity_sums(coef, g, grad, xi, count, mean_g, cz, cy, cx, p, nb):
    """:func:`_affine_sensitivity_sums` for any order (``Σ g_k f_l b_j b_j'`` per pair)."""
    nz, ny, nx = coef.shape
    m_par = 3 * nb
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
        monomials(np.float64(xi[i, 0]), np.float64(xi[i, 1]), np.float64(xi[i, 2]), nb, b)
        wz = cz + xi[i, 0]
        wy = cy + xi[i, 1]
        wx = cx + xi[i, 2]
        for j in range(nb):
            wz += p[j] * b[j]
            wy += p[nb + j] * b[j]
            wx += p[2 * nb + j] * b[j]
        if not (0.0 <= wz <= nz - 1 and 0.0 <= wy <= ny - 1 and 0.0 <= wx <= nx - 1):
            continue
        f, fz, fy, fx = sample_with_gradient_point(coef, wz, wy, wx)
        used += 1
        sum_f += f
        sum_ff += f * f
        dg = g[i] - mean_g
        for k in range(3):
            gk = np.float64(grad[i, k])
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
    return cross, sum_jf, sum_jfg, used, sum_f, sum_ff


@njit(parallel=True, **KERNEL_OPTIONS)
def subvolume_moments(reference, gradient, mask, use_mask, centers, half, nb, variance, power):
    """Gray variance and gradient power of each POI's reference subvolume, from plain sums.

    The noise stage's part of :func:`subvolume_statistics` (the same numbers, without ``H``):
    ``variance = Σ(g − ḡ)² / n`` and ``power = Σ |∇G|² / n`` over the ``n`` unmasked voxels,
    summed in float64 from the float32 volumes as there.

    Parameters
    ----------
    reference, gradient, mask, use_mask, centers, half, nb
        As in :func:`subvolume_statistics` (``nb`` only sets the ``3·nb + 3`` voxels needed).
    variance : ndarray (N,) float64, out
        Gray variance (gray levels²); NaN where fewer than ``3·nb + 3`` voxels are usable.
    power : ndarray (N,) float64, out
        Mean of ``|∇G|²`` (gray²/voxel²); NaN where the variance is.
    """
    m_par = 3 * nb
    for n in prange(centers.shape[0]):
        cz = centers[n, 0]
        cy = centers[n, 1]
        cx = centers[n, 2]
        count = 0
        sum_g = 0.0
        sum_power = 0.0
        for z in range(cz - half, cz + half + 1):
            for y in range(cy - half, cy + half + 1):
                for x in range(cx - half, cx + half + 1):
                    if use_mask and not mask[z, y, x]:
                        continue
                    sum_g += np.float64(reference[z, y, x])
                    for k in range(3):
                        gk = np.float64(gradient[k, z, y, x])
                        sum_power += gk * gk
                    count += 1
        variance[n] = np.nan
        power[n] = np.nan
        if count < m_par + 3:
            continue
        mean_g = sum_g / count
        ss_g = 0.0
        for z in range(cz - half, cz + half + 1):
            for y in range(cy - half, cy + half + 1):
                for x in range(cx - half, cx + half + 1):
                    if use_mask and not mask[z, y, x]:
                        continue
                    d = np.float64(reference[z, y, x]) - mean_g
                    ss_g += d * d
        delta_g = np.sqrt(ss_g)  # as reference_terms: Σ(g − ḡ)² through its square root
        variance[n] = delta_g * delta_g / count
        power[n] = sum_power / count


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
        g = np.empty(n_total, np.float32)  # exact copies, as in icgn.match_one
        grad = np.empty((n_total, 3), np.float32)
        xi = np.empty((n_total, 3), np.float32)
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
        if nb == 10:
            mean_g, delta_g, ok, low, sum_j, sum_jg = _quadratic_reference_terms(g, grad, xi, count)
        else:
            mean_g, delta_g, ok, low, sum_j, sum_jg = reference_terms(g, grad, xi, count, nb)
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
            ok_perp, low_perp = cholesky_solve_setup(h_perp, m_par)
            h_inv = np.empty(3)
            if ok_perp:
                translation_h_inverse(low_perp, m_par, nb, h_inv)
            for k in range(3):
                sigma[n, k] = np.sqrt(residual * h_inv[k]) if ok_perp else np.inf
            continue
        # A from the deformed volume's gradient at the warped voxels
        if nb == 4:
            cross, sum_jf, sum_jfg, used, sum_f, sum_ff = _affine_sensitivity_sums(
                coef_deformed, g, grad, xi, count, mean_g, cz, cy, cx, params[n]
            )
        elif nb == 10:
            cross, sum_jf, sum_jfg, used, sum_f, sum_ff = _quadratic_sensitivity_sums(
                coef_deformed, g, grad, xi, count, mean_g, cz, cy, cx, params[n]
            )
        else:
            cross, sum_jf, sum_jfg, used, sum_f, sum_ff = _sensitivity_sums(
                coef_deformed, g, grad, xi, count, mean_g, cz, cy, cx, params[n], nb
            )
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
        inverse = compose_inverse(identity, cross, m_par)
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
