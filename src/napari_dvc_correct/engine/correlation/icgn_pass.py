"""The deformed side of one IC-GN iteration: sample ``F`` over the warped subvolume and sum.

:func:`sample_pass` runs in two loops. The first computes each voxel's warped position and
samples ``F`` there (the vector tap sum of :mod:`.simd_taps` in the interior, mirrored taps near
the border) into a float32 buffer, chunk by chunk: positions, in-volume flags, tap offsets and
fractions for a chunk of voxels first (loops LLVM vectorizes across voxels), then the tap sums
(measured 1.3× the per-voxel loop). The second loop sums ``Σf``, ``Σf²``, ``Σ(g − ḡ)f`` and
``Σ J f`` from it. Separate loops keep each one's values in registers (measured 1.3× one fused
loop). All sums are float64.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from .._numba_setup import FAST_KERNEL_OPTIONS
from .interpolation import sample_mirrored
from .simd_taps import taps64

#: Voxels per chunk of :func:`_affine_samples`: the chunk's positions, tap offsets and fractions
#: (about 10 kB) stay in L1.
CHUNK = 256


@njit(inline="always", **FAST_KERNEL_OPTIONS)
def _chunk_buffers():
    return (
        np.empty(CHUNK),  # z positions
        np.empty(CHUNK),  # y
        np.empty(CHUNK),  # x
        np.empty(CHUNK, np.int64),  # flat index of the tap (-1, -1, -1)
        np.empty(CHUNK, np.float32),  # fractional z
        np.empty(CHUNK, np.float32),  # fractional y
        np.empty(CHUNK, np.float32),  # fractional x
        np.empty(CHUNK, np.bool_),  # all 64 taps inside
    )


@njit(inline="always", **FAST_KERNEL_OPTIONS)
def _axis(position, n, limit, stride, starts, fraction, first):
    """Integer part (clamped to ``[1, limit]``, so any position is safe) and fraction along one axis."""
    for j in range(n):
        w = position[j]
        k = int(min(max(w, 1.0), limit))
        if first:
            starts[j] = (k - 1) * stride
        else:
            starts[j] += (k - 1) * stride
        fraction[j] = np.float32(w - k)


@njit(inline="always", **FAST_KERNEL_OPTIONS)
def _sample_chunk(coef, flat, c0, n, buffers, outside, values):
    """Sample ``F`` at a chunk's positions into ``values[c0:c0 + n]``; returns the voxels outside.

    The flags, integer parts and fractions are separate branch-free loops over the chunk, which
    LLVM vectorizes across voxels; the tap sums then run per voxel (:func:`.simd_taps.taps64`).
    """
    nz, ny, nx = coef.shape
    plane = ny * nx
    pz, py, px, starts, fz, fy, fx, inner = buffers
    lz = nz - 2.0
    ly = ny - 2.0
    lx = nx - 2.0
    for j in range(n):
        wz = pz[j]
        wy = py[j]
        wx = px[j]
        inner[j] = (wz >= 1.0) & (wz < lz) & (wy >= 1.0) & (wy < ly) & (wx >= 1.0) & (wx < lx)
    _axis(pz, n, lz, plane, starts, fz, True)
    _axis(py, n, ly, nx, starts, fy, False)
    _axis(px, n, lx, 1, starts, fx, False)
    n_outside = 0
    for j in range(n):
        if inner[j]:
            values[c0 + j] = taps64(flat, starts[j], nx, plane, fz[j], fy[j], fx[j])
        else:
            wz = pz[j]
            wy = py[j]
            wx = px[j]
            if 0.0 <= wz <= nz - 1 and 0.0 <= wy <= ny - 1 and 0.0 <= wx <= nx - 1:
                values[c0 + j] = sample_mirrored(coef, wz, wy, wx)
            else:
                outside[c0 + j] = True
                n_outside += 1
    return n_outside


@njit(**FAST_KERNEL_OPTIONS)
def _affine_samples(coef, xi, count, cz, cy, cx, p, outside, values):
    """Samples of ``F`` at the first-order warp of every voxel; returns the voxels outside."""
    flat = coef.reshape(coef.size)
    buffers = _chunk_buffers()
    pz, py, px = buffers[0], buffers[1], buffers[2]
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
    n_outside = 0
    for c0 in range(0, count, CHUNK):
        n = min(CHUNK, count - c0)
        for j in range(n):
            z = xi[c0 + j, 0]
            y = xi[c0 + j, 1]
            x = xi[c0 + j, 2]
            pz[j] = t0 + a00 * z + a01 * y + a02 * x
            py[j] = t1 + a10 * z + a11 * y + a12 * x
            px[j] = t2 + a20 * z + a21 * y + a22 * x
        n_outside += _sample_chunk(coef, flat, c0, n, buffers, outside, values)
    return n_outside


@njit(inline="always", **FAST_KERNEL_OPTIONS)
def _quadratic_term(p, q, z, y, x, zz, yy, xx, zy, yx, zx):
    return (
        p[q]
        + p[q + 1] * z
        + p[q + 2] * y
        + p[q + 3] * x
        + p[q + 4] * zz
        + p[q + 5] * yy
        + p[q + 6] * xx
        + p[q + 7] * zy
        + p[q + 8] * yx
        + p[q + 9] * zx
    )


@njit(**FAST_KERNEL_OPTIONS)
def _quadratic_samples(coef, xi, count, cz, cy, cx, p, outside, values):
    """:func:`_affine_samples` for the second-order warp (``p`` has 30 entries)."""
    flat = coef.reshape(coef.size)
    buffers = _chunk_buffers()
    pz, py, px = buffers[0], buffers[1], buffers[2]
    n_outside = 0
    for c0 in range(0, count, CHUNK):
        n = min(CHUNK, count - c0)
        for j in range(n):
            z = np.float64(xi[c0 + j, 0])
            y = np.float64(xi[c0 + j, 1])
            x = np.float64(xi[c0 + j, 2])
            zz = z * z
            yy = y * y
            xx = x * x
            zy = z * y
            yx = y * x
            zx = z * x
            pz[j] = cz + z + _quadratic_term(p, 0, z, y, x, zz, yy, xx, zy, yx, zx)
            py[j] = cy + y + _quadratic_term(p, 10, z, y, x, zz, yy, xx, zy, yx, zx)
            px[j] = cx + x + _quadratic_term(p, 20, z, y, x, zz, yy, xx, zy, yx, zx)
        n_outside += _sample_chunk(coef, flat, c0, n, buffers, outside, values)
    return n_outside


@njit(**FAST_KERNEL_OPTIONS)
def _affine_sums(values, g, grad, xi, count, mean_g, sum_jf):
    sum_f = 0.0
    sum_ff = 0.0
    sum_gf = 0.0
    s00 = s01 = s02 = s03 = 0.0
    s10 = s11 = s12 = s13 = 0.0
    s20 = s21 = s22 = s23 = 0.0
    for i in range(count):
        z = np.float64(xi[i, 0])
        y = np.float64(xi[i, 1])
        x = np.float64(xi[i, 2])
        f = np.float64(values[i])
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
    return sum_f, sum_ff, sum_gf


@njit(**FAST_KERNEL_OPTIONS)
def _quadratic_sums(values, g, grad, xi, count, mean_g, sum_jf):
    sum_f = 0.0
    sum_ff = 0.0
    sum_gf = 0.0
    for i in range(count):
        f = np.float64(values[i])
        sum_f += f
        sum_ff += f * f
        sum_gf += (g[i] - mean_g) * f
    for k in range(3):  # one loop per gradient component: 10 sums stay in registers
        s0 = s1 = s2 = s3 = s4 = s5 = s6 = s7 = s8 = s9 = 0.0
        for i in range(count):
            z = np.float64(xi[i, 0])
            y = np.float64(xi[i, 1])
            x = np.float64(xi[i, 2])
            fk = grad[i, k] * np.float64(values[i])
            s0 += fk
            s1 += fk * z
            s2 += fk * y
            s3 += fk * x
            s4 += fk * (z * z)
            s5 += fk * (y * y)
            s6 += fk * (x * x)
            s7 += fk * (z * y)
            s8 += fk * (y * x)
            s9 += fk * (z * x)
        q = 10 * k
        sum_jf[q] = s0
        sum_jf[q + 1] = s1
        sum_jf[q + 2] = s2
        sum_jf[q + 3] = s3
        sum_jf[q + 4] = s4
        sum_jf[q + 5] = s5
        sum_jf[q + 6] = s6
        sum_jf[q + 7] = s7
        sum_jf[q + 8] = s8
        sum_jf[q + 9] = s9
    return sum_f, sum_ff, sum_gf


@njit(**FAST_KERNEL_OPTIONS)
def sample_pass(coef, g, grad, xi, count, mean_g, cz, cy, cx, p, nb, outside, sum_jf):
    """One pass over the subvolume at warp ``p`` (3·nb parameters, ``nb`` = 4 or 10).

    Samples ``F`` (B-spline coefficients ``coef``) at every warped voxel ``c + W(ξ_i; p)``,
    ``ξ_i = xi[i]`` (z, y, x), and returns ``(Σf, Σf², Σ(g − ḡ)f, voxels outside)``, filling
    ``sum_jf = Σ J f`` (``J = ∇G · ∂W/∂p``, ``grad`` holding ``∇G``). Voxels whose warped
    position leaves ``F`` are flagged in ``outside``; when there are any, only their count is
    returned (the sums are 0 and ``sum_jf`` is left as it was: the caller drops those voxels and
    samples again).
    """
    values = np.empty(count, np.float32)
    if nb == 4:
        n_outside = _affine_samples(coef, xi, count, cz, cy, cx, p, outside, values)
    else:
        n_outside = _quadratic_samples(coef, xi, count, cz, cy, cx, p, outside, values)
    if n_outside > 0:
        return 0.0, 0.0, 0.0, n_outside
    if nb == 4:
        sum_f, sum_ff, sum_gf = _affine_sums(values, g, grad, xi, count, mean_g, sum_jf)
    else:
        sum_f, sum_ff, sum_gf = _quadratic_sums(values, g, grad, xi, count, mean_g, sum_jf)
    return sum_f, sum_ff, sum_gf, n_outside
