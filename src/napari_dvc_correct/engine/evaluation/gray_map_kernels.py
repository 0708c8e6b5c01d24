"""The gray-level map's whole-volume passes, compiled: applying a local map, and the per-cell
sums it is fitted from.

* :func:`apply_local_map`: :meth:`.gray_levels.GrayLevelMap.apply` maps the loaded scan's gray
  levels into the reference's, ``contrast(X) · F + offset(X)`` with ``contrast`` and ``offset``
  interpolated trilinearly from the map's cell centres. Done with NumPy, each voxel's
  coefficients take six whole-block float64 arrays (two takes and a blend per axis) before the
  float32 product; the correction applies the map to every pull-back and forward warp of the
  volume. Here the same arithmetic runs voxel by voxel: the blends along ``z`` then ``y`` on the
  small cell-sized arrays, the blend along ``x`` per voxel, the coefficients rounded to float32
  and ``a · F + b`` in float32, so every value equals NumPy's to the bit (tested).
* :func:`cell_sums`: the sums ``1, f, g, f², fg, g²`` per cell of :func:`.gray_levels.block_sums`
  in one pass over the block, voxel by voxel in C order as ``np.bincount`` adds its weights, so
  every sum equals NumPy's to the bit (tested), without the block's float64 copies.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from .._numba_setup import KERNEL_OPTIONS


def axis_blend(start: int, stop: int, cell: int, n_cells: int):
    """Per voxel ``start .. stop - 1`` of one axis: the lower and upper cell centre and their
    weights ``(low, high, 1 - w, w)`` of the trilinear interpolation (float64 weights)."""
    position = (np.arange(start, stop) + 0.5) / cell - 0.5
    position = np.clip(position, 0.0, n_cells - 1)
    low = np.minimum(np.floor(position).astype(int), max(n_cells - 2, 0))
    high = np.minimum(low + 1, n_cells - 1)
    weight = position - low
    return low.astype(np.int64), high.astype(np.int64), 1.0 - weight, weight


@njit(**KERNEL_OPTIONS)  # serial: a parallel kernel's cache load (~50 ms) costs more than it saves
def _apply_planes(contrast, offset, z_blend, y_blend, x_blend, moved, out):
    """``out = float32(c) · moved + float32(o)`` with ``c`` and ``o`` the cell-centre arrays
    ``contrast`` and ``offset`` blended along z, then y, then x (``*_blend``: low, high,
    1 - w, w per voxel of that axis)."""
    zl, zh, z0, z1 = z_blend
    yl, yh, y0, y1 = y_blend
    xl, xh, x0, x1 = x_blend
    cy, cx = contrast.shape[1], contrast.shape[2]
    ny, nx = yl.shape[0], xl.shape[0]
    for a in range(zl.shape[0]):
        plane_c = np.empty((cy, cx))
        plane_o = np.empty((cy, cx))
        for j in range(cy):
            for k in range(cx):
                plane_c[j, k] = contrast[zl[a], j, k] * z0[a] + contrast[zh[a], j, k] * z1[a]
                plane_o[j, k] = offset[zl[a], j, k] * z0[a] + offset[zh[a], j, k] * z1[a]
        line_c = np.empty(cx)
        line_o = np.empty(cx)
        for b in range(ny):
            for k in range(cx):
                line_c[k] = plane_c[yl[b], k] * y0[b] + plane_c[yh[b], k] * y1[b]
                line_o[k] = plane_o[yl[b], k] * y0[b] + plane_o[yh[b], k] * y1[b]
            for d in range(nx):
                c = np.float32(line_c[xl[d]] * x0[d] + line_c[xh[d]] * x1[d])
                o = np.float32(line_o[xl[d]] * x0[d] + line_o[xh[d]] * x1[d])
                out[a, b, d] = c * moved[a, b, d] + o


def apply_local_map(
    contrast: np.ndarray, offset: np.ndarray, cell: int, moved: np.ndarray, region
) -> np.ndarray:
    """``contrast(X) · moved + offset(X)`` at the voxels of ``region``, float32.

    Parameters
    ----------
    contrast, offset : ndarray, shape (cz, cy, cx), float64
        The local map at the cells' centres (cell ``i`` centred on voxel ``(i + 0.5) cell - 0.5``).
    cell : int
        Cell edge (voxels), > 0.
    moved : ndarray, shape of ``region``, float32
        The loaded scan's gray levels at the voxels of ``region`` (NaN stays NaN).
    region : tuple of 3 slices
        The voxels of ``moved`` in the volume (starts and stops given).

    Returns
    -------
    ndarray, float32, shape of ``moved``
    """
    contrast = np.ascontiguousarray(contrast, dtype=np.float64)
    offset = np.ascontiguousarray(offset, dtype=np.float64)
    moved = np.ascontiguousarray(moved, dtype=np.float32)
    if len(region) != 3 or any(
        s.stop - s.start != n for s, n in zip(region, moved.shape, strict=False)
    ):
        raise ValueError(f"region {region} does not match the block's shape {moved.shape}")
    blends = tuple(
        axis_blend(s.start, s.stop, int(cell), contrast.shape[axis])
        for axis, s in enumerate(region)
    )
    out = np.empty(moved.shape, np.float32)
    if moved.size:
        _apply_planes(contrast, offset, *blends, moved, out)
    return out


@njit(**KERNEL_OPTIONS)
def _cell_sums(reference, moved, mapped, trim, limit, iz, iy, ix, n, f, g, ff, fg, gg):
    """Add each voxel's ``1, f, g, f², fg, g²`` to its cell's sums (in place), in C order; the
    voxels where ``f`` or ``g`` is not finite, or (``trim``) where ``|mapped - g| > limit``, are
    left out."""
    for a in range(reference.shape[0]):
        for b in range(reference.shape[1]):
            for d in range(reference.shape[2]):
                gv = np.float64(reference[a, b, d])
                fv = np.float64(moved[a, b, d])
                if not (np.isfinite(fv) and np.isfinite(gv)):
                    continue
                if trim and not abs(np.float64(mapped[a, b, d]) - gv) <= limit:
                    continue
                k = iz[a]
                j = iy[b]
                i = ix[d]
                n[k, j, i] += 1.0
                f[k, j, i] += fv
                g[k, j, i] += gv
                ff[k, j, i] += fv * fv
                fg[k, j, i] += fv * gv
                gg[k, j, i] += gv * gv


def cell_sums(reference, moved, mapped, limit: float, cell_index, cells_shape):
    """Per-cell sums ``(n, f, g, ff, fg, gg)`` (float64 arrays of ``cells_shape``) of a block.

    Parameters
    ----------
    reference, moved : ndarray, shape (bz, by, bx)
        ``G`` and ``F~`` on the block (any real dtype; taken as float64).
    mapped : ndarray, same shape, or None
        The previous map applied to ``moved`` (float32): voxels with ``|mapped - G| > limit``
        are left out. None: no trimming.
    limit : float
    cell_index : tuple of 3 int arrays
        The cell of each voxel along z, y and x (block lengths).
    cells_shape : tuple of 3 ints
    """
    reference = np.ascontiguousarray(reference)
    moved = np.ascontiguousarray(moved)
    if reference.dtype.kind != "f":
        reference = reference.astype(np.float64)
    if moved.dtype.kind != "f":
        moved = moved.astype(np.float64)
    trim = mapped is not None
    mapped = np.ascontiguousarray(mapped) if trim else np.zeros((1, 1, 1), np.float32)
    sums = tuple(np.zeros(tuple(int(c) for c in cells_shape)) for _ in range(6))
    index = tuple(np.ascontiguousarray(i, dtype=np.int64) for i in cell_index)
    _cell_sums(reference, moved, mapped, trim, float(limit), *index, *sums)
    return sums
