"""The per-voxel sums of the uncertainty estimate (:func:`.icgn_uncertainty.subvolume_statistics`).

One pass over a subvolume each: the sensitivity ``A``'s sums over the deformed volume at the warped
voxels (:func:`affine_sensitivity_sums` for first order, :func:`quadratic_sensitivity_sums` for
second, :func:`sensitivity_sums` for any); the reference's ``H``, ``Σ J`` and ``Σ J (g − ḡ)`` come
from :func:`.icgn_reference.reference_terms`, as in IC-GN. The fast ones sum each x-row times powers of
``x`` and fold the rows into moments of the local coordinates (voxels, axis order (z, y, x)).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from .._numba_setup import KERNEL_OPTIONS
from .icgn_reference import (
    _QUADRATIC_INDEX,
    _QUADRATIC_PRODUCT,
    _QUARTIC_POWERS,
    add_to_rows,
    fold_quartic_row,
    fold_row,
)
from .interpolation import sample_with_gradient_point
from .shape_function import PRODUCT_TABLE, monomials
from .simd_taps import sample_with_gradient_interior_vector


@njit(inline="always", **KERNEL_OPTIONS)
def value_and_gradient(coefficients, flat, z, y, x):
    """:func:`.sample_with_gradient_point`, four-wide where all 64 taps are inside.

    ``flat`` is ``coefficients`` (C-contiguous) as 1-D. Interior positions go through
    :func:`.simd_taps.taps64_with_gradient` (float32 tap sums, as IC-GN's sampling), the others
    through the mirrored scalar path; returns float64 values.
    """
    nz, ny, nx = coefficients.shape
    if not (1.0 <= z < nz - 2.0 and 1.0 <= y < ny - 2.0 and 1.0 <= x < nx - 2.0):
        return sample_with_gradient_point(coefficients, z, y, x)
    v, gz, gy, gx = sample_with_gradient_interior_vector(flat, ny * nx, nx, z, y, x)
    return np.float64(v), np.float64(gz), np.float64(gy), np.float64(gx)


@njit(**KERNEL_OPTIONS)
def affine_sensitivity_sums(coef, g, grad, xi, count, mean_g, cz, cy, cx, p):
    """First order: ``Σ J_G ⊗ ∇F(W) b bᵀ`` (as 9 × 10 moments), ``Σ J_F``, ``Σ J_F (g − ḡ)``, ``Σf``,
    ``Σf²`` and the voxels used, in one pass with x-row sums folded into the moments (as in
    :func:`.icgn_reference.affine_terms`)."""
    nz, ny, nx = coef.shape
    flat = coef.reshape(coef.size)
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
        f, fz, fy, fx = value_and_gradient(coef, flat, wz, wy, wx)
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


@njit(**KERNEL_OPTIONS)
def quadratic_sensitivity_sums(coef, g, grad, xi, count, mean_g, cz, cy, cx, p):
    """Second order: :func:`sensitivity_sums` with the 15 per-voxel quantities (``g_k f_l``,
    ``f_l``, ``f_l (g − ḡ)``) summed along each x-row times ``1 … x⁴`` and folded into the 35
    moments ``z^a y^b x^c`` (degree ≤ 4) once per row, as :func:`affine_sensitivity_sums`."""
    nb = 10
    m_par = 30
    nz, ny, nx = coef.shape
    flat = coef.reshape(coef.size)
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
            fold_quartic_row(moments, rows, current_z, current_y, zp, yp)
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
        f, fz, fy, fx = value_and_gradient(coef, flat, wz, wy, wx)
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
        add_to_rows(rows, values, x)
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
def sensitivity_sums(coef, g, grad, xi, count, mean_g, cz, cy, cx, p, nb):
    """:func:`affine_sensitivity_sums` for any order (``Σ g_k f_l b_j b_j'`` per pair)."""
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
