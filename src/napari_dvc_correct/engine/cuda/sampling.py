"""Tricubic B-spline sampling on the GPU (numba.cuda), the same interpolant as
:mod:`napari_dvc_correct.engine.correlation.interpolation`.

The coefficients are a flat float32 device array (C order, strides ``sz = ny * nx`` and
``sy = nx``). A sample at position ``i + t`` per axis (``i`` integer, ``t`` in ``[0, 1)``) sums the
4×4×4 coefficients ``i - 1 .. i + 2`` weighted by the cubic B-spline basis. The weights and the sum
are float32 (the CPU path sums in float64): the difference is about 1e-7 of the gray range, far below
what moves a match by 1e-3 voxel. Every constant below is float32 so that numba keeps the arithmetic
in single precision (a float64 literal would silently promote it, at half the H100's FP32 rate).

Taps come from ordinary global loads (L1 / L2 cached): numba.cuda has no texture objects, and the
hardware's trilinear filtering would bias sub-voxel estimates by ~1/256 voxel anyway.
"""

from __future__ import annotations

import math

import numpy as np
from numba import float32, int64, uint64

from ._numba_cuda import cuda

_ZERO = np.float32(0.0)
_ONE = np.float32(1.0)
_HALF = np.float32(0.5)
_THREE = np.float32(3.0)
_TWO = np.float32(2.0)
_FOUR = np.float32(4.0)
_SIX = np.float32(6.0)
_SIXTH = np.float32(1.0 / 6.0)


@cuda.jit(device=True, inline="always")
def bspline_weights(t):
    """Cubic B-spline weights of taps ``i - 1 .. i + 2`` for the fraction ``t`` (float32)."""
    s = _ONE - t
    t2 = t * t
    t3 = t2 * t
    w0 = s * s * s * _SIXTH
    w1 = (_THREE * t3 - _SIX * t2 + _FOUR) * _SIXTH
    w2 = (-_THREE * t3 + _THREE * t2 + _THREE * t + _ONE) * _SIXTH
    w3 = t3 * _SIXTH
    return w0, w1, w2, w3


@cuda.jit(device=True, inline="always")
def _row(coef, i, w0, w1, w2, w3):
    # unsigned indices: numba then skips the negative-index wraparound test on every load
    return (
        w0 * coef[uint64(i)]
        + w1 * coef[uint64(i + 1)]
        + w2 * coef[uint64(i + 2)]
        + w3 * coef[uint64(i + 3)]
    )


@cuda.jit(device=True, inline="always")
def _plane(coef, i, sy, wy0, wy1, wy2, wy3, wx0, wx1, wx2, wx3):
    return (
        wy0 * _row(coef, i, wx0, wx1, wx2, wx3)
        + wy1 * _row(coef, i + sy, wx0, wx1, wx2, wx3)
        + wy2 * _row(coef, i + 2 * sy, wx0, wx1, wx2, wx3)
        + wy3 * _row(coef, i + 3 * sy, wx0, wx1, wx2, wx3)
    )


@cuda.jit(device=True, inline="always")
def sample_interior(coef, sz, sy, iz, iy, ix, tz, ty, tx):
    """Value at ``(iz + tz, iy + ty, ix + tx)``; all 64 taps inside (``1 <= i <= n - 3``)."""
    wz0, wz1, wz2, wz3 = bspline_weights(tz)
    wy0, wy1, wy2, wy3 = bspline_weights(ty)
    wx0, wx1, wx2, wx3 = bspline_weights(tx)
    base = (iz - 1) * sz + (iy - 1) * sy + (ix - 1)
    return (
        wz0 * _plane(coef, base, sy, wy0, wy1, wy2, wy3, wx0, wx1, wx2, wx3)
        + wz1 * _plane(coef, base + sz, sy, wy0, wy1, wy2, wy3, wx0, wx1, wx2, wx3)
        + wz2 * _plane(coef, base + 2 * sz, sy, wy0, wy1, wy2, wy3, wx0, wx1, wx2, wx3)
        + wz3 * _plane(coef, base + 3 * sz, sy, wy0, wy1, wy2, wy3, wx0, wx1, wx2, wx3)
    )


@cuda.jit(device=True, inline="always")
def mirror(index, n):
    """Mirror an index into ``[0, n - 1]`` (scipy's ``mode="mirror"``)."""
    if index >= 0 and index < n:
        return index
    if n == 1:
        return int64(0)
    period = 2 * (n - 1)
    index = abs(index) % period
    if index > n - 1:
        index = period - index
    return index


