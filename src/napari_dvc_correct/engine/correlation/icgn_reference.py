"""The reference side of IC-GN, computed once per POI: gradients, steepest-descent terms, Hessian.

``∇G`` of the whole reference volume (from its B-spline coefficients), then per subvolume the
steepest-descent images ``J = ∇G · ∂W/∂p`` summed into the Hessian ``H = Σ JᵀJ`` (in moments of
the local coordinates for the affine part), and the translation entries of ``H⁻¹``.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from .._numba_setup import FAST_KERNEL_OPTIONS, KERNEL_OPTIONS
from .interpolation import _mirror
from .shape_function import PRODUCT_TABLE, cholesky_solve, cholesky_solve_setup

#: z-planes of :func:`gradient_volume` per parallel task (each task re-reads two planes around).
GRADIENT_PLANES_PER_TASK = 8


@njit(inline="always", **KERNEL_OPTIONS)
def _plane_terms(coefficients, plane, rows, x0, x_below, x_above, value_x, deriv_x, value_yx,
                 deriv_y, deriv_x_value_y):  # fmt: skip
    """One coefficient plane's x- then y-passes over a window: ``s_y s_x c``, ``d_y s_x c`` and
    ``s_y d_x c``.

    ``s = (1, 4, 1) / 6`` and ``d = (-1, 0, 1) / 2`` are the cubic B-spline's value and
    derivative weights at integer positions (taps ``i - 1, i, i + 1``). The window's ``n`` rows
    ``y0 … y0 + n - 1`` and ``m`` columns ``x0 … x0 + m - 1``: ``rows`` (n + 2,) holds the
    coefficient row of each virtual row ``y0 - 1 … y0 + n`` and ``x_below``, ``x_above`` (m,) the
    columns ``x - 1`` and ``x + 1``, mirrored at the volume's faces. ``value_x`` and ``deriv_x``
    (n + 2, m) are scratch; the three outputs are (n, m).
    """
    n_rows, m = value_x.shape
    for r in range(n_rows):
        row = coefficients[plane, rows[r]]
        for j in range(m):
            left = np.float64(row[x_below[j]])
            right = np.float64(row[x_above[j]])
            value_x[r, j] = (left + 4.0 * np.float64(row[x0 + j]) + right) / 6.0
            deriv_x[r, j] = 0.5 * (right - left)
    for r in range(n_rows - 2):
        for j in range(m):
            value_yx[r, j] = (value_x[r, j] + 4.0 * value_x[r + 1, j] + value_x[r + 2, j]) / 6.0
            deriv_y[r, j] = 0.5 * (value_x[r + 2, j] - value_x[r, j])
            deriv_x_value_y[r, j] = (
                deriv_x[r, j] + 4.0 * deriv_x[r + 1, j] + deriv_x[r + 2, j]
            ) / 6.0


@njit(inline="always", **KERNEL_OPTIONS)
def _z_pass(value, deriv_y, deriv_x_value_y, virtual, out, iz):
    """The z-pass of output plane ``iz`` from the ring of three planes' terms (slot ``v % 3``
    holds virtual plane ``v``; ``virtual`` is the one above ``iz``)."""
    low = (virtual - 2) % 3
    mid = (virtual - 1) % 3
    high = virtual % 3
    n, m = value.shape[1], value.shape[2]
    for r in range(n):
        for j in range(m):
            out[0, iz, r, j] = 0.5 * (value[high, r, j] - value[low, r, j])
            out[1, iz, r, j] = (
                deriv_y[low, r, j] + 4.0 * deriv_y[mid, r, j] + deriv_y[high, r, j]
            ) / 6.0
            out[2, iz, r, j] = (
                deriv_x_value_y[low, r, j]
                + 4.0 * deriv_x_value_y[mid, r, j]
                + deriv_x_value_y[high, r, j]
            ) / 6.0


@njit(**KERNEL_OPTIONS)
def _window_gradient(coefficients, z0, y0, x0, nz_out, ny_out, nx_out, out, out_z):
    """:func:`gradient_volume` on the window of ``nz_out × ny_out × nx_out`` voxels from
    ``(z0, y0, x0)`` into planes ``out_z … out_z + nz_out - 1`` of ``out`` (3, ·, ny_out, nx_out)
    float32: per virtual plane ``z0 - 1 … z0 + nz_out`` (mirrored) an x- and a y-pass, then the
    z-pass over a ring of three planes. Sums in float64; a voxel's value does not depend on the
    window."""
    nz, ny, nx = coefficients.shape
    rows = np.empty(ny_out + 2, np.int64)
    for r in range(ny_out + 2):
        rows[r] = _mirror(y0 - 1 + r, ny)
    x_below = np.empty(nx_out, np.int64)
    x_above = np.empty(nx_out, np.int64)
    for j in range(nx_out):
        x_below[j] = _mirror(x0 + j - 1, nx)
        x_above[j] = _mirror(x0 + j + 1, nx)
    value_x = np.empty((ny_out + 2, nx_out))
    deriv_x = np.empty((ny_out + 2, nx_out))
    value = np.empty((3, ny_out, nx_out))
    deriv_y = np.empty((3, ny_out, nx_out))
    deriv_x_value_y = np.empty((3, ny_out, nx_out))
    for virtual in range(nz_out + 2):
        slot = virtual % 3
        _plane_terms(coefficients, _mirror(z0 - 1 + virtual, nz), rows, x0, x_below, x_above,
                     value_x, deriv_x, value[slot], deriv_y[slot], deriv_x_value_y[slot])  # fmt: skip
        if virtual >= 2:
            _z_pass(value, deriv_y, deriv_x_value_y, virtual, out, out_z + virtual - 2)


@njit(parallel=True, **KERNEL_OPTIONS)
def gradient_volume(coefficients):
    """Gradient of the B-spline interpolant at every voxel, shape (3, nz, ny, nx), float32.

    At integer positions the cubic B-spline weights are ``(1, 4, 1) / 6`` and the derivative
    weights ``(-1, 0, 1) / 2``, so the gradient is a 3×3×3 stencil on the coefficients (mirrored
    taps), applied here separably (:func:`_window_gradient`, one task per
    :data:`GRADIENT_PLANES_PER_TASK` output planes). Sums in float64.
    """
    nz, ny, nx = coefficients.shape
    out = np.empty((3, nz, ny, nx), np.float32)
    per_task = GRADIENT_PLANES_PER_TASK
    n_tasks = (nz + per_task - 1) // per_task
    for task in prange(n_tasks):
        z0 = task * per_task
        z1 = min(nz, z0 + per_task)
        _window_gradient(coefficients, z0, 0, 0, z1 - z0, ny, nx, out, z0)
    return out


@njit(**KERNEL_OPTIONS)
def subvolume_gradient(coefficients, cz, cy, cx, half):
    """:func:`gradient_volume`'s values on the subvolume of half size ``half`` around
    ``(cz, cy, cx)`` (inside the volume), shape (3, 2·half + 1, 2·half + 1, 2·half + 1) float32,
    equal bit for bit to the whole volume's there."""
    edge = 2 * half + 1
    out = np.empty((3, edge, edge, edge), np.float32)
    _window_gradient(coefficients, cz - half, cy - half, cx - half, edge, edge, edge, out, 0)
    return out


