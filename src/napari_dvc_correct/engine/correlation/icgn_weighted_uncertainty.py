"""Uncertainty of a weighted-subvolume match (:mod:`.icgn_weighted`): the weighted sandwich.

The weighted match solves ``Φ(p) = Σ w J_G⊥ᵀ r(p) = 0`` (``r = (g − ḡ) − (Δg/Δf)(f − f̄)``,
``⊥``: orthogonal, with the weights, to the gray offset and scale that ZNSSD ignores). Noise
moves the solution by ``δp = −A₁⁻¹ Φ`` with the sensitivity ``A₁ = (Δg/Δf) Σ w J_G⊥ J_Fᵀ``,
and ``Φ``'s covariance carries the weights squared, so

``Cov p = σ_r² A₁⁻¹ C A₁⁻ᵀ``,   ``C = (H₂⊥ + sym A₂⊥) / 2``

with ``H₂⊥ = Σ w² J⊥ J⊥ᵀ`` and ``A₂⊥ = (Δg/Δf) Σ w² J_G⊥ J_Fᵀ`` (the pairing of the reference's
noise in ``J_G`` and in ``r``, as :func:`.icgn_uncertainty.subvolume_statistics` derives it for
unit weights) and ``σ_r² = Σ w r² / (W − (3·nb + 2) W₂ / W)`` (``W = Σ w``, ``W₂ = Σ w²``).
Where the reference's noise adds little to ``H`` (not ``sensitive``) ``A = H₁⊥`` and
``C = H₂⊥``: ``Cov p = σ_r² H₁⊥⁻¹ H₂⊥ H₁⊥⁻¹``. With every weight 1 both are
:mod:`.icgn_uncertainty`'s estimates. Voxels, gray levels, axis order (z, y, x).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from .._numba_setup import KERNEL_OPTIONS
from .icgn_reference import (
    _QUADRATIC_INDEX,
    _QUADRATIC_PRODUCT,
    add_to_rows,
    fold_quartic_row,
)
from .shape_function import cholesky_solve_setup, inverse_rows, monomials
from .uncertainty_sums import value_and_gradient


@njit(**KERNEL_OPTIONS)
def weighted_sensitivity_sums(coef, g, grad, xi, w, count, mean_g, cz, cy, cx, p, nb):
    """One pass over the warped subvolume: ``Σ w J_G J_Fᵀ``, ``Σ w² J_G J_Fᵀ``, ``Σ w J_F``,
    ``Σ w (g − ḡ) J_F``, ``Σ w² J_F``, ``Σ w² (g − ḡ) J_F``, ``Σ w f``, ``Σ w f²`` and whether
    every voxel's warped position lies in ``F`` (``J_F = ∇F(W) ⊗ b``). Row sums folded into
    the moments of degree ≤ 4 (as :func:`.uncertainty_sums.quadratic_sensitivity_sums`)."""
    m_par = 3 * nb
    nz, ny, nx = coef.shape
    flat = coef.reshape(coef.size)
    moments = np.zeros((30, 35))
    rows = np.zeros((5, 30))
    values = np.empty(30)
    b = np.empty(10)
    zp = np.empty(5)
    yp = np.empty(5)
    sum_f = 0.0
    sum_ff = 0.0
    complete = True
    current_z = np.float64(xi[0, 0]) if count else 0.0
    current_y = np.float64(xi[0, 1]) if count else 0.0
    for i in range(count + 1):
        if i == count or xi[i, 0] != current_z or xi[i, 1] != current_y:
            fold_quartic_row(moments, rows, current_z, current_y, zp, yp)
            if i == count:
                break
            current_z = np.float64(xi[i, 0])
            current_y = np.float64(xi[i, 1])
        x = np.float64(xi[i, 2])
        monomials(current_z, current_y, x, nb, b)
        wz = cz + current_z
        wy = cy + current_y
        wx = cx + x
        for j in range(nb):
            wz += p[j] * b[j]
            wy += p[nb + j] * b[j]
            wx += p[2 * nb + j] * b[j]
        if not (0.0 <= wz <= nz - 1 and 0.0 <= wy <= ny - 1 and 0.0 <= wx <= nx - 1):
            complete = False
            continue
        f, fz, fy, fx = value_and_gradient(coef, flat, wz, wy, wx)
        weight = w[i]
        weight2 = weight * weight
        sum_f += weight * f
        sum_ff += weight * f * f
        dg = g[i] - mean_g
        for k in range(3):
            gk = np.float64(grad[i, k])
            values[3 * k] = weight * gk * fz
            values[3 * k + 1] = weight * gk * fy
            values[3 * k + 2] = weight * gk * fx
            values[9 + 3 * k] = weight2 * gk * fz
            values[9 + 3 * k + 1] = weight2 * gk * fy
            values[9 + 3 * k + 2] = weight2 * gk * fx
        for l in range(3):
            fl = fz if l == 0 else (fy if l == 1 else fx)
            values[18 + l] = weight * fl
            values[21 + l] = weight * fl * dg
            values[24 + l] = weight2 * fl
            values[27 + l] = weight2 * fl * dg
        add_to_rows(rows, values, x)
    cross1 = np.empty((m_par, m_par))
    cross2 = np.empty((m_par, m_par))
    for k in range(3):
        for l in range(3):
            q = 3 * k + l
            for j in range(nb):
                for j2 in range(nb):
                    cross1[k * nb + j, l * nb + j2] = moments[q, _QUADRATIC_PRODUCT[j, j2]]
                    cross2[k * nb + j, l * nb + j2] = moments[9 + q, _QUADRATIC_PRODUCT[j, j2]]
    linear = np.empty((4, m_par))
    for t in range(4):
        for l in range(3):
            for j in range(nb):
                linear[t, l * nb + j] = moments[18 + 3 * t + l, _QUADRATIC_INDEX[j]]
    return cross1, cross2, linear, sum_f, sum_ff, complete


@njit(**KERNEL_OPTIONS)
def weighted_sigma(
    coef_deformed, g, grad, xi, w, count, nb, mean_g, delta_g, second, sum_j, sum_jg, total,
    zncc, p, cz, cy, cx, noise_power, out,
):  # fmt: skip
    """The weighted sandwich uncertainty of a match, from the terms the weighted IC-GN holds
    (``second``: :func:`.icgn_weighted.weighted_terms`' last return): ``out[:3]`` the
    standard deviations of
    ``(uz, uy, ux)`` (voxels; NaN where they cannot be told, ``inf`` where ``A`` is singular),
    ``out[3]`` 1, or 2 where the weighted gradient power is below ``noise_power`` (then with the
    sensitivity pass). See :func:`weighted_sigma_at`."""
    sensitive = noise_power > 0.0 and second[7] < noise_power
    weighted_sigma_at(
        coef_deformed, g, grad, xi, w, count, nb, mean_g, delta_g, second, sum_j, sum_jg, total,
        zncc, p, cz, cy, cx, sensitive, out[:3],
    )  # fmt: skip
    out[3] = 2.0 if sensitive else 1.0


@njit(**KERNEL_OPTIONS)
def weighted_sigma_at(
    coef_deformed, g, grad, xi, w, count, nb, mean_g, delta_g, second, sum_j, sum_jg, total,
    zncc, p, cz, cy, cx, sensitive, out,
):  # fmt: skip
    """``out`` (3,): ``sqrt(diag(σ_r² A₁⁻¹ C A₁⁻ᵀ))`` at the translations (module docstring),
    from ``H₁``, ``H₂`` and the squared-weight sums of ``second``
    (:func:`.icgn_weighted.weighted_terms`), with the sensitivity measured from ``F`` where ``sensitive``; NaN where fewer than
    ``3·nb + 3`` voxels, no gray variance, no finite ZNCC or part of the warped subvolume
    outside ``F``."""
    m_par = 3 * nb
    for k in range(3):
        out[k] = np.nan
    if count < m_par + 3 or delta_g == 0.0 or not np.isfinite(zncc):
        return
    ss_g = delta_g * delta_g
    h1, h2, s2j, s2jd, total2, w2d, w2dd, _ = second
    m = sum_j / total
    c = sum_jg / ss_g
    h1p = np.empty((m_par, m_par))
    h2p = np.empty((m_par, m_par))
    for r in range(m_par):
        for q in range(r + 1):
            v = h1[r, q] - sum_j[r] * m[q] - sum_jg[r] * c[q]
            h1p[r, q] = v
            h1p[q, r] = v
        for q in range(m_par):
            h2p[r, q] = (
                h2[r, q]
                - s2j[r] * m[q] - m[r] * s2j[q] + total2 * m[r] * m[q]
                - s2jd[r] * c[q] - c[r] * s2jd[q] + w2dd * c[r] * c[q]
                + w2d * (m[r] * c[q] + c[r] * m[q])
            )  # fmt: skip
    dof = total - (m_par + 2) * total2 / total
    if not (dof > 0.0):
        return
    residual = 2.0 * ss_g * max(1.0 - zncc, 0.0) / dof
    if sensitive:
        cross1, cross2, linear, sum_f, sum_ff, complete = weighted_sensitivity_sums(
            coef_deformed, g, grad, xi, w, count, mean_g, cz, cy, cx, p, nb
        )
        if not complete:
            return
        ss_f = sum_ff - sum_f * sum_f / total
        if not (ss_f > 0.0):
            return
        ratio = delta_g / np.sqrt(ss_f)
        a1 = np.empty((m_par, m_par))
        a2 = np.empty((m_par, m_par))
        for r in range(m_par):
            for q in range(m_par):
                a1[r, q] = ratio * (cross1[r, q] - m[r] * linear[0, q] - c[r] * linear[1, q])
                a2[r, q] = ratio * (cross2[r, q] - m[r] * linear[2, q] - c[r] * linear[3, q])
        middle = np.empty((m_par, m_par))
        for r in range(m_par):
            for q in range(m_par):
                middle[r, q] = 0.5 * h2p[r, q] + 0.25 * (a2[r, q] + a2[q, r])
    else:
        ok, _ = cholesky_solve_setup(h1p, m_par)
        if not ok:
            for k in range(3):
                out[k] = np.inf
            return
        a1 = h1p
        middle = h2p
    translations = np.array([0, nb, 2 * nb])
    inverse = inverse_rows(a1, translations, m_par)  # A₁⁻¹ at the translations
    for k in range(3):
        quad = 0.0
        for r in range(m_par):
            t = 0.0
            for q in range(m_par):
                t += middle[r, q] * inverse[k, q]
            quad += inverse[k, r] * t
        value = np.sqrt(residual * max(quad, 0.0))
        out[k] = value if np.isfinite(value) else np.inf
