"""The inverse of a field spline on a voxel lattice: exact on a coarse lattice, interpolated, verified.

The forward warp needs, at every loaded-state voxel ``x``, the reference position ``X`` with
``X + u(X) = x``. Newton at every voxel (:meth:`.field_spline.FieldSpline.invert`) costs about two
tricubic evaluations of the field with its Jacobian per voxel. The inverse displacement
``v(x) = x - X(x)`` is as smooth as the field, so :func:`invert_lattice`

1. solves the inverse exactly (Newton, cold start ``X = x - u(x)``) on a coarse lattice of
   voxels whose indices are multiples of ``stride`` along each axis (the whole volume's indices,
   not the box's: a box's answer does not depend on how a volume is cut into boxes);
2. checks every coarse cell (the ``stride³`` voxels between 8 coarse nodes): the cubic
   interpolation of ``v`` at the cell's centre (where the interpolation error of a smooth function
   peaks) against the exact inverse there (Newton from the interpolated guess), and that the cell's
   4 × 4 × 4 interpolation nodes all converged;
3. interpolates ``v`` to every voxel (4-point Lagrange cubic along each axis, separably: a dozen
   multiply-adds per voxel) in the cells that pass, and runs Newton per voxel, from the interpolated
   guess, in the cells that fail (narrow shear bands, folds, kinks of the extrapolated field,
   points that do not converge): those voxels get the exact per-voxel answer and its convergence
   flag.

The centre check passes when the interpolation error there is below ``accuracy / CHECK_SAFETY``;
the factor covers cells whose error peaks off-centre (measured on shear bands: the largest error in
a cell is at most about 1.6 times its centre error, see ``tests/engine/test_inverse_lattice.py``).

Positions are ``(z, y, x)`` voxels.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit, prange

from ._numba_setup import KERNEL_OPTIONS
from .field_spline_kernels import HULL_TOLERANCE, _eval_one, newton_inverse

#: A cell passes when its centre's interpolation error is below ``accuracy / CHECK_SAFETY``.
CHECK_SAFETY = 4.0

#: Interpolation nodes per axis (quintic Lagrange), and how many lie below a cell's first node.
TAPS = 6
BELOW = 2

#: A cell fails when the volume ratio ``det(I + du/dX)`` is below this at one of its nodes (folds).
MIN_DETERMINANT = 0.2

#: Largest coarse stride (voxels) chosen automatically.
MAX_STRIDE = 4


class LatticeInverse(NamedTuple):
    """:func:`invert_lattice`'s answer for the ``N`` voxels of a box, in C order.

    Attributes
    ----------
    positions : ndarray, shape (N, 3), float64
        Reference positions ``X`` ``(z, y, x)`` in voxels.
    converged : ndarray, shape (N,), bool
        False where the per-voxel Newton (in cells that failed the check) did not converge.
    in_hull : ndarray, shape (N,), bool
        Where ``X`` lies in the grid's hull.
    exact : ndarray, shape (N,), bool
        Voxels solved by Newton (coarse nodes and the voxels of failed cells); the others are
        interpolated.
    """

    positions: np.ndarray
    converged: np.ndarray
    in_hull: np.ndarray
    exact: np.ndarray


def polish_step(accuracy: float) -> float:
    """Newton step (voxels) below which a voxel of a failed cell is accepted.

    Newton's error after a step of length ``d`` is about ``C d^2`` with ``C ~ |d2u/dX2| /
    (1 - |du/dX|)``, a few tenths at most where the check lets cells through; steps below
    ``sqrt(accuracy / 10)`` (0.01 voxel for 1e-3) therefore leave errors below ``accuracy / 10``.
    Starting from the interpolated guess one step usually suffices.
    """
    return float(np.sqrt(accuracy / 10.0))


def auto_stride(step) -> int:
    """Coarse stride for a grid of node spacing ``step`` (voxels): half the smallest step, 1 to 4.

    Interpolation errors grow as ``(stride / step)^4``; half a node step keeps the check's failure
    rate low on fields the node grid resolves.
    """
    return int(max(1, min(MAX_STRIDE, np.floor(float(np.min(step)) / 2.0))))


@njit(inline="always", **KERNEL_OPTIONS)
def _lagrange_weights(t):
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


@njit(**KERNEL_OPTIONS)
def _axis_weights(start, count, stride):
    """Per voxel of one box axis: first of its 4 coarse nodes (box-local) and their weights."""
    first_cell = start // stride
    node = np.empty(count, np.int64)
    weight = np.empty((count, TAPS))
    for i in range(count):
        cell = (start + i) // stride
        t = (start + i - cell * stride) / stride
        node[i] = cell - first_cell
        w = _lagrange_weights(t)
        for k in range(TAPS):
            weight[i, k] = w[k]
    return node, weight


@njit(inline="always", **KERNEL_OPTIONS)
def _solve(spline, z, y, x, max_iterations, tolerance, position, value, jacobian):
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


@njit(parallel=True, **KERNEL_OPTIONS)
def _coarse_inverse(spline, first_node, stride, max_iterations, tolerance, v, ok, determinant):
    """Exact inverse displacement ``v = x - X`` (nz, ny, nx, 3) at coarse nodes ``first_node + i``.

    Cold starts only, so a node's answer does not depend on its neighbours. ``determinant`` gets
    ``det(I + du/dX)`` at the last Newton iterate.
    """
    nz, ny, nx = ok.shape
    for a in prange(nz):
        value = np.empty(3)
        jacobian = np.empty((3, 3))
        position = np.empty(3)
        z = float((first_node[0] + a) * stride)
        for b in range(ny):
            y = float((first_node[1] + b) * stride)
            for d in range(nx):
                x = float((first_node[2] + d) * stride)
                _eval_one(*spline, z, y, x, value)
                position[0] = z - value[0]
                position[1] = y - value[1]
                position[2] = x - value[2]
                ok[a, b, d] = _solve(
                    spline, z, y, x, max_iterations, tolerance, position, value, jacobian
                )
                v[a, b, d, 0] = z - position[0]
                v[a, b, d, 1] = y - position[1]
                v[a, b, d, 2] = x - position[2]
                determinant[a, b, d] = np.linalg.det(np.eye(3) + jacobian)


@njit(parallel=True, **KERNEL_OPTIONS)
def _check_cells(
    spline, first_node, stride, max_iterations, tolerance, limit, v, ok, determinant, fail
):
    """Flag the coarse cells (nz, ny, nx) whose interpolation cannot be trusted.

    Cell ``(a, b, d)`` lies between box-local coarse nodes ``a + BELOW`` and ``a + BELOW + 1``
    (and so on) and is interpolated from nodes ``a .. a + TAPS - 1``. It fails when one of those
    did not converge or has a volume ratio below :data:`MIN_DETERMINANT`, or when the interpolated
    inverse at its centre differs from the exact one by ``limit`` voxels or more (or Newton does
    not converge there).
    """
    centre = _lagrange_weights(0.5)
    nz, ny, nx = fail.shape
    for a in prange(nz):
        value = np.empty(3)
        jacobian = np.empty((3, 3))
        position = np.empty(3)
        guess = np.empty(3)
        for b in range(ny):
            for d in range(nx):
                good = True
                guess[:] = 0.0
                for i in range(TAPS):
                    for j in range(TAPS):
                        wij = centre[i] * centre[j]
                        for k in range(TAPS):
                            node = (a + i, b + j, d + k)
                            if not ok[node] or determinant[node] < MIN_DETERMINANT:
                                good = False
                            w = wij * centre[k]
                            for c in range(3):
                                guess[c] += w * v[a + i, b + j, d + k, c]
                if good:
                    z = (first_node[0] + a + BELOW + 0.5) * stride
                    y = (first_node[1] + b + BELOW + 0.5) * stride
                    x = (first_node[2] + d + BELOW + 0.5) * stride
                    position[0] = z - guess[0]
                    position[1] = y - guess[1]
                    position[2] = x - guess[2]
                    good = _solve(
                        spline, z, y, x, max_iterations, tolerance, position, value, jacobian
                    )
                    error = max(
                        abs(z - guess[0] - position[0]),
                        abs(y - guess[1] - position[1]),
                        abs(x - guess[2] - position[2]),
                    )
                    good = good and error < limit
                fail[a, b, d] = not good


@njit(parallel=True, **KERNEL_OPTIONS)
def _interpolate(
    spline,
    grid_shape,
    box_start,
    z_node,
    z_weight,
    y_node,
    y_weight,
    x_node,
    x_weight,
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
    """Interpolate ``v`` to every voxel of the box (C order), Newton in the failed cells."""
    origin = spline[2]
    step = spline[3]
    nz = z_node.shape[0]
    ny = y_node.shape[0]
    nx = x_node.shape[0]
    cy, cx = v.shape[1], v.shape[2]
    for a in prange(nz):
        value = np.empty(3)
        jacobian = np.empty((3, 3))
        position = np.empty(3)
        plane = np.zeros((cy, cx, 3))
        row = np.empty((cx, 3))
        za = z_node[a]
        for i in range(TAPS):
            w = z_weight[a, i]
            if w != 0.0:
                source = v[za + i]
                for j in range(cy):
                    for k in range(cx):
                        for c in range(3):
                            plane[j, k, c] += w * source[j, k, c]
        z = float(box_start[0] + a)
        z_node_voxel = z_weight[a, BELOW] == 1.0
        for b in range(ny):
            yb = y_node[b]
            row[:] = 0.0
            for j in range(TAPS):
                w = y_weight[b, j]
                if w != 0.0:
                    for k in range(cx):
                        for c in range(3):
                            row[k, c] += w * plane[yb + j, k, c]
            y = float(box_start[1] + b)
            zy_node_voxel = z_node_voxel and y_weight[b, BELOW] == 1.0
            index = (a * ny + b) * nx
            for d in range(nx):
                xd = x_node[d]
                w = x_weight[d]
                for c in range(3):
                    value[c] = (
                        w[0] * row[xd, c]
                        + w[1] * row[xd + 1, c]
                        + w[2] * row[xd + 2, c]
                        + w[3] * row[xd + 3, c]
                        + w[4] * row[xd + 4, c]
                        + w[5] * row[xd + 5, c]
                    )
                x = float(box_start[2] + d)
                position[0] = z - value[0]
                position[1] = y - value[1]
                position[2] = x - value[2]
                solved = zy_node_voxel and w[BELOW] == 1.0  # a coarse node: v is exact there
                ok = True
                if solved:
                    ok = node_ok[za + BELOW, yb + BELOW, xd + BELOW]
                elif fail[za, yb, xd]:
                    solved = True
                    ok = _solve(spline, z, y, x, max_iterations, polish, position, value, jacobian)
                positions[index + d, 0] = position[0]
                positions[index + d, 1] = position[1]
                positions[index + d, 2] = position[2]
                converged[index + d] = ok
                exact[index + d] = solved
                in_hull[index + d] = (
                    _inside(position[0], origin[0], step[0], grid_shape[0])
                    and _inside(position[1], origin[1], step[1], grid_shape[1])
                    and _inside(position[2], origin[2], step[2], grid_shape[2])
                )


@njit(inline="always", **KERNEL_OPTIONS)
def _inside(position, origin, step, n):
    t = (position - origin) / step
    return t >= -HULL_TOLERANCE and t <= n - 1 + HULL_TOLERANCE


def invert_lattice(
    spline,
    box,
    max_iterations: int = 50,
    tolerance: float = 1e-4,
    accuracy: float = 1e-3,
    stride: int | None = None,
) -> LatticeInverse:
    """Reference positions ``X`` with ``X + u(X) = x`` at every voxel ``x`` of ``box``.

    Parameters
    ----------
    spline : FieldSpline
        A displacement spline (3 components), :class:`.field_spline.FieldSpline`.
    box : tuple of 3 slices
        Voxel index ranges ``(z, y, x)`` of the loaded state (whole-volume indices, step 1).
    max_iterations, tolerance : int, float
        Newton's iteration limit and step tolerance (voxels), as in
        :meth:`.field_spline.FieldSpline.invert`.
    accuracy : float
        Largest interpolation error (voxels) accepted in a coarse cell; cells above it are solved
        voxel by voxel.
    stride : int, optional
        Coarse lattice spacing in voxels (default :func:`auto_stride` of the node step). 1 solves
        every voxel by Newton.

    Returns
    -------
    LatticeInverse
        Per voxel of ``box`` in C order.
    """
    if spline.components != 3:
        raise ValueError("invert_lattice needs a displacement spline (3 components)")
    stride = auto_stride(spline.step) if stride is None else int(stride)
    if stride < 1:
        raise ValueError(f"stride must be a positive number of voxels, got {stride}")
    if not accuracy > 0:
        raise ValueError(f"accuracy must be a positive number of voxels, got {accuracy}")
    starts = np.array([s.start for s in box], np.int64)
    counts = np.array([s.stop - s.start for s in box], np.int64)
    n = int(np.prod(counts))
    result = LatticeInverse(
        np.empty((n, 3)), np.empty(n, np.bool_), np.empty(n, np.bool_), np.empty(n, np.bool_)
    )
    if n == 0:
        return result
    first_cell = starts // stride
    first_node = first_cell - BELOW
    cells = (starts + counts - 1) // stride - first_cell + 1
    nodes = tuple(int(n) for n in cells + TAPS - 1)
    args = (
        spline.extended,
        spline.pad,
        spline.origin,
        spline.step,
        spline.trend_offset,
        spline.trend_matrix,
    )
    iterations = (int(max_iterations), float(tolerance))
    v = np.empty((*nodes, 3))
    node_ok = np.empty(nodes, np.bool_)
    determinant = np.empty(nodes)
    _coarse_inverse(args, first_node, stride, *iterations, v, node_ok, determinant)
    fail = np.zeros(tuple(int(n) for n in cells), np.bool_)
    if stride > 1:
        limit = float(accuracy) / CHECK_SAFETY
        _check_cells(args, first_node, stride, *iterations, limit, v, node_ok, determinant, fail)
    axes = [_axis_weights(int(starts[a]), int(counts[a]), stride) for a in range(3)]
    polish = max(float(tolerance), polish_step(accuracy))
    _interpolate(
        args,
        spline.grid_shape,
        starts,
        *axes[0],
        *axes[1],
        *axes[2],
        int(max_iterations),
        polish,
        v,
        node_ok,
        fail,
        *result,
    )
    return result