@njit(**KERNEL_OPTIONS)
def gradient_source(gradient, cz, cy, cx, half):
    """Where a subvolume's ``∇G`` is read: ``(array, oz, oy, ox)``, voxel ``(z, y, x)`` at
    ``array[:, z - oz, y - oy, x - ox]``.

    ``gradient`` is ``∇G`` (3, nz, ny, nx), returned as it is with offsets 0, or ``G``'s B-spline
    coefficients (1, nz, ny, nx), from which the subvolume's ``∇G`` is computed here
    (:func:`subvolume_gradient`): the same values without a volume of 12 bytes per voxel.
    """
    if gradient.shape[0] == 3:
        return gradient, 0, 0, 0
    block = subvolume_gradient(gradient[0], cz, cy, cx, half)
    return block, cz - half, cy - half, cx - half


_PAIR = np.array([[0, 3, 5], [3, 1, 4], [5, 4, 2]], dtype=np.int64)  # (k, k') -> QUAD_AXES row


@njit(inline="always", **KERNEL_OPTIONS)
def fold_row(moments, row0, row1, row2, z, y, n):
    """Add one (z, y) row's sums to the moments and clear them.

    ``row0[q]``, ``row1[q]`` and ``row2[q]`` hold a row's sums of quantity ``q`` times 1, x and
    x²; ``moments[q]`` gathers ``Σ 1, z, y, x, z², y², x², zy, yx, zx`` times the quantity over
    the rows folded so far (the affine shape function's products, 10 per quantity).
    """
    for q in range(n):
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


