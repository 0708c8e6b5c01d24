"""The per-voxel stage of the lattice inverse: interpolation between coarse nodes, Newton where
a cell failed its check, and the forward warp's sampling of ``G`` fused with both.

:class:`.inverse_lattice.LatticeInverter` solves the inverse displacement ``v = x - X`` exactly
on a coarse lattice and marks the cells whose interpolation fails its check. The kernels here
fill a box's voxels from that, plane by plane (in parallel over z planes) and row by row:

* :func:`interpolate_planes` writes the reference positions ``X`` (with their convergence, hull
  and "solved by Newton" flags) of every voxel;
* :func:`warp_planes` samples ``G`` at ``X`` as soon as a row of positions is made (the positions
  never leave the cache): the forward warp's values and hull flags, nothing else.

Both make a row's positions with the same code (:func:`_fill_row`), so their positions agree bit
for bit. The interpolation is 6-point Lagrange along z (per plane), y (per row) and x, each pass
a loop over contiguous values that LLVM vectorises (``v`` is held component-major; along x one
pass per phase of the coarse stride, :func:`_fill_cells`), and :func:`.simd_taps.sample_interior_vector` samples ``G``
with 16 four-wide row sums (SIMD over the 4 contiguous x taps), as IC-GN does.

Positions are ``(z, y, x)`` voxels.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from .._numba_setup import KERNEL_OPTIONS
from ..correlation.interpolation import in_interior, sample_mirrored
from ..correlation.simd_taps import sample_interior_vector
from .field_spline_kernels import _eval_one, newton_inverse

#: Interpolation nodes per axis (quintic Lagrange), and how many lie below a cell's first node.
TAPS = 6
BELOW = 2


@njit(inline="always", **KERNEL_OPTIONS)
def lagrange_weights(t):
    """6-point Lagrange (quintic) weights of the nodes at -2 .. 3 for a position ``t`` in [0, 1).

    Exact (0, 0, 1, 0, 0, 0) at ``t = 0``.
    """
    a = t + 2.0
    b = t + 1.0
    c = t
    d = t - 1.0
    e = t - 2.0
    f = t - 3.0
    return (
        b * c * d * e * f / -120.0,
        a * c * d * e * f / 24.0,
        a * b * d * e * f / -12.0,
        a * b * c * e * f / 12.0,
        a * b * c * d * f / -24.0,
        a * b * c * d * e / 120.0,
    )


def axis_weights(start, count, stride):
    """Per voxel of one box axis: first of its 6 coarse nodes (box-local) and their weights.

    NumPy, not a kernel (one cache load fewer per process): the same operations as the kernels'
    :func:`lagrange_weights`, element by element, so the same numbers bit for bit."""
    voxel = np.arange(int(start), int(start) + int(count), dtype=np.int64)
    cell = voxel // stride
    t = (voxel - cell * stride) / stride
    weight = np.stack(lagrange_weights.py_func(t), axis=1) if count else np.empty((0, TAPS))
    return cell - int(start) // stride, np.ascontiguousarray(weight)


@njit(inline="always", **KERNEL_OPTIONS)
def evaluate(spline, z, y, x, out):
    """:func:`.field_spline_kernels._eval_one` with the spline's arguments as one tuple, inlined
    (no call: the array arguments' reference counts cost as much as the evaluation)."""
    _eval_one(spline[0], spline[1], spline[2], spline[3], spline[4], spline[5], z, y, x, out)


@njit(inline="always", **KERNEL_OPTIONS)
def solve(spline, z, y, x, max_iterations, tolerance, position, value, jacobian):
    """:func:`.field_spline_kernels.newton_inverse` with the spline's arguments as one tuple."""
    return newton_inverse(
        spline[0],
        spline[1],
        spline[2],
        spline[3],
        spline[4],
        spline[5],
        z,
        y,
        x,
        max_iterations,
        tolerance,
        position,
        value,
        jacobian,
    )


def phase_table(start, count, stride):
    """Per voxel of the box's x axis its phase ``(start + d) % stride``, and per phase the 6
    weights of :func:`lagrange_weights` (those of :func:`axis_weights`, the same numbers; NumPy,
    as :func:`axis_weights`)."""
    phase = np.arange(int(start), int(start) + int(count), dtype=np.int64) % stride
    table = np.stack(lagrange_weights.py_func(np.arange(stride, dtype=np.int64) / stride), axis=1)
    return phase, np.ascontiguousarray(table)


@njit(inline="always", **KERNEL_OPTIONS)
def _fill_plane(v, za, z_weight, a, plane):
    """``v`` (3, nz, ny, nx) interpolated along z to box plane ``a``: ``plane`` (3, cy, cx)."""
    plane[:] = 0.0
    cy, cx = plane.shape[1], plane.shape[2]
    for c in range(3):
        for i in range(TAPS):
            w = z_weight[a, i]
            if w != 0.0:
                source = v[c, za + i]
                target = plane[c]
                for j in range(cy):
                    for k in range(cx):
                        target[j, k] += w * source[j, k]


@njit(inline="always", **KERNEL_OPTIONS)
def _fill_line(plane, yb, y_weight, b, line):
    """``plane`` interpolated along y to box row ``b``: ``line`` (3, cx)."""
    line[:] = 0.0
    cx = line.shape[1]
    for c in range(3):
        for j in range(TAPS):
            w = y_weight[b, j]
            if w != 0.0:
                for k in range(cx):
                    line[c, k] += w * plane[c, yb + j, k]


@njit(inline="always", **KERNEL_OPTIONS)
def _fill_cells(line, table, cells):
    """``line`` (3, cx) interpolated along x at every phase of every cell: ``cells`` (stride, 3,
    cx - 5), contiguous along the cells (the loops vectorise)."""
    count = cells.shape[2]
    for p in range(table.shape[0]):
        w0 = table[p, 0]
        w1 = table[p, 1]
        w2 = table[p, 2]
        w3 = table[p, 3]
        w4 = table[p, 4]
        w5 = table[p, 5]
        for c in range(3):
            source = line[c]
            target = cells[p, c]
            for m in range(count):
                target[m] = (
                    w0 * source[m]
                    + w1 * source[m + 1]
                    + w2 * source[m + 2]
                    + w3 * source[m + 3]
                    + w4 * source[m + 4]
                    + w5 * source[m + 5]
                )


@njit(inline="always", **KERNEL_OPTIONS)
def _fill_row(
    spline,
    z,
    y,
    x0,
    za,
    yb,
    zy_node_voxel,
    x_node,
    x_phase,
    max_iterations,
    polish,
    cells,
    node_ok,
    fail,
    value,
    jacobian,
    position,
    out,
    ok_out,
    exact_out,
    first,
):
    """Positions of one box row (x from ``x0``) into ``out[first + d]`` and their flags.

    Interpolated (``cells``: :func:`_fill_cells` of the row's ``v``) where the cell passed its
    check, exact at the coarse nodes, Newton from the interpolated guess in failed cells.
    """
    for d in range(x_node.shape[0]):
        xd = x_node[d]
        phase = x_phase[d]
        x = float(x0 + d)
        p0 = z - cells[phase, 0, xd]
        p1 = y - cells[phase, 1, xd]
        p2 = x - cells[phase, 2, xd]
        solved = zy_node_voxel and phase == 0  # a coarse node: v is exact there
        ok = True
        if solved:
            ok = node_ok[za + BELOW, yb + BELOW, xd + BELOW]
        elif fail[za, yb, xd]:
            solved = True
            position[0] = p0
            position[1] = p1
            position[2] = p2
            ok = solve(spline, z, y, x, max_iterations, polish, position, value, jacobian)
            p0 = position[0]
            p1 = position[1]
            p2 = position[2]
        i = first + d
        out[i, 0] = p0
        out[i, 1] = p1
        out[i, 2] = p2
        ok_out[i] = ok
        exact_out[i] = solved


@njit(inline="always", **KERNEL_OPTIONS)
def _in_hull(hull_low, hull_high, p0, p1, p2):
    return (
        hull_low[0] <= p0 <= hull_high[0]
        and hull_low[1] <= p1 <= hull_high[1]
        and hull_low[2] <= p2 <= hull_high[2]
    )


@njit(parallel=True, **KERNEL_OPTIONS)
def interpolate_planes(
    spline,
    hull_low,
    hull_high,
    box_start,
    z_node,
    z_weight,
    y_node,
    y_weight,
    x_node,
    x_phase,
    table,
    max_iterations,
    polish,
    v,
    node_ok,
    fail,
    positions,
    converged,
    in_hull,
    exact,
):
    """Positions ``(N, 3)`` and flags ``(N,)`` of every voxel of the box's planes (C order)."""
    nz = z_node.shape[0]
    ny = y_node.shape[0]
    nx = x_node.shape[0]
    cy, cx = v.shape[2], v.shape[3]
    stride = table.shape[0]
    for a in prange(nz):
        value = np.empty(3)
        jacobian = np.empty((3, 3))
        position = np.empty(3)
        plane = np.empty((3, cy, cx))
        line = np.empty((3, cx))
        cells = np.empty((stride, 3, cx - TAPS + 1))
        za = z_node[a]
        _fill_plane(v, za, z_weight, a, plane)
        z = float(box_start[0] + a)
        z_node_voxel = z_weight[a, BELOW] == 1.0
        for b in range(ny):
            yb = y_node[b]
            _fill_line(plane, yb, y_weight, b, line)
            _fill_cells(line, table, cells)
            index = (a * ny + b) * nx
            _fill_row(
                spline,
                z,
                float(box_start[1] + b),
                box_start[2],
                za,
                yb,
                z_node_voxel and y_weight[b, BELOW] == 1.0,
                x_node,
                x_phase,
                max_iterations,
                polish,
                cells,
                node_ok,
                fail,
                value,
                jacobian,
                position,
                positions,
                converged,
                exact,
                index,
            )
            for d in range(nx):
                i = index + d
                in_hull[i] = _in_hull(
                    hull_low, hull_high, positions[i, 0], positions[i, 1], positions[i, 2]
                )


@njit(inline="always", **KERNEL_OPTIONS)
def sample_or_nan(coefficients, flat, z, y, x):
    """Value at ``(z, y, x)``, NaN outside ``[0, n - 1]`` along any axis (or not finite);
    ``flat`` is ``coefficients`` (C contiguous) as one axis."""
    nz, ny, nx = coefficients.shape
    if not (0.0 <= z <= nz - 1 and 0.0 <= y <= ny - 1 and 0.0 <= x <= nx - 1):
        return np.float32(np.nan)
    if in_interior(coefficients, z, y, x):
        return sample_interior_vector(flat, ny * nx, nx, z, y, x)
    return np.float32(sample_mirrored(coefficients, z, y, x))


@njit(inline="always", **KERNEL_OPTIONS)
def sample_region_or_flag(coefficients, flat, z, y, x, region):
    """:func:`sample_or_nan` of a volume of which ``coefficients`` hold a region.

    ``region`` (4, 3) float64 rows: the region's first voxel in the volume, the volume's last
    voxel, and the lowest and highest region-relative positions whose coefficients are the
    volume's. NaN outside the volume (or not finite), ``+inf`` inside it but outside that part
    of the region (for the caller to sample otherwise).
    """
    if not (0.0 <= z <= region[1, 0] and 0.0 <= y <= region[1, 1] and 0.0 <= x <= region[1, 2]):
        return np.float32(np.nan)
    rz = z - region[0, 0]
    ry = y - region[0, 1]
    rx = x - region[0, 2]
    if not (
        region[2, 0] <= rz <= region[3, 0]
        and region[2, 1] <= ry <= region[3, 1]
        and region[2, 2] <= rx <= region[3, 2]
    ):
        return np.float32(np.inf)
    return sample_or_nan(coefficients, flat, rz, ry, rx)


def region_bounds(coefficients_shape, region_start=(0, 0, 0), whole_shape=None, margin=0):
    """The ``region`` argument of :func:`sample_region_or_flag` (see there).

    ``coefficients_shape`` is the region's, starting at voxel ``region_start`` of a volume of
    ``whole_shape`` (default: the region is the whole volume); its coefficients equal the
    volume's ``margin`` voxels inside every face that is not the volume's own.
    """
    start = np.asarray(region_start, np.int64).reshape(3)
    shape = np.asarray(coefficients_shape, np.int64).reshape(3)
    whole = start + shape if whole_shape is None else np.asarray(whole_shape, np.int64).reshape(3)
    low = np.where(start > 0, margin, 0)
    high = shape - 1 - np.where(start + shape < whole, margin, 0)
    return np.array([start, whole - 1, low, high], np.float64)


@njit(parallel=True, **KERNEL_OPTIONS)
def warp_planes(
    spline,
    hull_low,
    hull_high,
    box_start,
    z_node,
    z_weight,
    y_node,
    y_weight,
    x_node,
    x_phase,
    table,
    max_iterations,
    polish,
    v,
    node_ok,
    fail,
    coefficients,
    region,
    values,
    in_hull,
):
    """``G(X)`` (``values``, (nz, ny, nx) float32, NaN where Newton did not converge or ``X`` is
    outside ``G``) and the hull flags of every voxel of the box's planes; positions stay in a row
    buffer. ``coefficients`` hold the region of ``G`` that ``region`` describes
    (:func:`region_bounds`); ``+inf`` where ``X`` leaves its valid part."""
    nz = z_node.shape[0]
    ny = y_node.shape[0]
    nx = x_node.shape[0]
    cy, cx = v.shape[2], v.shape[3]
    stride = table.shape[0]
    flat = coefficients.reshape(-1)
    for a in prange(nz):
        value = np.empty(3)
        jacobian = np.empty((3, 3))
        position = np.empty(3)
        plane = np.empty((3, cy, cx))
        line = np.empty((3, cx))
        cells = np.empty((stride, 3, cx - TAPS + 1))
        row = np.empty((nx, 3))
        row_ok = np.empty(nx, np.bool_)
        row_exact = np.empty(nx, np.bool_)
        za = z_node[a]
        _fill_plane(v, za, z_weight, a, plane)
        z = float(box_start[0] + a)
        z_node_voxel = z_weight[a, BELOW] == 1.0
        for b in range(ny):
            yb = y_node[b]
            _fill_line(plane, yb, y_weight, b, line)
            _fill_cells(line, table, cells)
            _fill_row(
                spline,
                z,
                float(box_start[1] + b),
                box_start[2],
                za,
                yb,
                z_node_voxel and y_weight[b, BELOW] == 1.0,
                x_node,
                x_phase,
                max_iterations,
                polish,
                cells,
                node_ok,
                fail,
                value,
                jacobian,
                position,
                row,
                row_ok,
                row_exact,
                0,
            )
            for d in range(nx):
                p0 = row[d, 0]
                p1 = row[d, 1]
                p2 = row[d, 2]
                in_hull[a, b, d] = _in_hull(hull_low, hull_high, p0, p1, p2)
                if row_ok[d]:
                    values[a, b, d] = sample_region_or_flag(coefficients, flat, p0, p1, p2, region)
                else:
                    values[a, b, d] = np.nan
