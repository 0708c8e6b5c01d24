"""The pull-back ``F~(X) = F(X + u(X))`` of a whole box in one pass (field spline and sampling).

:func:`.warp.pull_back_block` with an in-memory sampler: for each z plane of the box the field
spline's coefficients are summed along z once, for each row along y once, and each voxel's
displacement is the four x taps of that row (the separable evaluation of
:meth:`.field_spline.FieldSpline.lattice`); ``F`` is sampled at ``X + u(X)`` as soon as it is
known, with the four-wide tap sum of IC-GN (:func:`.inverse_per_voxel.sample_or_nan`). No array of
positions or displacements is made. Planes run in parallel.

Positions are ``(z, y, x)`` voxels; values float32, NaN where ``X + u(X)`` falls outside ``F``
or (``outside="nan"``) ``X`` lies outside the grid's hull. ``F`` may be a region of a larger
volume (``tiled.volumes.LazySampler``): positions that leave the part of the region whose
coefficients are the whole volume's come back ``+inf`` for the caller to sample otherwise.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from .._numba_setup import KERNEL_OPTIONS
from .field_spline import FieldSpline
from .field_spline_kernels import lattice_plane, lattice_row, lattice_value
from .inverse_per_voxel import region_bounds, sample_region_or_flag


@njit(parallel=True, **KERNEL_OPTIONS)
def pull_back_planes(
    field_coefficients,
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
    z_inside,
    y_inside,
    x_inside,
    box_start,
    coefficients,
    region,
    values,
):
    """``values[a, b, d] = F(X + u(X))`` at voxel ``X = box_start + (a, b, d)`` (NaN outside
    ``F`` or where an axis's ``*_inside`` flag is False).

    ``coefficients`` hold the region of ``F`` that ``region`` describes
    (:func:`.inverse_per_voxel.region_bounds`); a position inside ``F`` but outside the region's valid
    part gets ``+inf``: the caller samples it otherwise."""
    py, px, nc = field_coefficients.shape[1:]
    nz, ny, nx = values.shape
    flat = coefficients.reshape(-1)
    for a in prange(nz):
        plane = np.empty((py, px, nc))
        row = np.empty((px, nc))
        lattice_plane(field_coefficients, z_index, z_weight, a, plane)
        z = float(box_start[0] + a)
        row_trend = np.empty(3)
        for b in range(ny):
            y = float(box_start[1] + b)
            if not (z_inside[a] and y_inside[b]):
                values[a, b, :] = np.nan
                continue
            lattice_row(plane, y_index, y_weight, b, row)
            for c in range(3):
                row_trend[c] = (
                    trend_offset[c]
                    + trend_matrix[c, 0] * z_trend[a]
                    + trend_matrix[c, 1] * y_trend[b]
                )
            for d in range(nx):
                if not x_inside[d]:
                    values[a, b, d] = np.nan
                    continue
                t = x_trend[d]
                tz = row_trend[0] + trend_matrix[0, 2] * t
                ty = row_trend[1] + trend_matrix[1, 2] * t
                tx = row_trend[2] + trend_matrix[2, 2] * t
                uz = lattice_value(row, x_index, x_weight, d, 0, tz)
                uy = lattice_value(row, x_index, x_weight, d, 1, ty)
                ux = lattice_value(row, x_index, x_weight, d, 2, tx)
                x = float(box_start[2] + d)
                values[a, b, d] = sample_region_or_flag(
                    coefficients, flat, z + uz, y + uy, x + ux, region
                )


def pull_back_box(
    coefficients: np.ndarray,
    spline: FieldSpline,
    box,
    outside: str = "extrapolate",
    *,
    region_start=(0, 0, 0),
    whole_shape=None,
    margin: int = 0,
) -> np.ndarray:
    """``F(X + u(X))`` at every voxel ``X`` of ``box`` (3 slices), shape of the box, float32.

    ``coefficients`` are ``F``'s B-spline coefficients (float32, C order); ``spline`` the
    displacement (3 components). NaN where ``X + u(X)`` falls outside ``F`` and, with
    ``outside="nan"``, where ``X`` lies outside the grid's hull. The same values as sampling
    :meth:`.field_spline.FieldSpline.lattice`'s positions, to float32 rounding.

    For a region of a larger ``F`` (out of core): ``coefficients`` are the region's, which starts
    at voxel ``region_start`` of ``F`` (shape ``whole_shape``), and equal ``F``'s only ``margin``
    voxels inside the region's faces that are not ``F``'s own. Voxels whose position lies inside
    ``F`` but outside that part come back ``+inf`` (sample them from ``F`` otherwise).
    """
    if spline.components != 3:
        raise ValueError("the pull-back needs a displacement spline (3 components)")
    coefficients = np.ascontiguousarray(coefficients, dtype=np.float32)
    region = region_bounds(coefficients.shape, region_start, whole_shape, margin)
    axes = [np.arange(s.start, s.stop, dtype=np.float64) for s in box]
    taps, trends = spline.lattice_taps(*axes)
    inside = (
        spline.lattice_inside(trends)
        if outside == "nan"
        else [np.ones(len(a), np.bool_) for a in axes]
    )
    values = np.empty(tuple(len(a) for a in axes), np.float32)
    pull_back_planes(
        spline.coefficients,
        *taps[0],
        *taps[1],
        *taps[2],
        *trends,
        spline.trend_offset,
        spline.trend_matrix,
        *inside,
        np.array([s.start for s in box], np.int64),
        coefficients,
        region,
        values,
    )
    return values