@njit(**FAST_KERNEL_OPTIONS)
def affine_terms(g, grad, xi, count, mean_g):
    """First order in one pass: ``Σ(g − ḡ)²``, ``H = Σ JᵀJ``, ``Σ J`` and ``Σ J (g − ḡ)``.

    ``H[(k, j), (k', j')] = Σ g_k g_k' b_j b_j'`` and ``b_j b_j'`` is one of the 10 monomials of
    degree ≤ 2, so 6 × 10 moments suffice. Voxels come in (z, y, x) row order: along each x-row
    the sums of ``g_k g_k' · (1, x, x²)``, ``g_k · (1, x)`` and ``g_k (g − ḡ) · (1, x)`` are
    kept in registers and folded into the moments once per row. Inputs may be float32 (the
    gathered subvolume); every product and sum is float64.
    """
    moments = np.zeros((6, 10))
    row0 = np.empty(6)
    row1 = np.empty(6)
    row2 = np.empty(6)
    sum_j = np.zeros(12)
    sum_jg = np.zeros(12)
    ss_g = 0.0
    start = 0
    while start < count:
        end = start + 1
        while end < count and xi[end, 0] == xi[start, 0] and xi[end, 1] == xi[start, 1]:
            end += 1
        q0 = q1 = q2 = q3 = q4 = q5 = 0.0  # Σ g_k g_k'
        x0 = x1 = x2 = x3 = x4 = x5 = 0.0  # Σ g_k g_k' x
        w0 = w1 = w2 = w3 = w4 = w5 = 0.0  # Σ g_k g_k' x²
        j0 = j1 = j2 = jx0 = jx1 = jx2 = 0.0  # Σ g_k, Σ g_k x
        h0 = h1 = h2 = hx0 = hx1 = hx2 = 0.0  # Σ g_k dg, Σ g_k x dg
        ss = 0.0
        for i in range(start, end):
            gz = np.float64(grad[i, 0])
            gy = np.float64(grad[i, 1])
            gx = np.float64(grad[i, 2])
            x = np.float64(xi[i, 2])
            xx = x * x
            p0 = gz * gz
            p1 = gy * gy
            p2 = gx * gx
            p3 = gz * gy
            p4 = gy * gx
            p5 = gz * gx
            q0 += p0
            q1 += p1
            q2 += p2
            q3 += p3
            q4 += p4
            q5 += p5
            x0 += p0 * x
            x1 += p1 * x
            x2 += p2 * x
            x3 += p3 * x
            x4 += p4 * x
            x5 += p5 * x
            w0 += p0 * xx
            w1 += p1 * xx
            w2 += p2 * xx
            w3 += p3 * xx
            w4 += p4 * xx
            w5 += p5 * xx
            dg = g[i] - mean_g
            ss += dg * dg
            j0 += gz
            j1 += gy
            j2 += gx
            jx0 += gz * x
            jx1 += gy * x
            jx2 += gx * x
            h0 += gz * dg
            h1 += gy * dg
            h2 += gx * dg
            hx0 += gz * x * dg
            hx1 += gy * x * dg
            hx2 += gx * x * dg
        ss_g += ss
        z = np.float64(xi[start, 0])
        y = np.float64(xi[start, 1])
        row0[0], row0[1], row0[2], row0[3], row0[4], row0[5] = q0, q1, q2, q3, q4, q5
        row1[0], row1[1], row1[2], row1[3], row1[4], row1[5] = x0, x1, x2, x3, x4, x5
        row2[0], row2[1], row2[2], row2[3], row2[4], row2[5] = w0, w1, w2, w3, w4, w5
        fold_row(moments, row0, row1, row2, z, y, 6)
        _fold_gradient(sum_j, sum_jg, 0, j0, jx0, h0, hx0, z, y)
        _fold_gradient(sum_j, sum_jg, 1, j1, jx1, h1, hx1, z, y)
        _fold_gradient(sum_j, sum_jg, 2, j2, jx2, h2, hx2, z, y)
        start = end
    hessian = np.empty((12, 12))
    for k in range(3):
        for j in range(4):
            for k2 in range(3):
                for j2 in range(4):
                    hessian[k * 4 + j, k2 * 4 + j2] = moments[_PAIR[k, k2], PRODUCT_TABLE[j, j2]]
    return ss_g, hessian, sum_j, sum_jg


@njit(inline="always", **KERNEL_OPTIONS)
def _fold_gradient(sum_j, sum_jg, k, s, sx, t, tx, z, y):
    """Add one row's ``Σ g_k (1, x)`` and ``Σ g_k dg (1, x)`` to ``Σ J`` and ``Σ J dg``."""
    sum_j[4 * k] += s
    sum_j[4 * k + 1] += z * s
    sum_j[4 * k + 2] += y * s
    sum_j[4 * k + 3] += sx
    sum_jg[4 * k] += t
    sum_jg[4 * k + 1] += z * t
    sum_jg[4 * k + 2] += y * t
    sum_jg[4 * k + 3] += tx


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