@cuda.jit(device=True)
def sample_mirrored(coef, nz, ny, nx, iz, iy, ix, tz, ty, tx):
    """Value at ``(iz + tz, iy + ty, ix + tx)`` with mirrored taps (slow path near the border)."""
    wz0, wz1, wz2, wz3 = bspline_weights(tz)
    wy0, wy1, wy2, wy3 = bspline_weights(ty)
    wx0, wx1, wx2, wx3 = bspline_weights(tx)
    sz = ny * nx
    x0 = mirror(ix - 1, nx)
    x1 = mirror(ix, nx)
    x2 = mirror(ix + 1, nx)
    x3 = mirror(ix + 2, nx)
    total = _ZERO
    for a in range(4):
        wz = wz0 if a == 0 else (wz1 if a == 1 else (wz2 if a == 2 else wz3))
        zoff = mirror(iz - 1 + a, nz) * sz
        inner = _ZERO
        for b in range(4):
            wy = wy0 if b == 0 else (wy1 if b == 1 else (wy2 if b == 2 else wy3))
            row = zoff + mirror(iy - 1 + b, ny) * nx
            inner += wy * (
                wx0 * coef[uint64(row + x0)]
                + wx1 * coef[uint64(row + x1)]
                + wx2 * coef[uint64(row + x2)]
                + wx3 * coef[uint64(row + x3)]
            )
        total += wz * inner
    return total


@cuda.jit(device=True, inline="always")
def split_position(base, w):
    """Integer tap origin and float32 fraction of the position ``base + w`` (``base`` integer).

    Splitting keeps full float32 precision of ``w`` however large the volume is (a float32 absolute
    position in a 3000-voxel volume would only resolve 2.4e-4 voxel).
    """
    fl = math.floor(w)
    return base + int64(fl), float32(w - float32(fl))


@cuda.jit(device=True, inline="always")
def inside(i, t, n):
    """True when the position ``i + t`` lies in ``[0, n - 1]``."""
    return i >= 0 and (i < n - 1 or (i == n - 1 and t == _ZERO))


@cuda.jit(device=True, inline="always")
def interior(i, n):
    """True when all taps of a position with integer part ``i`` lie inside ``[0, n - 1]``."""
    return i >= 1 and i <= n - 3


@cuda.jit
def _sample_kernel(coef, nz, ny, nx, points, cval, out):
    start = cuda.grid(1)
    stride = cuda.gridsize(1)
    sz = ny * nx
    for n in range(start, points.shape[0], stride):
        z = points[n, 0]
        y = points[n, 1]
        x = points[n, 2]
        if not (0.0 <= z <= nz - 1 and 0.0 <= y <= ny - 1 and 0.0 <= x <= nx - 1):
            out[n] = cval
            continue
        fz = math.floor(z)
        fy = math.floor(y)
        fx = math.floor(x)
        iz = int64(fz)
        iy = int64(fy)
        ix = int64(fx)
        tz = float32(z - fz)
        ty = float32(y - fy)
        tx = float32(x - fx)
        if interior(iz, nz) and interior(iy, ny) and interior(ix, nx):
            out[n] = sample_interior(coef, sz, nx, iz, iy, ix, tz, ty, tx)
        else:
            out[n] = sample_mirrored(coef, nz, ny, nx, iz, iy, ix, tz, ty, tx)


def sample_cuda(
    coefficients: np.ndarray, points: np.ndarray, cval: float = np.nan, *, threads_per_block=None
) -> np.ndarray:
    """GPU version of :func:`napari_dvc_correct.engine.correlation.interpolation.sample`.

    Parameters
    ----------
    coefficients : ndarray, shape (nz, ny, nx), float32
        From :func:`~napari_dvc_correct.engine.correlation.interpolation.prefilter`. Kept on the GPU between
        calls while the same array object is alive (see :mod:`.memory`).
    points : ndarray, shape (N, 3), float64
        Positions ``(z, y, x)`` in voxels.
    cval : float
        Value for points outside ``[0, n - 1]`` along any axis.

    Returns
    -------
    ndarray, shape (N,), float32
    """
    from ..correlation.interpolation import _check_points
    from .memory import default_threads, to_device_cached

    points = _check_points(points)
    coefficients = np.asarray(coefficients)
    if coefficients.ndim != 3:
        raise ValueError(f"coefficients must be 3-D, got shape {coefficients.shape}")
    nz, ny, nx = coefficients.shape
    out = np.empty(points.shape[0], np.float32)
    if points.shape[0] == 0:
        return out
    threads = threads_per_block or default_threads()
    blocks = min((points.shape[0] + threads - 1) // threads, 65535)
    d_coef = to_device_cached(coefficients, flat=True)
    d_out = cuda.device_array(points.shape[0], np.float32)
    _sample_kernel[blocks, threads](
        d_coef, nz, ny, nx, cuda.to_device(points), np.float32(cval), d_out
    )
    d_out.copy_to_host(out)
    return out
