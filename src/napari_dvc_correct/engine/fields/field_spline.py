"""The cubic-spline field: a grid field evaluated anywhere (paper step c, densification).

A :class:`~napari_dvc_correct.engine.fields.field.DisplacementField` lives on a coarse grid of points of
interest. The self-correcting strategy (paper Fig. 3) needs it at every voxel:
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
from scipy import ndimage

from ..slabs import iter_slabs
from .field import DisplacementField
from .field_spline_kernels import (
    HULL_TOLERANCE,
    _axis_taps,
    _eval_lattice,
    _eval_points,
    _invert_points,
    extend_coefficients,
    hull_bounds,
)
from .inverse_lattice import LatticeInverse, invert_lattice

#: Nodes added on each side of the grid (linear extrapolation) before the spline fit.
PAD_NODES = 3

#: Voxels per chunk for slab-by-slab evaluation (about 50 MB of float64 positions).
DEFAULT_CHUNK_VOXELS = 1 << 21


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
                "(napari_dvc_correct.engine.correction.cleaning.clean, with fill_masked=True for masked nodes)"
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
        # mirrored copy for the point kernels of 3-component splines (no mirroring per tap)
        self.extended = extend_coefficients(self.coefficients) if self.components == 3 else None
        self.pad = PAD_NODES

    @classmethod
    def from_field(cls, field: DisplacementField) -> FieldSpline:
        """Spline of the displacement ``field.u`` (3 components)."""
        return cls(field.origin, field.step, field.u)

    def _args(self):
        """Arguments of the 3-component point kernels (extended coefficients first)."""
        return (
            self.extended,
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
                self.coefficients,
                self.extended if self.extended is not None else self.coefficients,
                *self._args()[1:],
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
        taps, trends = self.lattice_taps(z, y, x)
        out = np.empty((*[len(t) for t in trends], self.components), np.float64)
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
            inside = self.lattice_inside(trends)
            hull = inside[0][:, None, None] & inside[1][None, :, None] & inside[2][None, None, :]
            out[~hull] = np.nan
        return out

    def lattice_taps(self, z: np.ndarray, y: np.ndarray, x: np.ndarray):
        """Per axis of the lattice ``z × y × x``: the spline's tap indices and weights (n, 4),
        and the grid coordinate ``(voxel - origin) / step`` of the linear trend (the separable
        evaluation of :meth:`lattice`, for kernels that use it, e.g. :mod:`.pull_back_fill`)."""
        axes = [np.ascontiguousarray(a, dtype=np.float64).reshape(-1) for a in (z, y, x)]
        taps = [
            _axis_taps(a, self.origin[i], self.step[i], self.pad, self.coefficients.shape[i])
            for i, a in enumerate(axes)
        ]
        trends = [(a - self.origin[i]) / self.step[i] for i, a in enumerate(axes)]
        return taps, trends

    def lattice_inside(self, trends) -> list[np.ndarray]:
        """Per axis, whether the lattice coordinates (``trends`` of :meth:`lattice_taps`) lie in
        the grid's hull."""
        return [self._inside_axis(t, i) for i, t in enumerate(trends)]

    def _inside_axis(self, t: np.ndarray, axis: int) -> np.ndarray:
        return (t >= -HULL_TOLERANCE) & (t <= self.grid_shape[axis] - 1 + HULL_TOLERANCE)

    def hull_slices(self, shape) -> tuple[slice, slice, slice]:
        """Voxel index ranges of a volume of ``shape`` that lie inside the grid's hull."""
        slices = []
        for a in range(3):
            low = self.origin[a] - HULL_TOLERANCE
            high = self.origin[a] + (self.grid_shape[a] - 1) * self.step[a] + HULL_TOLERANCE
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

    def invert_lattice(
        self,
        box,
        max_iterations: int = 50,
        tolerance: float = 1e-4,
        accuracy: float = 1e-3,
        stride: int | None = None,
        outside_accuracy: float | None = None,
    ) -> LatticeInverse:
        """:meth:`invert` at every voxel of ``box`` (3 slices of voxel indices), much faster.

        Exact on a coarse lattice, interpolated between its nodes where a check shows the
        interpolation within ``accuracy`` voxels (``outside_accuracy`` where the field is
        extrapolated beyond the grid's hull), Newton per voxel elsewhere; see
        :func:`.inverse_lattice.invert_lattice`.
        """
        return invert_lattice(
            self, box, max_iterations, tolerance, accuracy, stride, outside_accuracy
        )


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
    """True for positions ``(N, 3)`` inside the box spanned by the spline's grid nodes.

    The box is widened by :data:`HULL_TOLERANCE` grid units (:func:`hull_bounds`), as in the
    lattice inverse's kernels.
    """
    low, high = hull_bounds(spline)
    return np.all((points >= low) & (points <= high), axis=1)