@njit(inline="always", **KERNEL_OPTIONS)
def _fold_moments(moments, rows, powers, z, y, zp, yp):
    """Add one (z, y) row's sums ``rows[c, q]`` (quantity ``q`` times ``x^c``) to
    ``moments[q, m]``, quantity ``q`` times the monomial ``z^a y^b x^c`` of ``powers`` row ``m``.
    ``zp`` and ``yp`` (5,) are scratch for the powers."""
    zp[0] = 1.0
    yp[0] = 1.0
    for e in range(1, 5):
        zp[e] = zp[e - 1] * z
        yp[e] = yp[e - 1] * y
    for m in range(powers.shape[0]):
        factor = zp[powers[m, 0]] * yp[powers[m, 1]]
        c = powers[m, 2]
        for q in range(moments.shape[0]):
            moments[q, m] += factor * rows[c, q]


_QUADRATIC_POWERS = _QUARTIC_POWERS[_QUADRATIC_INDEX]  # the 10 b_j, as z^a y^b x^c


@njit(inline="always", **KERNEL_OPTIONS)
def fold_quartic_row(moments, rows, z, y, zp, yp):
    """Add one (z, y) row's sums to the 35 quartic moments and clear them.

    ``rows[c, q]`` holds the row's sum of quantity ``q`` times ``x^c`` (c = 0 … 4);
    ``moments[q, m]`` gathers quantity ``q`` times the monomial ``z^a y^b x^c`` of
    :data:`_QUARTIC_POWERS` row ``m``. ``zp`` and ``yp`` (5,) are scratch for the powers.
    """
    _fold_moments(moments, rows, _QUARTIC_POWERS, z, y, zp, yp)
    rows[:] = 0.0


@njit(inline="always", **KERNEL_OPTIONS)
def add_to_rows(rows, values, x):
    """Add one voxel's quantities times ``1, x, … x⁴`` to its row's sums ``rows[c, q]`` (see
    :func:`fold_quartic_row`)."""
    xc = 1.0
    for c in range(rows.shape[0]):
        for q in range(values.shape[0]):
            rows[c, q] += values[q] * xc
        xc *= x


