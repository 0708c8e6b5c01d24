"""Device-side algebra of the GPU IC-GN kernel (:mod:`.icgn`): ``@cuda.jit(device=True)`` helpers.

* :func:`block_reduce`: shared-memory tree reduction of per-thread float64 sums over a block;
* :func:`monomials32`, :func:`factor_value`: per-voxel shape-function monomials and reference-moment
  factors (float32, in the orders of :mod:`..icgn` and :mod:`.tables`);
* :func:`cholesky`, :func:`cholesky_solve`: the Gauss-Newton Hessian's factor and solve (float64,
  the CPU's positivity and conditioning test);
* :func:`warp_matrix`, :func:`invert`: the warp's action on the monomials and its inverse, for the
  composition ``W(p) ∘ W(Δp)⁻¹``;
* :func:`finish`: thread 0 writes one POI's result.

Matrices are flat, row-major arrays; sizes are passed as arguments. ``warp_matrix`` and the
Cholesky solve repeat the CPU's (:mod:`..shape_function`) line for line on purpose: a CUDA device
function is compiled on its own and cannot call an ``@njit`` one (the duplicate finder pairs them).
"""

from __future__ import annotations

import math

import numpy as np

from ._numba_cuda import cuda

#: Values reduced per round of the shared-memory tree reduction.
REDUCE_CHUNK = 16

_ZERO = np.float32(0.0)
_ONE = np.float32(1.0)


@cuda.jit(device=True)
def block_reduce(acc, n, red, out, out_base, t, threads):
    """Sum ``acc[0:n]`` over the block's threads into ``out[out_base:out_base + n]`` (float64).

    Every thread of the block must call it. ``red`` is shared scratch of
    ``REDUCE_CHUNK * threads`` float64; ``threads`` is a power of two >= REDUCE_CHUNK.
    """
    for c0 in range(0, n, REDUCE_CHUNK):
        m = min(REDUCE_CHUNK, n - c0)
        for i in range(m):
            red[i * threads + t] = acc[c0 + i]
        cuda.syncthreads()
        s = threads // 2
        while s > 0:
            if t < s:
                for i in range(m):
                    red[i * threads + t] += red[i * threads + t + s]
            cuda.syncthreads()
            s //= 2
        if t < m:
            out[out_base + c0 + t] = red[t * threads]
        cuda.syncthreads()


@cuda.jit(device=True, inline="always")
def monomials32(z, y, x, nb, b):
    """Shape-function monomials (float32) in the order of :mod:`..icgn`."""
    b[0] = _ONE
    b[1] = z
    b[2] = y
    b[3] = x
    if nb == 10:
        b[4] = z * z
        b[5] = y * y
        b[6] = x * x
        b[7] = z * y
        b[8] = y * x
        b[9] = z * x


@cuda.jit(device=True, inline="always")
def factor_value(fid, g0, g1, g2, dg):
    """Factor ``fid`` of :mod:`.tables` for one voxel (0 for an unused slot)."""
    if fid < 0:
        return _ZERO
    if fid < 3:
        return g0 if fid == 0 else (g1 if fid == 1 else g2)
    if fid < 6:
        return (g0 if fid == 3 else (g1 if fid == 4 else g2)) * dg
    if fid == 6:
        return g0 * g0
    if fid == 7:
        return g0 * g1
    if fid == 8:
        return g0 * g2
    if fid == 9:
        return g1 * g1
    if fid == 10:
        return g1 * g2
    if fid == 11:
        return g2 * g2
    return dg * dg


@cuda.jit(device=True)
def cholesky(a, m):
    """In-place lower Cholesky factor of the m×m row-major ``a`` (lower triangle read).

    Same test as the CPU: fails when a pivot is not positive or the smallest pivot is below 1e-12
    of the largest.
    """
    largest = 0.0
    smallest = math.inf
    for j in range(m):
        s = a[j * m + j]
        for k in range(j):
            s -= a[j * m + k] * a[j * m + k]
        if not (s > 0.0):
            return False
        d = math.sqrt(s)
        a[j * m + j] = d
        largest = max(largest, s)
        smallest = min(smallest, s)
        for i in range(j + 1, m):
            v = a[i * m + j]
            for k in range(j):
                v -= a[i * m + k] * a[j * m + k]
            a[i * m + j] = v / d
    return not (smallest < 1e-12 * largest)


@cuda.jit(device=True)
def cholesky_solve(low, rhs, m, y, out):
    for i in range(m):
        s = rhs[i]
        for k in range(i):
            s -= low[i * m + k] * y[k]
        y[i] = s / low[i * m + i]
    for i in range(m - 1, -1, -1):
        s = y[i]
        for k in range(i + 1, m):
            s -= low[k * m + i] * out[k]
        out[i] = s / low[i * m + i]


@cuda.jit(device=True)
def warp_matrix(p, nb, m, product_table, quad_axes):
    """``m`` (nb×nb, row-major) with ``b(W(ξ; p)) ≈ m b(ξ)``, as :func:`..icgn.warp_matrix`."""
    for i in range(nb * nb):
        m[i] = 0.0
    m[0] = 1.0
    for k in range(3):
        for j in range(nb):
            m[(1 + k) * nb + j] = p[k * nb + j]
        m[(1 + k) * nb + 1 + k] += 1.0
    if nb == 10:
        for q in range(6):
            a = quad_axes[q, 0]
            b = quad_axes[q, 1]
            row = 4 + q
            for i in range(nb):
                ci = m[(1 + a) * nb + i]
                if ci == 0.0:
                    continue
                for j in range(nb):
                    target = product_table[i, j]
                    if target >= 0:
                        m[row * nb + target] += ci * m[(1 + b) * nb + j]


@cuda.jit(device=True)
def invert(m, nb, inv, work):
    """``inv = m⁻¹`` (nb×nb) by Gauss–Jordan with partial pivoting; False if singular."""
    w = 2 * nb
    for i in range(nb):
        for j in range(nb):
            work[i * w + j] = m[i * nb + j]
            work[i * w + nb + j] = 1.0 if i == j else 0.0
    for col in range(nb):
        pivot = col
        best = abs(work[col * w + col])
        for r in range(col + 1, nb):
            v = abs(work[r * w + col])
            if v > best:
                best = v
                pivot = r
        if best == 0.0:
            return False
        if pivot != col:
            for j in range(w):
                tmp = work[col * w + j]
                work[col * w + j] = work[pivot * w + j]
                work[pivot * w + j] = tmp
        d = work[col * w + col]
        for j in range(w):
            work[col * w + j] /= d
        for r in range(nb):
            if r != col:
                f = work[r * w + col]
                if f != 0.0:
                    for j in range(w):
                        work[r * w + j] -= f * work[col * w + j]
    for i in range(nb):
        for j in range(nb):
            inv[i * nb + j] = work[i * w + nb + j]
    return True


@cuda.jit(device=True, inline="always")
def finish(poi, code, value, its, p_sh, n_par, params, zncc, status, iterations, flag):
    """Thread 0: write a POI's result and tell the block to stop."""
    for r in range(n_par):
        params[poi, r] = p_sh[r]
    zncc[poi] = value
    status[poi] = code
    iterations[poi] = its
    flag[0] = 1
