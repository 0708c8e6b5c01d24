"""The cubic-spline field: a grid field evaluated anywhere (paper step c, densification).

A :class:`~napari_dvc_correct.engine.field.DisplacementField` lives on a coarse grid of points of
interest. The self-correcting strategy (SPEC §3, paper Fig. 3) needs it at every voxel:
:class:`FieldSpline` is a cubic B-spline through the grid nodes, evaluated at any points
(:meth:`FieldSpline.__call__`), separably on a voxel lattice (:meth:`FieldSpline.lattice`) and
inverted (:meth:`FieldSpline.invert`, Newton steps with the spline's exact Jacobian);
:func:`densify` and :func:`iter_dense` evaluate it on a whole volume, slab by slab, so a 512³
volume never needs a dense ``3 × 512³`` array. Warping volumes by it is :mod:`.warp`'s job, gray
residuals :mod:`.residual`'s.

All positions are ``(z, y, x)`` in reference voxels; values are in voxels.

How the field spline is built
-----------------------------
The global affine trend of the node values is removed (least squares), the remainder is padded by
:data:`PAD_NODES` nodes on each side by linear extrapolation and interpolated by a cubic B-spline
(``scipy.ndimage.spline_filter``, mirror boundary beyond the padding); the trend is added back at
evaluation. An affine field is therefore reproduced exactly everywhere, inside and outside the grid,
and smooth fields are continued naturally over the few voxels between the outermost nodes and the
volume's border (where subvolumes of the boundary nodes still reach). Beyond the padding the
non-affine part is held constant.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
from numba import njit, prange
from scipy import ndimage

from ._numba_setup import KERNEL_OPTIONS
from .field import DisplacementField
from .interpolation import _mirror, bspline_derivative_weights, bspline_weights
from .slabs import iter_slabs

#: Nodes added on each side of the grid (linear extrapolation) before the spline fit.
PAD_NODES = 3

#: Voxels per chunk for slab-by-slab evaluation (about 50 MB of float64 positions).
DEFAULT_CHUNK_VOXELS = 1 << 21

#: Hull tolerance in grid units: a position within this of the outermost node is inside.
_HULL_TOLERANCE = 1e-6


# --- kernels ----------------------------------------------------------------------------------
@njit(inline="always", **KERNEL_OPTIONS)
def _clamp(value, low, high):
    return min(max(value, low), high)


@njit(**KERNEL_OPTIONS)
def _eval_one(coefficients, pad, origin, step, trend_offset, trend_matrix, z, y, x, out):
    """Spline value at ``(z, y, x)`` (voxels) into ``out`` (C,); always extrapolates."""
    pz, py, px, nc = coefficients.shape
    tz = (z - origin[0]) / step[0]
    ty = (y - origin[1]) / step[1]
    tx = (x - origin[2]) / step[2]
    qz = _clamp(tz + pad, 0.0, pz - 1.0)
    qy = _clamp(ty + pad, 0.0, py - 1.0)
    qx = _clamp(tx + pad, 0.0, px - 1.0)
    fz = np.floor(qz)
    fy = np.floor(qy)
    fx = np.floor(qx)
    wz = bspline_weights(qz - fz)
    wy = bspline_weights(qy - fy)
    wx = bspline_weights(qx - fx)
    iz = int(fz)
    iy = int(fy)
    ix = int(fx)
    for c in range(nc):
        out[c] = trend_offset[c] + trend_matrix[c, 0] * tz + trend_matrix[c, 1] * ty
        out[c] += trend_matrix[c, 2] * tx
    for a in range(4):
        za = _mirror(iz - 1 + a, pz)
        for b in range(4):
            yb = _mirror(iy - 1 + b, py)
            wab = wz[a] * wy[b]
            for d in range(4):
                xd = _mirror(ix - 1 + d, px)
                w = wab * wx[d]
                for c in range(nc):
                    out[c] += w * coefficients[za, yb, xd, c]


@njit(parallel=True, **KERNEL_OPTIONS)
def _eval_points(
    coefficients,
    pad,
    origin,
    step,
    trend_offset,
    trend_matrix,
    grid_shape,
    points,
    nan_outside,
    out,
):
    nc = coefficients.shape[3]
    for i in prange(points.shape[0]):
        z = points[i, 0]
        y = points[i, 1]
        x = points[i, 2]
        if nan_outside:
            inside = True
            for a in range(3):
                t = (points[i, a] - origin[a]) / step[a]
                if t < -_HULL_TOLERANCE or t > grid_shape[a] - 1 + _HULL_TOLERANCE:
                    inside = False
            if not inside:
                for c in range(nc):
                    out[i, c] = np.nan
                continue
        if not (np.isfinite(z) and np.isfinite(y) and np.isfinite(x)):
            for c in range(nc):
                out[i, c] = np.nan
            continue
        _eval_one(coefficients, pad, origin, step, trend_offset, trend_matrix, z, y, x, out[i])


@njit(**KERNEL_OPTIONS)
def _eval_one_with_jacobian(
    coefficients, pad, origin, step, trend_offset, trend_matrix, point, out, jacobian, taps, index
):
    """Value (3,) and Jacobian ``d out_c / d X_a`` (3, 3) of a displacement spline at ``point``.

    ``taps`` (3, 10) and ``index`` (3, 4) are work arrays reused between calls (the hot loop
    allocates nothing): per axis the grid coordinate, the floor of the padded coordinate, 4
    weights and 4 derivative weights (per voxel), and the 4 mirrored tap indices.
    """
    sizes = coefficients.shape
    nc = sizes[3]
    for a in range(3):
        t = (point[a] - origin[a]) / step[a]
        q = t + pad
        clamped = q < 0.0 or q > sizes[a] - 1.0
        q = _clamp(q, 0.0, sizes[a] - 1.0)
        f = np.floor(q)
        w = bspline_weights(q - f)
        d = bspline_derivative_weights(q - f)
        taps[a, 0] = t
        taps[a, 1] = f
        for k in range(4):
            taps[a, 2 + k] = w[k]
            taps[a, 6 + k] = 0.0 if clamped else d[k] / step[a]
            index[a, k] = _mirror(int(f) - 1 + k, sizes[a])
    for c in range(nc):
        out[c] = trend_offset[c]
        for a in range(3):
            out[c] += trend_matrix[c, a] * taps[a, 0]
            jacobian[c, a] = trend_matrix[c, a] / step[a]
    for i in range(4):
        za = index[0, i]
        wz = taps[0, 2 + i]
        dz = taps[0, 6 + i]
        for j in range(4):
            yb = index[1, j]
            wy = taps[1, 2 + j]
            dy = taps[1, 6 + j]
            for k in range(4):
                xd = index[2, k]
                wx = taps[2, 2 + k]
                dx = taps[2, 6 + k]
                w = wz * wy * wx
                gz = dz * wy * wx
                gy = wz * dy * wx
                gx = wz * wy * dx
                for c in range(nc):
                    coefficient = coefficients[za, yb, xd, c]
                    out[c] += w * coefficient
                    jacobian[c, 0] += gz * coefficient
                    jacobian[c, 1] += gy * coefficient
                    jacobian[c, 2] += gx * coefficient


#: Targets per work item of the parallel inversion (work arrays are allocated per item).
_INVERT_BLOCK = 4096


@njit(parallel=True, **KERNEL_OPTIONS)
def _invert_points(
    coefficients,
    pad,
    origin,
    step,
    trend_offset,
    trend_matrix,
    targets,
    max_iterations,
    tolerance,
    out,
    converged,
):
    """Solve ``X + u(X) = x`` for each target ``x``, starting from ``X = x - u(x)``.

    Newton steps ``X <- X - (I + du/dX)^-1 (X + u(X) - x)`` (quadratic convergence), with the
    plain fixed-point step ``X <- x - u(X)`` wherever the Jacobian is nearly singular.
    """
    n = targets.shape[0]
    n_blocks = (n + _INVERT_BLOCK - 1) // _INVERT_BLOCK
    for block in prange(n_blocks):
        value = np.empty(3)
        jacobian = np.empty((3, 3))
        position = np.empty(3)
        taps = np.empty((3, 10))
        index = np.empty((3, 4), np.int64)
        for i in range(block * _INVERT_BLOCK, min(n, (block + 1) * _INVERT_BLOCK)):
            z = targets[i, 0]
            y = targets[i, 1]
            x = targets[i, 2]
            _eval_one(coefficients, pad, origin, step, trend_offset, trend_matrix, z, y, x, value)
            position[0] = z - value[0]
            position[1] = y - value[1]
            position[2] = x - value[2]
            ok = False
            for _ in range(max_iterations):
                _eval_one_with_jacobian(
                    coefficients,
                    pad,
                    origin,
                    step,
                    trend_offset,
                    trend_matrix,
                    position,
                    value,
                    jacobian,
                    taps,
                    index,
                )
                r0 = position[0] + value[0] - z
                r1 = position[1] + value[1] - y
                r2 = position[2] + value[2] - x
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
                det = a00 * c00 + a10 * c01 + a20 * c02
                if abs(det) > 1e-6:
                    c10 = a12 * a20 - a10 * a22
                    c11 = a00 * a22 - a02 * a20
                    c12 = a02 * a10 - a00 * a12
                    c20 = a10 * a21 - a11 * a20
                    c21 = a01 * a20 - a00 * a21
                    c22 = a00 * a11 - a01 * a10
                    d0 = (c00 * r0 + c01 * r1 + c02 * r2) / det
                    d1 = (c10 * r0 + c11 * r1 + c12 * r2) / det
                    d2 = (c20 * r0 + c21 * r1 + c22 * r2) / det
                else:
                    d0 = r0
                    d1 = r1
                    d2 = r2
                position[0] -= d0
                position[1] -= d1
                position[2] -= d2
                if max(abs(d0), abs(d1), abs(d2)) < tolerance:
                    ok = True
                    break
            out[i, 0] = position[0]
            out[i, 1] = position[1]
            out[i, 2] = position[2]
            converged[i] = ok


@njit(**KERNEL_OPTIONS)
def _axis_taps(coordinates, origin, step, pad, n_padded):
    """Tap indices (n, 4) and weights (n, 4) of voxel coordinates along one axis."""
    n = coordinates.shape[0]
    index = np.empty((n, 4), np.int64)
    weight = np.empty((n, 4), np.float64)
    for v in range(n):
        q = _clamp((coordinates[v] - origin) / step + pad, 0.0, n_padded - 1.0)
        f = np.floor(q)
        w = bspline_weights(q - f)
        i = int(f)
        for a in range(4):
            index[v, a] = _mirror(i - 1 + a, n_padded)
            weight[v, a] = w[a]
    return index, weight


@njit(parallel=True, **KERNEL_OPTIONS)
def _eval_lattice(
    coefficients,
    z_index,
    z_weight,
    y_index,
    y_weight,
    x_index,
    x_weight,
    z_trend,
    y_trend,
    x_trend,
    trend_offset,
    trend_matrix,
    out,
):
    """Separable evaluation on the lattice ``z × y × x`` into ``out`` (nz, ny, nx, C)."""
    py, px, nc = coefficients.shape[1], coefficients.shape[2], coefficients.shape[3]
    ny = y_index.shape[0]
    nx = x_index.shape[0]
    for a in prange(z_index.shape[0]):
        plane = np.zeros((py, px, nc))
        for t in range(4):
            w = z_weight[a, t]
            source = coefficients[z_index[a, t]]
            for j in range(py):
                for k in range(px):
                    for c in range(nc):
                        plane[j, k, c] += w * source[j, k, c]
        row = np.empty((px, nc))
        for b in range(ny):
            row[:] = 0.0
            for t in range(4):
                w = y_weight[b, t]
                source_row = plane[y_index[b, t]]
                for k in range(px):
                    for c in range(nc):
                        row[k, c] += w * source_row[k, c]
            for d in range(nx):
                for c in range(nc):
                    value = (
                        trend_offset[c]
                        + trend_matrix[c, 0] * z_trend[a]
                        + trend_matrix[c, 1] * y_trend[b]
                        + trend_matrix[c, 2] * x_trend[d]
                    )
                    for t in range(4):
                        value += x_weight[d, t] * row[x_index[d, t], c]
                    out[a, b, d, c] = value


# --- the field spline -------------------------------------------------------------------------
def _pad_linear(values: np.ndarray, pad: int) -> np.ndarray:
    """Pad the three grid axes of ``values`` (nz, ny, nx, C) by linear extrapolation."""
    for axis in range(3):
        n = values.shape[axis]
        first = np.take(values, [0], axis=axis)
        last = np.take(values, [n - 1], axis=axis)
        if n > 1:
            slope_low = first - np.take(values, [1], axis=axis)
            slope_high = last - np.take(values, [n - 2], axis=axis)
        else:
            slope_low = np.zeros_like(first)
            slope_high = np.zeros_like(last)
        low = [first + slope_low * k for k in range(pad, 0, -1)]
        high = [last + slope_high * k for k in range(1, pad + 1)]
        values = np.concatenate([*low, values, *high], axis=axis)
    return values


class FieldSpline:
    """Cubic B-spline through the nodes of a grid quantity, evaluated anywhere.

    Parameters
    ----------
    origin, step : tuple of 3 floats
        Grid geometry ``(z, y, x)`` in voxels (as in :class:`DisplacementField`).
    values : ndarray, shape (nz, ny, nx, C)
        Node values (any number ``C`` of components, e.g. 3 for a displacement, 9 for a
        gradient). Must be finite: clean a field first (:func:`.cleaning.clean`).

    Notes
    -----
    The spline interpolates the node values; affine fields are reproduced exactly everywhere
    (see the module notes for the boundary treatment).
    """

    def __init__(self, origin, step, values: np.ndarray) -> None:
        values = np.asarray(values, dtype=np.float64)
        if values.ndim != 4:
            raise ValueError(f"values must have shape (nz, ny, nx, C), got {values.shape}")
        if not np.all(np.isfinite(values)):
            bad = int(np.sum(~np.all(np.isfinite(values), axis=-1)))
            raise ValueError(
                f"the field has {bad} nodes without a finite value: replace them first "
                "(napari_dvc_correct.engine.cleaning.clean, with fill_masked=True for masked nodes)"
            )
        self.origin = np.asarray(origin, dtype=np.float64).reshape(3)
        self.step = np.asarray(step, dtype=np.float64).reshape(3)
        self.grid_shape = np.asarray(values.shape[:3], dtype=np.int64)
        self.components = values.shape[3]
        # global affine trend in grid-index coordinates t = (p - origin) / step
        index = np.indices(values.shape[:3], dtype=np.float64).reshape(3, -1).T
        design = np.column_stack([np.ones(len(index)), index])
        flat = values.reshape(-1, self.components)
        solution, *_ = np.linalg.lstsq(design, flat, rcond=None)
        self.trend_offset = np.ascontiguousarray(solution[0])
        self.trend_matrix = np.ascontiguousarray(solution[1:].T)  # (C, 3)
        residual = (flat - design @ solution).reshape(values.shape)
        padded = _pad_linear(residual, PAD_NODES)
        coefficients = np.empty_like(padded)
        for c in range(self.components):
            coefficients[..., c] = ndimage.spline_filter(padded[..., c], order=3, mode="mirror")
        self.coefficients = np.ascontiguousarray(coefficients)
        self.pad = PAD_NODES

    @classmethod
    def from_field(cls, field: DisplacementField) -> FieldSpline:
        """Spline of the displacement ``field.u`` (3 components)."""
        return cls(field.origin, field.step, field.u)

    def _args(self):
        return (
            self.coefficients,
            self.pad,
            self.origin,
            self.step,
            self.trend_offset,
            self.trend_matrix,
        )

    def __call__(
        self,
        points: np.ndarray,
        outside: str = "extrapolate",
        chunk_points: int = DEFAULT_CHUNK_VOXELS,
    ) -> np.ndarray:
        """Values at ``points`` (N, 3) ``(z, y, x)`` voxels, shape (N, C), float64.

        ``outside="nan"`` returns NaN for points outside the grid's hull (the box spanned by the
        nodes); ``"extrapolate"`` continues the field there. Non-finite points give NaN.
        """
        _check_outside(outside)
        points = np.ascontiguousarray(points, dtype=np.float64)
        if points.ndim != 2 or points.shape[1] != 3:
            raise ValueError(f"points must have shape (N, 3) in (z, y, x), got {points.shape}")
        out = np.empty((points.shape[0], self.components), np.float64)
        for start in range(0, points.shape[0], chunk_points):
            stop = start + chunk_points
            _eval_points(
                *self._args(),
                self.grid_shape,
                points[start:stop],
                outside == "nan",
                out[start:stop],
            )
        return out

    def lattice(
        self, z: np.ndarray, y: np.ndarray, x: np.ndarray, outside: str = "extrapolate"
    ) -> np.ndarray:
        """Values on the lattice ``z × y × x`` (1-D voxel coordinates), shape (nz, ny, nx, C).

        Separable evaluation: much faster than :meth:`__call__` on the same positions.
        """
        _check_outside(outside)
        axes = [np.ascontiguousarray(a, dtype=np.float64).reshape(-1) for a in (z, y, x)]
        taps = [
            _axis_taps(a, self.origin[i], self.step[i], self.pad, self.coefficients.shape[i])
            for i, a in enumerate(axes)
        ]
        trends = [(a - self.origin[i]) / self.step[i] for i, a in enumerate(axes)]
        out = np.empty((*[len(a) for a in axes], self.components), np.float64)
        _eval_lattice(
            self.coefficients,
            *taps[0],
            *taps[1],
            *taps[2],
            *trends,
            self.trend_offset,
            self.trend_matrix,
            out,
        )
        if outside == "nan":
            inside = [self._inside_axis(t, i) for i, t in enumerate(trends)]
            hull = inside[0][:, None, None] & inside[1][None, :, None] & inside[2][None, None, :]
            out[~hull] = np.nan
        return out

    def _inside_axis(self, t: np.ndarray, axis: int) -> np.ndarray:
        return (t >= -_HULL_TOLERANCE) & (t <= self.grid_shape[axis] - 1 + _HULL_TOLERANCE)

    def hull_slices(self, shape) -> tuple[slice, slice, slice]:
        """Voxel index ranges of a volume of ``shape`` that lie inside the grid's hull."""
        slices = []
        for a in range(3):
            low = self.origin[a] - _HULL_TOLERANCE
            high = self.origin[a] + (self.grid_shape[a] - 1) * self.step[a] + _HULL_TOLERANCE
            start = max(0, int(np.ceil(low)))
            stop = min(int(shape[a]), int(np.floor(high)) + 1)
            slices.append(slice(start, max(start, stop)))
        return tuple(slices)

    def invert(
        self,
        targets: np.ndarray,
        max_iterations: int = 50,
        tolerance: float = 1e-4,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Reference positions ``X`` with ``X + u(X) = x`` for targets ``x`` (N, 3).

        Newton's fixed-point iteration ``X <- X - (I + du/dX)^-1 (X + u(X) - x)`` from
        ``X = x - u(x)``, using the spline's exact derivative (a few steps even at strains of
        0.3; the plain step ``X <- x - u(X)`` where the Jacobian is nearly singular). Only for
        3-component (displacement) splines.

        Returns
        -------
        positions : ndarray, shape (N, 3), float64
        converged : ndarray, shape (N,), bool
            False where the last step was still larger than ``tolerance`` voxels.
        """
        if self.components != 3:
            raise ValueError("invert needs a displacement spline (3 components)")
        targets = np.ascontiguousarray(targets, dtype=np.float64)
        out = np.empty_like(targets)
        converged = np.empty(targets.shape[0], np.bool_)
        _invert_points(
            *self._args(), targets, int(max_iterations), float(tolerance), out, converged
        )
        return out, converged


def _check_outside(outside: str) -> None:
    if outside not in ("extrapolate", "nan"):
        raise ValueError(f"outside must be 'extrapolate' or 'nan', got {outside!r}")


def as_field_spline(field) -> FieldSpline:
    """``field`` itself if it is a :class:`FieldSpline`, else the spline of a :class:`DisplacementField`."""
    if isinstance(field, FieldSpline):
        return field
    if isinstance(field, DisplacementField):
        return FieldSpline.from_field(field)
    raise TypeError(f"expected a DisplacementField or FieldSpline, got {type(field).__name__}")


def lattice_points(z: slice, shape) -> np.ndarray:
    """Voxel positions ``(N, 3)`` ``(z, y, x)`` of the slab ``z`` of a volume of ``shape``, C order."""
    grids = np.meshgrid(
        np.arange(z.start, z.stop, dtype=np.float64),
        np.arange(shape[1], dtype=np.float64),
        np.arange(shape[2], dtype=np.float64),
        indexing="ij",
    )
    return np.stack([g.reshape(-1) for g in grids], axis=1)


# --- densification ----------------------------------------------------------------------------
def densify(
    field: DisplacementField | FieldSpline,
    points: np.ndarray | None = None,
    *,
    shape=None,
    outside: str = "extrapolate",
    dtype=np.float32,
    out: np.ndarray | None = None,
    chunk_voxels: int = DEFAULT_CHUNK_VOXELS,
) -> np.ndarray:
    """Cubic-spline densification of a grid field (paper step c).

    Give either ``points`` (any positions) or ``shape`` (every voxel of a volume).

    Parameters
    ----------
    field : DisplacementField or FieldSpline
        The grid field; all nodes must hold finite values (clean it first). Passing a prebuilt
        :class:`FieldSpline` avoids refitting when densifying repeatedly.
    points : ndarray, shape (N, 3), optional
        Positions ``(z, y, x)`` in reference voxels.
    shape : tuple of 3 ints, optional
        Volume shape ``(nz, ny, nx)``: evaluate at every voxel, slab by slab.
    outside : {"extrapolate", "nan"}
        What to return outside the box spanned by the grid nodes (the hull).
    dtype : numpy dtype
        Output dtype for ``shape`` (float32 by default: ``3 × 512³`` is 1.6 GB in float32).
        Evaluation always runs in float64. Results for ``points`` are float64.
    out : ndarray, shape (nz, ny, nx, 3), optional
        Where to write the dense field (e.g. a ``numpy.memmap`` or a Zarr array for volumes that
        do not fit in memory); only with ``shape``.
    chunk_voxels : int
        Voxels evaluated at a time.

    Returns
    -------
    ndarray
        ``(N, 3)`` float64 for ``points``; ``(nz, ny, nx, 3)`` of ``dtype`` (or ``out``) for
        ``shape``. Displacements in voxels, components ``(uz, uy, ux)``.

    See Also
    --------
    iter_dense : the same, yielded slab by slab without building the full array.
    """
    spline = as_field_spline(field)
    if (points is None) == (shape is None):
        raise ValueError("give exactly one of points (N, 3) or shape (nz, ny, nx)")
    if points is not None:
        return spline(points, outside=outside, chunk_points=chunk_voxels)
    shape = check_shape(shape)
    if out is None:
        out = np.empty((*shape, spline.components), dtype=dtype)
    elif tuple(out.shape) != (*shape, spline.components):
        raise ValueError(f"out must have shape {(*shape, spline.components)}, got {out.shape}")
    for z, block in iter_dense(spline, shape, outside=outside, chunk_voxels=chunk_voxels):
        out[z] = block
    return out


def iter_dense(
    field: DisplacementField | FieldSpline,
    shape,
    *,
    outside: str = "extrapolate",
    chunk_voxels: int = DEFAULT_CHUNK_VOXELS,
) -> Iterator[tuple[slice, np.ndarray]]:
    """Yield ``(z_slice, values)`` with the dense field on each slab of a volume of ``shape``.

    ``values`` has shape ``(slab_depth, ny, nx, C)``, float64; only one slab lives at a time.
    """
    spline = as_field_spline(field)
    shape = check_shape(shape)
    y = np.arange(shape[1], dtype=np.float64)
    x = np.arange(shape[2], dtype=np.float64)
    for z in iter_slabs(shape, chunk_voxels):
        zc = np.arange(z.start, z.stop, dtype=np.float64)
        yield z, spline.lattice(zc, y, x, outside=outside)


def check_shape(shape) -> tuple[int, int, int]:
    shape = tuple(int(n) for n in shape)
    if len(shape) != 3 or min(shape) < 1:
        raise ValueError(f"shape must be 3 positive ints (nz, ny, nx), got {shape}")
    return shape


def inside_hull(spline: FieldSpline, points: np.ndarray) -> np.ndarray:
    """True for positions ``(N, 3)`` inside the box spanned by the spline's grid nodes."""
    t = (points - spline.origin) / spline.step
    return np.all((t >= -_HULL_TOLERANCE) & (t <= spline.grid_shape - 1 + _HULL_TOLERANCE), axis=1)