@njit(**FAST_KERNEL_OPTIONS)
def quadratic_reference_terms(g, grad, xi, count):
    """Second order: :func:`.icgn_reference.reference_terms` (same returns) from moments.

    ``H[(k, j), (k', j')] = Σ g_k g_k' b_j b_j'``, ``Σ J = Σ g_k b_j`` and ``Σ J (g − ḡ)``: the
    6 products ``g_k g_k'`` times the 35 monomials of degree ≤ 4, the 3 ``g_k`` and the 3
    ``g_k (g − ḡ)`` times the 10 ``b_j`` (degree ≤ 2). Voxels come in (z, y, x) row order: along
    each x-row the sums of the products times ``1 … x⁴`` (``a{c}{q}``, 30) and of the six others
    times ``1, x, x²`` (``b{c}{q}``, 18) are kept in registers, then folded into the moments once
    per row. Inputs may be float32 (the gathered subvolume); every product and sum is float64.
    """
    nb = 10
    m_par = 30
    mean_g = 0.0
    for i in range(count):
        mean_g += g[i]
    mean_g /= max(count, 1)
    ss_g = 0.0
    for i in range(count):
        d = g[i] - mean_g
        ss_g += d * d
    products = np.zeros((6, _QUARTIC_POWERS.shape[0]))  # g_k g_k' (QUAD_AXES order) · z^a y^b x^c
    linear = np.zeros((6, nb))  # g_z, g_y, g_x, g_z dg, g_y dg, g_x dg · b_j
    rows = np.empty((5, 6))
    linear_rows = np.empty((3, 6))
    zp = np.empty(5)
    yp = np.empty(5)
    start = 0
    while start < count:
        end = start + 1
        while end < count and xi[end, 0] == xi[start, 0] and xi[end, 1] == xi[start, 1]:
            end += 1
        a00 = a01 = a02 = a03 = a04 = a05 = 0.0
        a10 = a11 = a12 = a13 = a14 = a15 = 0.0
        a20 = a21 = a22 = a23 = a24 = a25 = 0.0
        a30 = a31 = a32 = a33 = a34 = a35 = 0.0
        a40 = a41 = a42 = a43 = a44 = a45 = 0.0
        b00 = b01 = b02 = b03 = b04 = b05 = 0.0
        b10 = b11 = b12 = b13 = b14 = b15 = 0.0
        b20 = b21 = b22 = b23 = b24 = b25 = 0.0
        for i in range(start, end):
            gz = np.float64(grad[i, 0])
            gy = np.float64(grad[i, 1])
            gx = np.float64(grad[i, 2])
            x = np.float64(xi[i, 2])
            x2 = x * x
            x3 = x2 * x
            x4 = x2 * x2
            p0, p1, p2, p3, p4, p5 = gz * gz, gy * gy, gx * gx, gz * gy, gy * gx, gz * gx
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
        rows[0, 0], rows[0, 1], rows[0, 2], rows[0, 3], rows[0, 4], rows[0, 5] = (
            a00, a01, a02, a03, a04, a05
        )  # fmt: skip
        rows[1, 0], rows[1, 1], rows[1, 2], rows[1, 3], rows[1, 4], rows[1, 5] = (
            a10, a11, a12, a13, a14, a15
        )  # fmt: skip
        rows[2, 0], rows[2, 1], rows[2, 2], rows[2, 3], rows[2, 4], rows[2, 5] = (
            a20, a21, a22, a23, a24, a25
        )  # fmt: skip
        rows[3, 0], rows[3, 1], rows[3, 2], rows[3, 3], rows[3, 4], rows[3, 5] = (
            a30, a31, a32, a33, a34, a35
        )  # fmt: skip
        rows[4, 0], rows[4, 1], rows[4, 2], rows[4, 3], rows[4, 4], rows[4, 5] = (
            a40, a41, a42, a43, a44, a45
        )  # fmt: skip
        linear_rows[0, 0], linear_rows[0, 1], linear_rows[0, 2] = b00, b01, b02
        linear_rows[0, 3], linear_rows[0, 4], linear_rows[0, 5] = b03, b04, b05
        linear_rows[1, 0], linear_rows[1, 1], linear_rows[1, 2] = b10, b11, b12
        linear_rows[1, 3], linear_rows[1, 4], linear_rows[1, 5] = b13, b14, b15
        linear_rows[2, 0], linear_rows[2, 1], linear_rows[2, 2] = b20, b21, b22
        linear_rows[2, 3], linear_rows[2, 4], linear_rows[2, 5] = b23, b24, b25
        z = np.float64(xi[start, 0])
        y = np.float64(xi[start, 1])
        _fold_moments(products, rows, _QUARTIC_POWERS, z, y, zp, yp)
        _fold_moments(linear, linear_rows, _QUADRATIC_POWERS, z, y, zp, yp)
        start = end
    hessian = np.empty((m_par, m_par))
    sum_j = np.empty(m_par)
    sum_jg = np.empty(m_par)
    for k in range(3):
        for j in range(nb):
            sum_j[k * nb + j] = linear[k, j]
            sum_jg[k * nb + j] = linear[3 + k, j]
            for k2 in range(3):
                for j2 in range(nb):
                    value = products[_PAIR[k, k2], _QUADRATIC_PRODUCT[j, j2]]
                    hessian[k * nb + j, k2 * nb + j2] = value
    delta_g = np.sqrt(ss_g)
    ok, low = cholesky_solve_setup(hessian, m_par)
    return mean_g, delta_g, ok, low, sum_j, sum_jg


@njit(**KERNEL_OPTIONS)
def reference_terms(g, grad, xi, count, nb):
    """Mean and norm of the reference subvolume, Cholesky factor of H = Σ JᵀJ, Σ J, Σ J (g − ḡ).

    ``g`` (count,), ``grad`` and ``xi`` (count, 3) may be float32; the sums are float64.
    """
    if nb != 4:
        return quadratic_reference_terms(g, grad, xi, count)
    mean_g = 0.0
    for i in range(count):
        mean_g += g[i]
    mean_g /= max(count, 1)
    ss_g, hessian, sum_j, sum_jg = affine_terms(g, grad, xi, count, mean_g)
    delta_g = np.sqrt(ss_g)
    ok, low = cholesky_solve_setup(hessian, 12)
    return mean_g, delta_g, ok, low, sum_j, sum_jg


@njit(**KERNEL_OPTIONS)
def translation_h_inverse(low, m_par, nb, out):
    """Diagonal of ``H⁻¹`` at the three translations, from the Cholesky factor of ``H``."""
    unit = np.zeros(m_par)
    column = np.empty(m_par)
    for k in range(3):
        unit[:] = 0.0
        unit[k * nb] = 1.0
        cholesky_solve(low, unit, m_par, column)
        out[k] = column[k * nb]
