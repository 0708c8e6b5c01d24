"""The inverse of a field spline on a voxel lattice: exact on a coarse lattice, interpolated, checked.

The forward warp needs, at every loaded-state voxel ``x``, the reference position ``X`` with
``X + u(X) = x``. Newton at every voxel (:meth:`.field_spline.FieldSpline.invert`) costs about two
tricubic evaluations of the field with its Jacobian per voxel. The inverse displacement
``v(x) = x - X(x)`` is nearly as smooth as the field, so :class:`LatticeInverter`

1. solves the inverse (Newton, to a step of :func:`polish_step`) on a coarse lattice of voxels
   whose indices are multiples of ``stride`` along each axis (:func:`auto_stride`: half the node
   step, at most 4). The indices are the whole volume's, not the box's, and each node's Newton
   start is fixed by them (warm-start chains along x, extrapolated from the two nodes below,
   restart cold every :data:`CHAIN` nodes): a box's answer does not depend on how a volume is
   cut into boxes (tiled and in-memory warps agree bit for bit);
2. checks every coarse cell (the ``stride³`` voxels between 8 coarse nodes) at 7 points, its low
   corner moved by half a cell along 1, 2 or 3 axes (edge midpoints, face centres, centre: where
   the interpolation errors of each axis peak; a point on a shared face or edge counts for every
   cell that has it): the residual ``X + u(X) - x`` of the interpolated inverse times the
   inverse gain ``||(I + du/dX)^-1||`` must stay below ``accuracy / CHECK_SAFETY``. A cell also
   fails when one of its 6³ interpolation nodes did not converge or is nearly singular
   (:data:`MAX_GAIN`: folds, extreme compression);
3. interpolates ``v`` to every voxel (6-point Lagrange along each axis, separably: about 20
   multiply-adds per voxel; the kernels are in :mod:`.inverse_per_voxel`, which can also sample the
   reference volume there at once, :meth:`LatticeInverter.warp`) in the cells that pass, and
   runs Newton per voxel, from the interpolated guess, in the cells that fail (narrow shear bands, folds, the kinks of the
   extrapolated field beyond the grid's hull, points that do not converge): those voxels get
   Newton's answer (to a step of :func:`polish_step`) and its convergence flag.

Measured on shear bands and smooth fields (``tests/engine/test_inverse_lattice.py``): the largest
error in a cell that passes is at most 1.15 times the largest check-point estimate, so
``CHECK_SAFETY = 2`` keeps every voxel within ``accuracy``. Where a cell's 8 corners all map at
least a voxel outside the grid's hull, the field is an extrapolation and ``outside_accuracy``
(:data:`OUTSIDE_RELAXATION` times ``accuracy`` by default) applies instead.

Positions are ``(z, y, x)`` voxels.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit, prange

from .._numba_setup import KERNEL_OPTIONS
from .field_spline_kernels import hull_bounds
from .inverse_per_voxel import (
    BELOW,
    TAPS,
    axis_weights,
    evaluate,
    interpolate_planes,
    lagrange_weights,
    phase_table,
    region_bounds,
    solve,
    warp_planes,
)

#: A cell passes when its centre's interpolation error is below ``accuracy / CHECK_SAFETY``.
CHECK_SAFETY = 2.0

#: A cell fails when the inverse gain ``||(I + du/dX)^-1||`` exceeds this at one of its nodes
#: (the map is nearly singular there: folds, extreme compression).
MAX_GAIN = 5.0

#: Outside the grid's hull the field is an extrapolation (linear padding of the node values, off
#: by far more than a tenth of a voxel from any real motion there): its inverse is accepted within
#: this many times the accuracy asked in the hull.
OUTSIDE_RELAXATION = 10.0

#: Coarse nodes per warm-start chain along x (whole-volume coarse indices, see _coarse_inverse).
CHAIN = 8

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


@njit(**KERNEL_OPTIONS)
def _inverse_gain(jacobian):
    """``||(I + J)^-1||_inf`` (the factor from a residual to a position error), inf if singular."""
    a00 = 1.0 + jacobian[0, 0]
    a01 = jacobian[0, 1]
    a02 = jacobian[0, 2]
    a10 = jacobian[1, 0]
    a11 = 1.0 + jacobian[1, 1]
    a12 = jacobian[1, 2]
    a20 = jacobian[2, 0]
    a21 = jacobian[2, 1]
    a22 = 1.0 + jacobian[2, 2]
    c00 = a11 * a22 - a12 * a21
    c01 = a02 * a21 - a01 * a22
    c02 = a01 * a12 - a02 * a11
    c10 = a12 * a20 - a10 * a22
    c11 = a00 * a22 - a02 * a20
    c12 = a02 * a10 - a00 * a12
    c20 = a10 * a21 - a11 * a20
    c21 = a01 * a20 - a00 * a21
    c22 = a00 * a11 - a01 * a10
    det = a00 * c00 + a10 * c01 + a20 * c02
    if not abs(det) > 1e-12:
        return np.inf
    rows = max(
        abs(c00) + abs(c01) + abs(c02),
        abs(c10) + abs(c11) + abs(c12),
        abs(c20) + abs(c21) + abs(c22),
    )
    return rows / abs(det)


@njit(parallel=True, **KERNEL_OPTIONS)
def _coarse_inverse(spline, first_node, stride, max_iterations, tolerance, v, ok, gain):
    """Exact inverse displacement ``v = x - X`` (nz, ny, nx, 3) at coarse nodes ``first_node + i``.

    Along x each node starts from its converged lower neighbours' answers: extrapolated linearly
    from the two below it (one Newton step to ``tolerance`` where the field is smooth), or the
    one below shifted by the stride. The chains restart cold (``X = x - u(x)``) at whole-volume
    coarse indices ``CHAIN k - BELOW`` (a whole volume's first node), so a node's answer does
    not depend on where a box begins. ``gain`` gets :func:`_inverse_gain` at the last Newton
    iterate (NaN where Newton did not converge).
    """
    nz, ny, nx = ok.shape
    # whole-volume coarse x index of the chain holding the box's first node
    chain_start = ((first_node[2] + BELOW) // CHAIN) * CHAIN - BELOW
    for a in prange(nz):
        value = np.empty(3)
        jacobian = np.empty((3, 3))
        position = np.empty(3)
        below = np.empty(3)
        z = float((first_node[0] + a) * stride)
        for b in range(ny):
            y = float((first_node[1] + b) * stride)
            solved = 0  # converged nodes in a row below this one, in this chain
            for node in range(chain_start, first_node[2] + nx):
                x = float(node * stride)
                if (node + BELOW) % CHAIN == 0:
                    solved = 0
                if solved >= 2:
                    for c in range(3):
                        last = position[c]
                        position[c] = 2.0 * last - below[c]
                        below[c] = last
                elif solved == 1:
                    for c in range(3):
                        below[c] = position[c]
                    position[2] += stride
                else:
                    evaluate(spline, z, y, x, value)
                    position[0] = z - value[0]
                    position[1] = y - value[1]
                    position[2] = x - value[2]
                converged = solve(
                    spline, z, y, x, max_iterations, tolerance, position, value, jacobian
                )
                solved = solved + 1 if converged else 0
                d = node - first_node[2]
                if d >= 0:
                    ok[a, b, d] = converged
                    v[a, b, d, 0] = z - position[0]
                    v[a, b, d, 1] = y - position[1]
                    v[a, b, d, 2] = x - position[2]
                    gain[a, b, d] = _inverse_gain(jacobian) if converged else np.nan


@njit(inline="always", **KERNEL_OPTIONS)
def _halves_x(source, count, centre, out):
    """``source`` (n, m, 3) at x node ``d + BELOW`` (``out[0]``) and half a cell above it
    (``out[1]``), for ``d < count``: ``out`` (2, n, count, 3)."""
    for j in range(source.shape[0]):
        for d in range(count):
            for c in range(3):
                out[0, j, d, c] = source[j, d + BELOW, c]
                total = 0.0
                for k in range(TAPS):
                    total += centre[k] * source[j, d + k, c]
                out[1, j, d, c] = total


@njit(parallel=True, **KERNEL_OPTIONS)
def _check_points(spline, grid_shape, first_node, stride, limit, outside_limit, v, gain, bad):
    """Check the interpolation at 7 points of each coarse cell (nz, ny, nx) of ``bad``.

    The points are the cell's low corner moved by half a cell along 1, 2 or 3 axes (3 edge
    midpoints, 3 face centres, the centre: where the per-axis interpolation errors peak). A point
    fails when its residual ``X + u(X) - x`` times the largest inverse gain at the cell's corner
    nodes (an estimate of the position error, see :func:`_inverse_gain`) reaches ``limit`` voxels;
    bit ``4 oz + 2 oy + ox`` of ``bad`` is set for the point at offsets ``o / 2``. Cells whose 8
    corners all map at least a voxel outside the grid's hull use ``outside_limit``.

    The interpolated inverse at the points is made plane of cells by plane of cells, separably
    (along z, then x, then y: each node row's half-cell values once, not once per cell).
    """
    origin = spline[2]
    step = spline[3]
    centre = lagrange_weights(0.5)
    nz, ny, nx = bad.shape
    rows, columns = v.shape[1], v.shape[2]
    for a in prange(nz):
        value = np.empty(3)
        along_z = np.empty((2, rows, columns, 3))  # (oz, y node, x node, component)
        along_x = np.empty((2, rows, nx, 3))  # (ox, y node, cell, component)
        guess = np.empty((2, 2, 2, ny, nx, 3))  # (oz, oy, ox, cell y, cell x, component)
        along_z[0] = v[a + BELOW]
        along_z[1] = 0.0
        for i in range(TAPS):
            w = centre[i]
            for j in range(rows):
                for k in range(columns):
                    for c in range(3):
                        along_z[1, j, k, c] += w * v[a + i, j, k, c]
        for oz in range(2):
            _halves_x(along_z[oz], nx, centre, along_x)
            for ox in range(2):
                for b in range(ny):
                    for d in range(nx):
                        for c in range(3):
                            guess[oz, 0, ox, b, d, c] = along_x[ox, b + BELOW, d, c]
                            total = 0.0
                            for j in range(TAPS):
                                total += centre[j] * along_x[ox, b + j, d, c]
                            guess[oz, 1, ox, b, d, c] = total
        for b in range(ny):
            for d in range(nx):
                g = 0.0
                outside = np.inf
                for i in range(2):
                    for j in range(2):
                        for k in range(2):
                            node = (a + BELOW + i, b + BELOW + j, d + BELOW + k)
                            g = max(g, gain[node])
                            far = 0.0
                            for c in range(3):
                                p = (first_node[c] + node[c]) * stride - v[
                                    node[0], node[1], node[2], c
                                ]
                                low = origin[c] - p
                                high = p - (origin[c] + (grid_shape[c] - 1) * step[c])
                                far = max(far, low, high)
                            outside = min(outside, far)
                cell_limit = outside_limit if outside >= 1.0 else limit
                mask = 0
                for bit in range(1, 8):
                    oz = (bit >> 2) & 1
                    oy = (bit >> 1) & 1
                    ox = bit & 1
                    z = (first_node[0] + a + BELOW + 0.5 * oz) * stride
                    y = (first_node[1] + b + BELOW + 0.5 * oy) * stride
                    x = (first_node[2] + d + BELOW + 0.5 * ox) * stride
                    g0 = guess[oz, oy, ox, b, d, 0]
                    g1 = guess[oz, oy, ox, b, d, 1]
                    g2 = guess[oz, oy, ox, b, d, 2]
                    evaluate(spline, z - g0, y - g1, x - g2, value)
                    residual = max(abs(value[0] - g0), abs(value[1] - g1), abs(value[2] - g2))
                    if not residual * g < cell_limit:  # also catches NaN gains
                        mask |= 1 << bit
                bad[a, b, d] = mask


@njit(parallel=True, **KERNEL_OPTIONS)
def _combine(ok, gain, bad, fail):
    """A cell fails if a node it is interpolated from did not converge or is (nearly) singular,
    or if a check point on its closure failed (its own, or its upper neighbours' low faces)."""
    nz, ny, nx = fail.shape
    for a in prange(nz):
        for b in range(ny):
            for d in range(nx):
                failed = False
                for i in range(TAPS):
                    for j in range(TAPS):
                        for k in range(TAPS):
                            node = (a + i, b + j, d + k)
                            if not ok[node] or not gain[node] <= MAX_GAIN:
                                failed = True
                for delta in range(8):
                    dz = (delta >> 2) & 1
                    dy = (delta >> 1) & 1
                    dx = delta & 1
                    # points of the neighbour a + delta on this cell's closure: offset 0 where
                    # delta is 1
                    mask = bad[a + dz, b + dy, d + dx]
                    for bit in range(1, 8):
                        if (mask >> bit) & 1 and (bit & delta) == 0:
                            failed = True
                fail[a, b, d] = failed


@njit(**KERNEL_OPTIONS)
def _coarse_stage(
    spline, grid_shape, first_node, stride, max_iterations, tolerance, limit, outside_limit,
    v, ok, gain, bad, fail,
):  # fmt: skip
    """:func:`_coarse_inverse`, then (``stride`` > 1) :func:`_check_points` and :func:`_combine`:
    one compiled entry, so one cache load per process instead of three."""
    _coarse_inverse(spline, first_node, stride, max_iterations, tolerance, v, ok, gain)
    if stride > 1:
        _check_points(spline, grid_shape, first_node, stride, limit, outside_limit, v, gain, bad)
        _combine(ok, gain, bad, fail)


class LatticeInverter:
    """The coarse stage of :func:`invert_lattice` for a box, then its voxels plane range by range.

    Building one runs Newton at the coarse nodes and checks every cell (a few percent of the
    work); :meth:`solve` interpolates (and runs Newton in failed cells) for any range of the
    box's z planes, so a large box can be processed in slabs without repeating the coarse stage
    and without holding all its positions.

    Parameters are those of :func:`invert_lattice`.
    """

    def __init__(
        self,
        spline,
        box,
        max_iterations: int = 50,
        tolerance: float = 1e-4,
        accuracy: float = 1e-3,
        stride: int | None = None,
        outside_accuracy: float | None = None,
    ) -> None:
        if spline.components != 3:
            raise ValueError("invert_lattice needs a displacement spline (3 components)")
        stride = auto_stride(spline.step) if stride is None else int(stride)
        if stride < 1:
            raise ValueError(f"stride must be a positive number of voxels, got {stride}")
        outside_accuracy = (
            OUTSIDE_RELAXATION * accuracy if outside_accuracy is None else outside_accuracy
        )
        if not (accuracy > 0 and outside_accuracy > 0):
            raise ValueError(
                f"accuracy and outside_accuracy must be positive numbers of voxels, got "
                f"{accuracy} and {outside_accuracy}"
            )
        self.spline = spline
        self.box = tuple(slice(int(s.start), int(s.stop)) for s in box)
        self.stride = stride
        self.max_iterations = int(max_iterations)
        self.polish = max(float(tolerance), polish_step(accuracy))
        self.hull = hull_bounds(spline)
        self.starts = np.array([s.start for s in self.box], np.int64)
        self.counts = np.array([s.stop - s.start for s in self.box], np.int64)
        self.args = (
            spline.extended,
            spline.pad,
            spline.origin,
            spline.step,
            spline.trend_offset,
            spline.trend_matrix,
        )
        if np.prod(self.counts) == 0:
            return
        first_cell = self.starts // stride
        first_node = first_cell - BELOW
        cells = (self.starts + self.counts - 1) // stride - first_cell + 1
        # one more node and check cell above the box: the upper faces of its last cells
        nodes = tuple(int(n) for n in cells + TAPS)
        self.v = np.empty((*nodes, 3))
        self.node_ok = np.empty(nodes, np.bool_)
        gain = np.empty(nodes)
        # the nodes to a step of polish_step, like the voxels of failed cells: errors below
        # accuracy / 10, and the check sees them (they enter the interpolated guesses)
        iterations = (self.max_iterations, self.polish)
        self.fail = np.zeros(tuple(int(n) for n in cells), np.bool_)
        bad = np.empty(tuple(int(n) for n in cells + 1) if stride > 1 else (0, 0, 0), np.int64)
        limits = (float(accuracy) / CHECK_SAFETY, float(outside_accuracy) / CHECK_SAFETY)
        _coarse_stage(
            self.args, spline.grid_shape, first_node, stride, *iterations, *limits,
            self.v, self.node_ok, gain, bad, self.fail,
        )  # fmt: skip
        # the fill kernels read v component by component (their loops vectorise)
        self.v_planes = np.ascontiguousarray(np.moveaxis(self.v, -1, 0))
        x_start, x_count = int(self.starts[2]), int(self.counts[2])
        self.axes = [
            axis_weights(int(self.starts[1]), int(self.counts[1]), stride),
            (axis_weights(x_start, x_count, stride)[0], *phase_table(x_start, x_count, stride)),
        ]

    def _plane_args(self, start: int, stop: int):
        """The fill kernels' arguments for the box's z planes ``start .. stop`` (box indices)."""
        z0 = int(self.starts[0])
        z_node, z_weight = axis_weights(z0 + start, stop - start, self.stride)
        z_node += (z0 + start) // self.stride - z0 // self.stride
        starts = self.starts.copy()
        starts[0] = z0 + start
        return (
            self.args,
            *self.hull,
            starts,
            z_node,
            z_weight,
            *self.axes[0],
            *self.axes[1],
            self.max_iterations,
            self.polish,
            self.v_planes,
            self.node_ok,
            self.fail,
        )

    def _planes(self, planes: slice | None) -> tuple[int, int]:
        start, stop, _ = (planes or slice(None)).indices(int(self.counts[0]))
        return start, max(start, stop)

    def solve(self, planes: slice | None = None) -> LatticeInverse:
        """Positions for the box's z planes ``planes`` (indices within the box; all by default)."""
        start, stop = self._planes(planes)
        n = (stop - start) * int(self.counts[1] * self.counts[2])
        result = LatticeInverse(
            np.empty((n, 3)), np.empty(n, np.bool_), np.empty(n, np.bool_), np.empty(n, np.bool_)
        )
        if n > 0:
            interpolate_planes(*self._plane_args(start, stop), *result)
        return result

    def warp(
        self, coefficients: np.ndarray, planes: slice | None = None, *, region=None
    ) -> tuple[np.ndarray, np.ndarray]:
        """The forward warp of the box's z planes ``planes``: ``G(X)`` sampled as ``X`` is made.

        Parameters
        ----------
        coefficients : ndarray, shape (nz, ny, nx), float32
            ``interpolation.prefilter(G)`` of the whole reference volume (whole-volume indices).
        planes : slice, optional
            z planes within the box (all by default).
        region : ndarray (4, 3), optional
            When ``coefficients`` are a region of ``G`` (out of core):
            :func:`.inverse_per_voxel.region_bounds` of it; voxels whose ``X`` leaves its valid part
            come back ``+inf``. Default: the coefficients are the whole ``G``.

        Returns
        -------
        values : ndarray, shape (planes, box ny, box nx), float32
            ``G(X)`` at the positions :meth:`solve` gives (the same bit for bit); NaN where
            Newton did not converge or ``X`` is outside ``G``. Equal to
            ``interpolation.sample(coefficients, X)`` to float32 rounding.
        in_hull : ndarray of bool, same shape
            Where ``X`` lies in the grid's hull.
        """
        start, stop = self._planes(planes)
        shape = (stop - start, int(self.counts[1]), int(self.counts[2]))
        values = np.empty(shape, np.float32)
        in_hull = np.empty(shape, np.bool_)
        if values.size > 0:
            coefficients = np.ascontiguousarray(coefficients, dtype=np.float32)
            if region is None:
                region = region_bounds(coefficients.shape)
            warp_planes(*self._plane_args(start, stop), coefficients, region, values, in_hull)
        return values, in_hull


def invert_lattice(
    spline,
    box,
    max_iterations: int = 50,
    tolerance: float = 1e-4,
    accuracy: float = 1e-3,
    stride: int | None = None,
    outside_accuracy: float | None = None,
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
    outside_accuracy : float, optional
        The same for cells that map at least a voxel outside the grid's hull, where the field is
        extrapolated (default :data:`OUTSIDE_RELAXATION` times ``accuracy``).

    Returns
    -------
    LatticeInverse
        Per voxel of ``box`` in C order.
    """
    inverter = LatticeInverter(
        spline, box, max_iterations, tolerance, accuracy, stride, outside_accuracy
    )
    return inverter.solve()
