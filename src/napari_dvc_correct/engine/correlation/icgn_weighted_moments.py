"""The reference side of a weighted-subvolume match in one pass over its voxels.

The weighted IC-GN (:mod:`.icgn_weighted`) needs ``H₁ = Σ w JᵀJ``, ``Σ w J`` and
``Σ w J (g − ḡ)``; its uncertainty (:mod:`.icgn_weighted_uncertainty`) needs the same with the
weights squared, ``H₂ = Σ w² JᵀJ``, ``Σ w² J`` and ``Σ w² J (g − ḡ)``, and the scalars ``W₂ = Σ w²``,
``Σ w² (g − ḡ)``, ``Σ w² (g − ḡ)²`` and the weighted gradient power ``Σ w |∇G|² / W``. Each
Hessian entry ``Σ c g_k g_k' b_j b_j'`` (``c = w`` or ``w²``, ``J = ∇G ⊗ b``) is one of the
6 gradient products times one of the 35 monomials of degree ≤ 4: along each x-row the 12
products (6 per weight) are summed times ``1 … x⁴`` in registers and folded into the moments
once per row, as :func:`.icgn_reference.quadratic_reference_terms` does for unit weights. Both
Hessians come out whole (no factor to rebuild them from). Voxels in (z, y, x) row order;
gray levels, voxels.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from .._numba_setup import FAST_KERNEL_OPTIONS, KERNEL_OPTIONS
from .icgn_reference import (
    _PAIR,
    _QUADRATIC_POWERS,
    _QUADRATIC_PRODUCT,
    _QUARTIC_POWERS,
    _fold_moments,
)


@njit(inline="always", **FAST_KERNEL_OPTIONS)
def _row_products(grad, xi, w, squared, start, end, rows, q0):
    """One row's sums of ``c g_k g_k'`` (``c = w``, or ``w²`` where ``squared``) times
    ``1 … x⁴`` into ``rows[0:5, q0:q0 + 6]`` (QUAD_AXES order of the products)."""
    a00 = a01 = a02 = a03 = a04 = a05 = 0.0
    a10 = a11 = a12 = a13 = a14 = a15 = 0.0
    a20 = a21 = a22 = a23 = a24 = a25 = 0.0
    a30 = a31 = a32 = a33 = a34 = a35 = 0.0
    a40 = a41 = a42 = a43 = a44 = a45 = 0.0
    for i in range(start, end):
        c = w[i] * w[i] if squared else w[i]
        gz = np.float64(grad[i, 0])
        gy = np.float64(grad[i, 1])
        gx = np.float64(grad[i, 2])
        x = np.float64(xi[i, 2])
        x2 = x * x
        x3 = x2 * x
        x4 = x2 * x2
        cz = c * gz
        cy = c * gy
        p0, p1, p2, p3, p4, p5 = cz * gz, cy * gy, c * gx * gx, cz * gy, cy * gx, cz * gx
        a00 += p0
        a01 += p1
        a02 += p2
        a03 += p3
        a04 += p4
        a05 += p5
        a10 += p0 * x
        a11 += p1 * x
        a12 += p2 * x
        a13 += p3 * x
        a14 += p4 * x
        a15 += p5 * x
        a20 += p0 * x2
        a21 += p1 * x2
        a22 += p2 * x2
        a23 += p3 * x2
        a24 += p4 * x2
        a25 += p5 * x2
        a30 += p0 * x3
        a31 += p1 * x3
        a32 += p2 * x3
        a33 += p3 * x3
        a34 += p4 * x3
        a35 += p5 * x3
        a40 += p0 * x4
        a41 += p1 * x4
        a42 += p2 * x4
        a43 += p3 * x4
        a44 += p4 * x4
        a45 += p5 * x4
    sums = (
        (a00, a01, a02, a03, a04, a05),
        (a10, a11, a12, a13, a14, a15),
        (a20, a21, a22, a23, a24, a25),
        (a30, a31, a32, a33, a34, a35),
        (a40, a41, a42, a43, a44, a45),
    )
    for power in range(5):
        row = sums[power]
        for q in range(6):
            rows[power, q0 + q] = row[q]


@njit(inline="always", **FAST_KERNEL_OPTIONS)
def _row_linear(g, grad, xi, w, squared, mean_g, start, end, rows, q0):
    """One row's sums of ``c g_k`` and ``c g_k (g − ḡ)`` (``c = w``, or ``w²`` where
    ``squared``) times ``1, x, x²`` into ``rows[0:3, q0:q0 + 6]``."""
    b00 = b01 = b02 = b03 = b04 = b05 = 0.0
    b10 = b11 = b12 = b13 = b14 = b15 = 0.0
    b20 = b21 = b22 = b23 = b24 = b25 = 0.0
    for i in range(start, end):
        c = w[i] * w[i] if squared else w[i]
        x = np.float64(xi[i, 2])
        x2 = x * x
        gz = c * np.float64(grad[i, 0])
        gy = c * np.float64(grad[i, 1])
        gx = c * np.float64(grad[i, 2])
        dg = g[i] - mean_g
        hz, hy, hx = gz * dg, gy * dg, gx * dg
        b00 += gz
        b01 += gy
        b02 += gx
        b03 += hz
        b04 += hy
        b05 += hx
        b10 += gz * x
        b11 += gy * x
        b12 += gx * x
        b13 += hz * x
        b14 += hy * x
        b15 += hx * x
        b20 += gz * x2
        b21 += gy * x2
        b22 += gx * x2
        b23 += hz * x2
        b24 += hy * x2
        b25 += hx * x2
    sums = ((b00, b01, b02, b03, b04, b05), (b10, b11, b12, b13, b14, b15),
            (b20, b21, b22, b23, b24, b25))  # fmt: skip
    for power in range(3):
        row = sums[power]
        for q in range(6):
            rows[power, q0 + q] = row[q]


@njit(**KERNEL_OPTIONS)
def weighted_reference_moments(g, grad, xi, w, count, nb):
    """Everything a weighted match and its uncertainty read from the reference subvolume.

    Parameters
    ----------
    g : (count,) float32 or float64
        Gray levels of the subvolume's voxels, in (z, y, x) row order.
    grad : (count, 3) float32 or float64
        ``∇G`` at those voxels, (z, y, x) components, gray levels per voxel.
    xi : (count, 3) float32 or float64
        The voxels' local coordinates (z, y, x), voxels.
    w : (count,) float64
        Weights, ≥ 0, not all 0.
    count, nb : int
        Voxels used; monomials of the shape function (4 or 10).

    Returns
    -------
    tuple
        ``(ḡ, Σ w (g − ḡ)², W, W₂, Σ w² (g − ḡ), Σ w² (g − ḡ)², Σ w |∇G|² / W, H₁, H₂,
        Σ w J, Σ w J (g − ḡ), Σ w² J, Σ w² J (g − ḡ))`` with ``ḡ = Σ w g / W``; the Hessians
        (3·nb, 3·nb) and the sums (3·nb,), parameters in (z, y, x) blocks of ``nb``. Every sum
        is float64.
    """
    m_par = 3 * nb
    total = 0.0
    sum_g = 0.0
    for i in range(count):
        total += w[i]
        sum_g += w[i] * g[i]
    mean_g = sum_g / total
    ss_g = 0.0
    total2 = 0.0
    w2d = 0.0
    w2dd = 0.0
    power = 0.0
    products = np.zeros((12, _QUARTIC_POWERS.shape[0]))  # w g_k g_k', w² g_k g_k' · z^a y^b x^c
    linear = np.zeros((12, 10))  # w g_k, w g_k dg, w² g_k, w² g_k dg · b_j
    rows = np.empty((5, 12))
    linear_rows = np.empty((3, 12))
    zp = np.empty(5)
    yp = np.empty(5)
    start = 0
    while start < count:
        end = start + 1
        while end < count and xi[end, 0] == xi[start, 0] and xi[end, 1] == xi[start, 1]:
            end += 1
        for i in range(start, end):
            weight = w[i]
            weight2 = weight * weight
            dg = g[i] - mean_g
            ss_g += weight * dg * dg
            total2 += weight2
            w2d += weight2 * dg
            w2dd += weight2 * dg * dg
            for k in range(3):
                power += weight * np.float64(grad[i, k]) ** 2
        _row_products(grad, xi, w, False, start, end, rows, 0)
        _row_products(grad, xi, w, True, start, end, rows, 6)
        _row_linear(g, grad, xi, w, False, mean_g, start, end, linear_rows, 0)
        _row_linear(g, grad, xi, w, True, mean_g, start, end, linear_rows, 6)
        z = np.float64(xi[start, 0])
        y = np.float64(xi[start, 1])
        _fold_moments(products, rows, _QUARTIC_POWERS, z, y, zp, yp)
        _fold_moments(linear, linear_rows, _QUADRATIC_POWERS, z, y, zp, yp)
        start = end
    h1 = np.empty((m_par, m_par))
    h2 = np.empty((m_par, m_par))
    sum_j = np.empty(m_par)
    sum_jg = np.empty(m_par)
    s2j = np.empty(m_par)
    s2jd = np.empty(m_par)
    for k in range(3):
        for j in range(nb):
            r = k * nb + j
            sum_j[r] = linear[k, j]
            sum_jg[r] = linear[3 + k, j]
            s2j[r] = linear[6 + k, j]
            s2jd[r] = linear[9 + k, j]
            for k2 in range(3):
                q = _PAIR[k, k2]
                for j2 in range(nb):
                    m = _QUADRATIC_PRODUCT[j, j2]
                    h1[r, k2 * nb + j2] = products[q, m]
                    h2[r, k2 * nb + j2] = products[6 + q, m]
    return (mean_g, ss_g, total, total2, w2d, w2dd, power / total, h1, h2, sum_j, sum_jg, s2j,
            s2jd)  # fmt: skip
