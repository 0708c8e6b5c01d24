"""Tricubic B-spline interpolation of volumes.

A volume is prefiltered once into cubic B-spline coefficients (the recursive filter of
``scipy.ndimage.spline_filter``, mirror boundary, lines in parallel); sampling then sums 4×4×4
coefficients weighted by the cubic B-spline basis.
The interpolant passes through the voxel values and has continuous second derivatives, which keeps
the IC-GN's sub-voxel bias low (a trilinear interpolant biases sub-voxel estimates towards integers).

Positions are ``(z, y, x)`` in voxels; voxel ``(i, j, k)`` sits at integer position ``(i, j, k)``.
Valid positions lie in ``[0, n - 1]`` along each axis; coefficients outside are mirrored, matching
``scipy.ndimage.map_coordinates(volume, ..., order=3, mode="mirror")``.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from .._numba_setup import KERNEL_OPTIONS

#: The pole of the cubic B-spline's recursive prefilter (Unser's ``z1 = sqrt(3) - 2``).
CUBIC_POLE = float(np.sqrt(3.0) - 2.0)

#: The prefilter's gain, ``(1 - z1)(1 - 1 / z1) = 6``.
CUBIC_GAIN = float((1.0 - CUBIC_POLE) * (1.0 - 1.0 / CUBIC_POLE))


def prefilter(volume: np.ndarray) -> np.ndarray:
    """Cubic B-spline coefficients of ``volume`` (mirror boundary, as scipy's ``spline_filter``).

    Parameters
    ----------
    volume : ndarray, shape (nz, ny, nx), any real dtype
        Gray values.

    Returns
    -------
    ndarray, float32, C-contiguous, same shape
        Coefficients for :func:`sample` and the IC-GN kernels: the recursive filter of
        :func:`_filter_lines` along x, then y, then z, each line in double precision and stored
        in float32 between axes (as ``scipy.ndimage.spline_filter(..., output=np.float32)``),
        lines in parallel.
    """
    volume = np.asarray(volume)
    if volume.ndim != 3:
        raise ValueError(f"prefilter needs a 3-D volume, got shape {volume.shape}")
    if volume.dtype.kind not in "uif" or volume.dtype == np.float16:
        volume = volume.astype(np.float32)
    volume = volume.view(np.ndarray)
    volume.flags.writeable = False  # one numba signature per dtype, read-only or not
    coefficients = np.empty(volume.shape, np.float32)
    _prefilter_xyz(volume, coefficients, CUBIC_POLE, CUBIC_GAIN)
    return coefficients


@njit(inline="always", **KERNEL_OPTIONS)
def _filter_lines(lines, n, pole, gain):
    """The cubic B-spline prefilter along axis 0 of ``lines`` (n, m): m lines of n samples.

    Gain, then the causal and anti-causal first-order recursions of pole ``z``, with the
    mirror-symmetric (period ``2n - 2``) initial values in closed form:
    ``c+[0] = (Σ_{k<n-1} z^k (c[k] + z^{n-1} c[n-1-k]) + ...) / (1 - z^{2n-2})`` and
    ``c-[n-1] = z / (z² - 1) (z c+[n-2] + c+[n-1])`` (Unser 1999; scipy's ``mirror`` mode); the
    sum stops where ``z^k`` falls below 1e-18.
    """
    m = lines.shape[1]
    if n == 1:
        return
    for i in range(n):
        for j in range(m):
            lines[i, j] *= gain
    z_last = pole ** (n - 1)
    first = np.empty(m)
    for j in range(m):
        first[j] = lines[0, j] + z_last * lines[n - 1, j]
    z_i = pole
    for i in range(1, n - 1):
        if abs(z_i) < 1e-18:  # the remaining terms are below float64's resolution
            break
        for j in range(m):
            first[j] += z_i * (lines[i, j] + z_last * lines[n - 1 - i, j])
        z_i *= pole
    scale = 1.0 / (1.0 - z_last * z_last)
    for j in range(m):
        lines[0, j] = first[j] * scale
    for i in range(1, n):
        for j in range(m):
            lines[i, j] += pole * lines[i - 1, j]
    end = pole / (pole * pole - 1.0)
    for j in range(m):
        lines[n - 1, j] = end * (pole * lines[n - 2, j] + lines[n - 1, j])
    for i in range(n - 2, -1, -1):
        for j in range(m):
            lines[i, j] = pole * (lines[i + 1, j] - lines[i, j])


@njit(parallel=True, **KERNEL_OPTIONS)
def _prefilter_xyz(volume, out, pole, gain):
    """The three axes in one kernel (one cache load per process instead of three), each axis a
    parallel loop that ends before the next starts.

    Along x, (z, y) rows in parallel, reading any real dtype and writing float32; along y, one
    z-plane per task, all of its x columns at once (contiguous rows); along z, one y-row of every
    plane per task, all of its x columns at once.
    """
    nz, ny, nx = volume.shape
    for task in prange(nz):
        line = np.empty((nx, 1))
        for iy in range(ny):
            for ix in range(nx):
                line[ix, 0] = volume[task, iy, ix]
            _filter_lines(line, nx, pole, gain)
            for ix in range(nx):
                out[task, iy, ix] = line[ix, 0]
    for iz in prange(nz):
        lines = np.empty((ny, nx))
        for iy in range(ny):
            for ix in range(nx):
                lines[iy, ix] = out[iz, iy, ix]
        _filter_lines(lines, ny, pole, gain)
        for iy in range(ny):
            for ix in range(nx):
                out[iz, iy, ix] = lines[iy, ix]
    for iy in prange(ny):
        lines = np.empty((nz, nx))
        for iz in range(nz):
            for ix in range(nx):
                lines[iz, ix] = out[iz, iy, ix]
        _filter_lines(lines, nz, pole, gain)
        for iz in range(nz):
            for ix in range(nx):
                out[iz, iy, ix] = lines[iz, ix]


@njit(inline="always", **KERNEL_OPTIONS)
def bspline_weights(t):
    """Cubic B-spline weights of the 4 taps ``floor(x) - 1 .. floor(x) + 2`` for ``t = x - floor(x)``."""
    s = 1.0 - t
    t2 = t * t
    t3 = t2 * t
    w0 = s * s * s / 6.0
    w1 = (3.0 * t3 - 6.0 * t2 + 4.0) / 6.0
    w2 = (-3.0 * t3 + 3.0 * t2 + 3.0 * t + 1.0) / 6.0
    w3 = t3 / 6.0
    return w0, w1, w2, w3


@njit(inline="always", **KERNEL_OPTIONS)
def bspline_derivative_weights(t):
    """Derivatives of :func:`bspline_weights` with respect to ``t``."""
    s = 1.0 - t
    d0 = -0.5 * s * s
    d1 = 0.5 * (3.0 * t * t - 4.0 * t)
    d2 = 0.5 * (-3.0 * t * t + 2.0 * t + 1.0)
    d3 = 0.5 * t * t
    return d0, d1, d2, d3


@njit(inline="always", **KERNEL_OPTIONS)
def _mirror(index, n):
    if n == 1:
        return 0
    period = 2 * (n - 1)
    index = abs(index) % period
    if index > n - 1:
        index = period - index
    return index


@njit(inline="always", **KERNEL_OPTIONS)
def in_interior(coefficients, z, y, x):
    """True when all 64 taps around ``(z, y, x)`` lie inside the array (fast path allowed)."""
    nz, ny, nx = coefficients.shape
    return 1.0 <= z < nz - 2.0 and 1.0 <= y < ny - 2.0 and 1.0 <= x < nx - 2.0


@njit(inline="always", **KERNEL_OPTIONS)
def _weights32(t):
    """:func:`bspline_weights` in float32 (the hot path: 40% faster, errors ~1e-7 relative)."""
    s = np.float32(1.0) - t
    t2 = t * t
    t3 = t2 * t
    sixth = np.float32(1.0 / 6.0)
    return (
        s * s * s * sixth,
        (np.float32(3.0) * t3 - np.float32(6.0) * t2 + np.float32(4.0)) * sixth,
        (np.float32(-3.0) * t3 + np.float32(3.0) * (t2 + t) + np.float32(1.0)) * sixth,
        t3 * sixth,
    )


@njit(inline="always", **KERNEL_OPTIONS)
def _row(c, z, y, ix, w0, w1, w2, w3):
    return w0 * c[z, y, ix - 1] + w1 * c[z, y, ix] + w2 * c[z, y, ix + 1] + w3 * c[z, y, ix + 2]


@njit(inline="always", **KERNEL_OPTIONS)
def _plane(c, z, iy, ix, wy0, wy1, wy2, wy3, wx0, wx1, wx2, wx3):
    return (
        wy0 * _row(c, z, iy - 1, ix, wx0, wx1, wx2, wx3)
        + wy1 * _row(c, z, iy, ix, wx0, wx1, wx2, wx3)
        + wy2 * _row(c, z, iy + 1, ix, wx0, wx1, wx2, wx3)
        + wy3 * _row(c, z, iy + 2, ix, wx0, wx1, wx2, wx3)
    )


@njit(inline="always", **KERNEL_OPTIONS)
def sample_interior(coefficients, z, y, x):
    """Value at ``(z, y, x)``; requires :func:`in_interior` (no bounds checks).

    The 64 taps are written out (4 planes × 4 rows × 4 columns) and weighted in float32; this is
    the innermost operation of IC-GN.
    """
    iz = int(z)
    iy = int(y)
    ix = int(x)
    wz0, wz1, wz2, wz3 = _weights32(np.float32(z - iz))
    wy0, wy1, wy2, wy3 = _weights32(np.float32(y - iy))
    wx0, wx1, wx2, wx3 = _weights32(np.float32(x - ix))
    c = coefficients
    return (
        wz0 * _plane(c, iz - 1, iy, ix, wy0, wy1, wy2, wy3, wx0, wx1, wx2, wx3)
        + wz1 * _plane(c, iz, iy, ix, wy0, wy1, wy2, wy3, wx0, wx1, wx2, wx3)
        + wz2 * _plane(c, iz + 1, iy, ix, wy0, wy1, wy2, wy3, wx0, wx1, wx2, wx3)
        + wz3 * _plane(c, iz + 2, iy, ix, wy0, wy1, wy2, wy3, wx0, wx1, wx2, wx3)
    )


@njit(**KERNEL_OPTIONS)
def sample_mirrored(coefficients, z, y, x):
    """Value at any ``(z, y, x)`` with mirrored taps (slow path near the border).

    The value part of :func:`sample_with_gradient_point`; the border is rare enough that the
    unused derivative sums cost nothing measurable.
    """
    return sample_with_gradient_point(coefficients, z, y, x)[0]


@njit(**KERNEL_OPTIONS)
def sample_point(coefficients, z, y, x, cval):
    """Value at ``(z, y, x)``; ``cval`` outside ``[0, n - 1]`` along any axis."""
    nz, ny, nx = coefficients.shape
    if not (0.0 <= z <= nz - 1 and 0.0 <= y <= ny - 1 and 0.0 <= x <= nx - 1):
        return cval
    if in_interior(coefficients, z, y, x):
        return sample_interior(coefficients, z, y, x)
    return sample_mirrored(coefficients, z, y, x)


@njit(parallel=True, **KERNEL_OPTIONS)
def _sample_many(coefficients, points, cval, out):
    for i in prange(points.shape[0]):
        out[i] = sample_point(coefficients, points[i, 0], points[i, 1], points[i, 2], cval)


@njit(**KERNEL_OPTIONS)
def sample_with_gradient_point(coefficients, z, y, x):
    """Value and gradient ``(v, dz, dy, dx)`` at ``(z, y, x)`` (mirrored taps)."""
    nz, ny, nx = coefficients.shape
    fz = np.floor(z)
    fy = np.floor(y)
    fx = np.floor(x)
    wz = bspline_weights(z - fz)
    wy = bspline_weights(y - fy)
    wx = bspline_weights(x - fx)
    dz = bspline_derivative_weights(z - fz)
    dy = bspline_derivative_weights(y - fy)
    dx = bspline_derivative_weights(x - fx)
    iz = int(fz)
    iy = int(fy)
    ix = int(fx)
    v = 0.0
    gz = 0.0
    gy = 0.0
    gx = 0.0
    for a in range(4):
        za = _mirror(iz - 1 + a, nz)
        for b in range(4):
            yb = _mirror(iy - 1 + b, ny)
            row_v = 0.0
            row_d = 0.0
            for c in range(4):
                coef = coefficients[za, yb, _mirror(ix - 1 + c, nx)]
                row_v += wx[c] * coef
                row_d += dx[c] * coef
            v += wz[a] * wy[b] * row_v
            gz += dz[a] * wy[b] * row_v
            gy += wz[a] * dy[b] * row_v
            gx += wz[a] * wy[b] * row_d
    return v, gz, gy, gx


@njit(parallel=True, **KERNEL_OPTIONS)
def _sample_many_with_gradient(coefficients, points, out):
    for i in prange(points.shape[0]):
        v, gz, gy, gx = sample_with_gradient_point(
            coefficients, points[i, 0], points[i, 1], points[i, 2]
        )
        out[i, 0] = v
        out[i, 1] = gz
        out[i, 2] = gy
        out[i, 3] = gx


def _check_points(points) -> np.ndarray:
    points = np.ascontiguousarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must have shape (N, 3) in (z, y, x), got {points.shape}")
    return points


def sample(coefficients: np.ndarray, points: np.ndarray, cval: float = np.nan) -> np.ndarray:
    """Interpolated values at ``points``.

    Parameters
    ----------
    coefficients : ndarray, shape (nz, ny, nx), float32
        From :func:`prefilter`.
    points : ndarray, shape (N, 3), float64
        Positions ``(z, y, x)`` in voxels.
    cval : float
        Value returned for points outside ``[0, n - 1]`` along any axis (NaN by default).

    Returns
    -------
    ndarray, shape (N,), float32
    """
    points = _check_points(points)
    out = np.empty(points.shape[0], np.float32)
    _sample_many(np.ascontiguousarray(coefficients, dtype=np.float32), points, float(cval), out)
    return out


def sample_with_gradient(coefficients: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Interpolated values and gradients at ``points`` (mirrored outside the volume).

    Returns
    -------
    ndarray, shape (N, 4), float64
        Columns ``value, d/dz, d/dy, d/dx`` (gray levels per voxel for the derivatives).
    """
    points = _check_points(points)
    out = np.empty((points.shape[0], 4), np.float64)
    _sample_many_with_gradient(np.ascontiguousarray(coefficients, dtype=np.float32), points, out)
    return out
