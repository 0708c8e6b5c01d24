"""Voxel quantities binned by a grid quantity: the residual against equivalent strain (Figs. 10–11).

The equivalent strain lives on the POI grid and the gray residual on voxels. Each voxel takes the
strain of its *nearest node*: every node owns the cell of ``step`` voxels around it, so binning is
the same as pooling each POI neighbourhood's residual sum and voxel count by the node's strain, and
no dense strain volume is ever built. Voxels outside every cell (farther than half a step beyond
the outermost nodes) and voxels with an undefined (NaN) residual are left out. Volumes are read
slab by slab.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from numba import njit, prange

from .._numba_setup import KERNEL_OPTIONS
from ..fields.field import DisplacementField
from ..slabs import iter_slabs


@dataclass(frozen=True)
class StrainBins:
    """Mean residual per equivalent-strain bin (paper Fig. 10).

    Attributes
    ----------
    edges : ndarray, shape (B + 1,)
        Bin edges (equivalent strain, dimensionless); the last bin includes its upper edge.
    voxels : ndarray, shape (B,), int64
        Voxels with a finite residual whose node's strain falls in each bin.
    mean_residual : ndarray, shape (B,), float64
        Mean gray residual in each bin (NaN for an empty bin).
    """

    edges: np.ndarray
    voxels: np.ndarray
    mean_residual: np.ndarray

    @property
    def centers(self) -> np.ndarray:
        return 0.5 * (self.edges[:-1] + self.edges[1:])


def strain_bin_edges(strains: Sequence[np.ndarray], n_bins: int = 10, upper=None) -> np.ndarray:
    """Common bin edges ``0 .. upper`` for one or several equivalent-strain grids.

    ``upper`` defaults to the 99.5th percentile of all finite strains (a few outlier nodes would
    otherwise stretch the axis), so the last bin also collects the strains above it.
    """
    if n_bins < 1:
        raise ValueError(f"n_bins must be >= 1, got {n_bins}")
    if upper is None:
        finite = np.concatenate([np.ravel(s)[np.isfinite(np.ravel(s))] for s in strains])
        upper = float(np.percentile(finite, 99.5)) if finite.size else 0.0
    upper = float(upper)
    if not upper > 0:
        upper = 1e-3  # a rigid motion: one meaningful bin near zero strain
    return np.linspace(0.0, upper, int(n_bins) + 1)


@dataclass
class GridPart:
    """Sums and counts over the sub-grid ``lo .. lo + sums.shape`` of a grid (one block's share)."""

    lo: tuple
    sums: np.ndarray
    counts: np.ndarray

    def add_to(self, sums: np.ndarray, counts: np.ndarray) -> None:
        """Add this part into whole-grid ``sums`` (float64) and ``counts`` (int64), in place."""
        if self.sums.size == 0:
            return
        where = tuple(slice(int(a), int(a) + n) for a, n in zip(self.lo, self.sums.shape))
        sums[where] += self.sums
        counts[where] += self.counts


def _empty_part() -> GridPart:
    return GridPart((0, 0, 0), np.zeros((0, 0, 0)), np.zeros((0, 0, 0), np.int64))


def node_voxels(field: DisplacementField, volume_shape) -> tuple[np.ndarray, ...]:
    """Per axis, the voxel nearest to each node (rounded, clipped into the volume), int64."""
    return tuple(
        np.clip(np.rint(c), 0, int(n) - 1).astype(np.int64)
        for c, n in zip(field.axis_coordinates(), volume_shape)
    )


def node_box_sums(residual: np.ndarray, box, centers, half: int) -> GridPart:
    """Sums and counts of the finite residual voxels of ``box`` in every node's ``(2M+1)^3`` box.

    Parameters
    ----------
    residual : ndarray, shape box_shape(box), float
        The residual on the voxels of ``box`` (NaN where undefined).
    box : tuple of 3 slices
        Where the block lies in the volume (voxels).
    centers : tuple of 3 int arrays
        Per axis, each node's voxel (:func:`node_voxels`); the grid is separable.
    half : int
        ``M``: node ``i``'s box spans ``centers[i] - M .. centers[i] + M``.

    Returns
    -------
    GridPart
        Over the nodes whose boxes meet the block; their sums (float64) and counts (int64) of
        the block's share. Summed over blocks that tile a volume, the whole boxes (clipped at the
        volume's borders).
    """
    return node_box_sums_nested(residual, box, centers, [half])[0]


def node_box_sums_nested(values: np.ndarray, box, centers, halves) -> list[GridPart]:
    """:func:`node_box_sums` for several half-sizes at once (one pass over the block's voxels;
    the same numbers as one call per half-size).

    Parameters
    ----------
    values, box, centers
        As :func:`node_box_sums`.
    halves : sequence of int
        The half-sizes ``M``, any order.

    Returns
    -------
    list of GridPart
        One per half-size, in ``halves``' order, all over the sub-grid of the nodes whose
        largest boxes meet the block (a node whose smaller box misses it adds 0).
    """
    halves = [int(h) for h in halves]
    largest = max(halves)
    ranges, bounds = [], []
    for s, c in zip(box, centers):
        meets = np.flatnonzero((c + largest >= s.start) & (c - largest < s.stop))
        if meets.size == 0:
            return [_empty_part() for _ in halves]
        ranges.append(meets)
        n = s.stop - s.start
        low = np.stack([np.clip(c[meets] - h - s.start, 0, n) for h in halves])
        high = np.stack([np.clip(c[meets] + h + 1 - s.start, 0, n) for h in halves])
        bounds += [np.ascontiguousarray(low, np.int64), np.ascontiguousarray(high, np.int64)]
    lo = tuple(int(r[0]) for r in ranges)
    sums = np.empty((len(halves), *(len(r) for r in ranges)))
    counts = np.empty(sums.shape, np.int64)
    _nested_box_sums(np.ascontiguousarray(values, dtype=np.float32), *bounds, sums, counts)
    return [GridPart(lo, sums[k], counts[k]) for k in range(len(halves))]


@njit(parallel=True, **KERNEL_OPTIONS)
def _nested_box_sums(residual, z_low, z_high, y_low, y_high, x_low, x_high, sums, counts):
    """Sums (float64) and counts of the finite voxels of ``residual`` in ``H`` sets of boxes:
    set ``h``'s box ``(i, j, k)`` is ``z_low[h, i]:z_high[h, i], y_low[h, j]:y_high[h, j],
    x_low[h, k]:x_high[h, k]`` (bounds of shape ``(H, g)``), into ``sums[h, i, j, k]``.

    Separable running sums (integral lines): along each x row every box's x range is one
    difference of the row's running sum (computed once for all sets), then the same along y over
    those row sums and along z over the plane sums, per set; one pass over the voxels whatever
    the boxes' size and overlap, and each set's numbers do not depend on the other sets."""
    nz, ny, nx = residual.shape
    nh = z_low.shape[0]
    gz, gy, gx = z_low.shape[1], y_low.shape[1], x_low.shape[1]
    rows = np.empty((nh, nz, ny, gx))
    row_counts = np.empty((nh, nz, ny, gx), np.int64)
    for z in prange(nz):
        running = np.empty(nx + 1)
        running_count = np.empty(nx + 1, np.int64)
        for y in range(ny):
            total = 0.0
            count = 0
            running[0] = 0.0
            running_count[0] = 0
            for x in range(nx):
                value = residual[z, y, x]
                if np.isfinite(value):
                    total += value
                    count += 1
                running[x + 1] = total
                running_count[x + 1] = count
            for h in range(nh):
                for k in range(gx):
                    rows[h, z, y, k] = running[x_high[h, k]] - running[x_low[h, k]]
                    row_counts[h, z, y, k] = (
                        running_count[x_high[h, k]] - running_count[x_low[h, k]]
                    )
    planes = np.empty((nh, nz, gy, gx))
    plane_counts = np.empty((nh, nz, gy, gx), np.int64)
    for z in prange(nz):
        running = np.empty(ny + 1)
        running_count = np.empty(ny + 1, np.int64)
        for h in range(nh):
            for k in range(gx):
                running[0] = 0.0
                running_count[0] = 0
                for y in range(ny):
                    running[y + 1] = running[y] + rows[h, z, y, k]
                    running_count[y + 1] = running_count[y] + row_counts[h, z, y, k]
                for j in range(gy):
                    planes[h, z, j, k] = running[y_high[h, j]] - running[y_low[h, j]]
                    plane_counts[h, z, j, k] = (
                        running_count[y_high[h, j]] - running_count[y_low[h, j]]
                    )
    for j in prange(gy):
        running = np.empty(nz + 1)
        running_count = np.empty(nz + 1, np.int64)
        for h in range(nh):
            for k in range(gx):
                running[0] = 0.0
                running_count[0] = 0
                for z in range(nz):
                    running[z + 1] = running[z] + planes[h, z, j, k]
                    running_count[z + 1] = running_count[z] + plane_counts[h, z, j, k]
                for i in range(gz):
                    sums[h, i, j, k] = running[z_high[h, i]] - running[z_low[h, i]]
                    counts[h, i, j, k] = running_count[z_high[h, i]] - running_count[z_low[h, i]]


def _cell_index(coords: np.ndarray, origin: float, step: float, n: int):
    """Nearest node index along one axis, and whether ``coords`` lie in the grid's cells."""
    position = (coords - origin) / step + 0.5  # cell k spans [k - 1/2, k + 1/2) steps
    inside = (position >= 0.0) & (position < n)
    return np.clip(np.floor(position), 0, n - 1).astype(np.int64), inside


def cell_sums_block(
    residual: np.ndarray, box, field: DisplacementField, positions: np.ndarray | None = None
):
    """Residual sum and voxel count per node cell from one block of voxels.

    Parameters
    ----------
    residual : ndarray, shape of ``box``, float
        The residual on the voxels of ``box`` (NaN voxels are skipped).
    box : tuple of 3 slices
        Where the block lies in the volume (voxels).
    field : DisplacementField
        Supplies the grid (origin, step, shape).
    positions : ndarray, shape (N, 3), optional
        Reference positions of the block's voxels in C order (for a residual in the loaded
        state); default the voxel positions themselves.

    Returns
    -------
    GridPart
        Sums (float64) and counts (int64) over the cells the block reaches.
    """
    grid = field.shape
    origin, step = field.origin, field.step
    r = np.asarray(residual, dtype=np.float64)
    if positions is None:
        index, inside = [], []
        for a, s in enumerate(box):
            coords = np.arange(s.start, s.stop, dtype=np.float64)
            i, o = _cell_index(coords, origin[a], step[a], grid[a])
            index.append(i)
            inside.append(o)
        keep = (
            inside[0][:, None, None] & inside[1][None, :, None] & inside[2][None, None, :]
        ) & np.isfinite(r)
        if not keep.any():
            return _empty_part()
        lo = [int(i[o].min()) for i, o in zip(index, inside)]
        hi = [int(i[o].max()) + 1 for i, o in zip(index, inside)]
        shape = [h - lo_ for lo_, h in zip(lo, hi)]
        local = [np.clip(i - lo_, 0, n - 1) for i, lo_, n in zip(index, lo, shape)]
        flat = (local[0][:, None, None] * shape[1] + local[1][None, :, None]) * shape[2] + local[2][
            None, None, :
        ]
        flat = np.broadcast_to(flat, r.shape)
    else:
        mapped = np.asarray(positions, dtype=np.float64)
        index = [_cell_index(mapped[:, a], origin[a], step[a], grid[a]) for a in range(3)]
        inside = (index[0][1] & index[1][1] & index[2][1]).reshape(r.shape)
        keep = inside & np.isfinite(r)
        if not keep.any():
            return _empty_part()
        kept = keep.reshape(-1)
        lo = [int(i[kept].min()) for i, _ in index]
        hi = [int(i[kept].max()) + 1 for i, _ in index]
        shape = [h - lo_ for lo_, h in zip(lo, hi)]
        local = [np.clip(i - lo_, 0, n - 1) for (i, _), lo_, n in zip(index, lo, shape)]
        flat = ((local[0] * shape[1] + local[1]) * shape[2] + local[2]).reshape(r.shape)
    n_cells = int(np.prod(shape))
    sums = np.bincount(flat[keep], weights=r[keep], minlength=n_cells).reshape(shape)
    counts = np.bincount(flat[keep], minlength=n_cells).astype(np.int64).reshape(shape)
    return GridPart(tuple(lo), sums, counts)


def cell_sums(
    residual: np.ndarray,
    field: DisplacementField,
    reference_positions: Callable[[np.ndarray], np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Residual sum and voxel count in each node's cell (the voxels nearest to that node).

    Parameters
    ----------
    residual : ndarray, shape (nz, ny, nx), float
        Gray residual volume (NaN voxels are skipped).
    field : DisplacementField
        Supplies the grid (origin, step, shape).
    reference_positions : callable, optional
        For a residual defined in the loaded state: maps deformed voxel positions (N, 3) to the
        reference positions (N, 3) the grid lives on. Default: the voxel positions themselves.

    Returns
    -------
    sums : ndarray, shape grid, float64
    counts : ndarray, shape grid, int64
    """
    sums = np.zeros(field.shape)
    counts = np.zeros(field.shape, np.int64)
    for zs in iter_slabs(residual.shape):
        box = (zs, slice(0, residual.shape[1]), slice(0, residual.shape[2]))
        positions = None
        if reference_positions is not None:
            r_shape = (zs.stop - zs.start, residual.shape[1], residual.shape[2])
            points = np.indices(r_shape, dtype=np.float64).reshape(3, -1).T
            points[:, 0] += zs.start
            positions = reference_positions(points)
        cell_sums_block(np.asarray(residual[zs]), box, field, positions).add_to(sums, counts)
    return sums, counts


def bin_cells_by_strain(
    sums: np.ndarray, counts: np.ndarray, strain: np.ndarray, edges: np.ndarray
) -> StrainBins:
    """Pool node cells into equivalent-strain bins (cells whose node strain is NaN are left out)."""
    edges = np.asarray(edges, dtype=np.float64)
    if edges.ndim != 1 or edges.size < 2 or np.any(np.diff(edges) <= 0):
        raise ValueError("strain bin edges must be a strictly increasing list of >= 2 values")
    if not (sums.shape == counts.shape == strain.shape):
        raise ValueError(
            f"cell sums {sums.shape}, counts {counts.shape} and strain {strain.shape} must all "
            "have the field's grid shape"
        )
    n_bins = edges.size - 1
    s = strain.ravel()
    ok = np.isfinite(s) & (s >= edges[0])
    which = np.clip(np.searchsorted(edges, s[ok], side="right") - 1, 0, n_bins - 1)
    bin_sums = np.bincount(which, weights=sums.ravel()[ok], minlength=n_bins)
    bin_counts = np.bincount(which, weights=counts.ravel()[ok], minlength=n_bins).astype(np.int64)
    with np.errstate(invalid="ignore", divide="ignore"):
        means = np.where(bin_counts > 0, bin_sums / np.maximum(bin_counts, 1), np.nan)
    return StrainBins(edges=edges, voxels=bin_counts, mean_residual=means)


def bin_residual_by_strain(
    residual: np.ndarray,
    strain: np.ndarray,
    field: DisplacementField,
    edges: np.ndarray,
    reference_positions: Callable[[np.ndarray], np.ndarray] | None = None,
) -> StrainBins:
    """Mean gray residual per equivalent-strain bin (paper Fig. 10).

    Each voxel takes the strain of its nearest grid node (see the module docstring).

    Parameters
    ----------
    residual : ndarray, shape (nz, ny, nx), float
        Gray residual volume (NaN where undefined).
    strain : ndarray, shape field.shape
        Equivalent strain on the grid (NaN nodes are left out).
    field : DisplacementField
        Its grid places the strain nodes.
    edges : ndarray, shape (B + 1,)
        Increasing bin edges, e.g. from :func:`strain_bin_edges`; strains above the last edge
        go to the last bin.
    reference_positions : callable, optional
        See :func:`cell_sums`.
    """
    if strain.shape != field.shape:
        raise ValueError(
            f"strain must have the field's grid shape {field.shape}, got {strain.shape}"
        )
    sums, counts = cell_sums(residual, field, reference_positions)
    return bin_cells_by_strain(sums, counts, strain, edges)
