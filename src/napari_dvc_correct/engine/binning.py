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

from .field import DisplacementField
from .slabs import iter_slabs


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


def _cell_index(coords: np.ndarray, origin: float, step: float, n: int):
    """Nearest node index along one axis, and whether ``coords`` lie in the grid's cells."""
    position = (coords - origin) / step + 0.5  # cell k spans [k - 1/2, k + 1/2) steps
    inside = (position >= 0.0) & (position < n)
    return np.clip(np.floor(position), 0, n - 1).astype(np.int64), inside


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
    grid = field.shape
    n_cells = int(np.prod(grid))
    sums = np.zeros(n_cells)
    counts = np.zeros(n_cells, np.int64)
    origin, step = field.origin, field.step
    for zs in iter_slabs(residual.shape):
        r = np.asarray(residual[zs], dtype=np.float64)
        if reference_positions is None:
            z = np.arange(zs.start, zs.stop, dtype=np.float64)
            iz, oz = _cell_index(z, origin[0], step[0], grid[0])
            iy, oy = _cell_index(
                np.arange(r.shape[1], dtype=np.float64), origin[1], step[1], grid[1]
            )
            ix, ox = _cell_index(
                np.arange(r.shape[2], dtype=np.float64), origin[2], step[2], grid[2]
            )
            flat = (iz[:, None, None] * grid[1] + iy[None, :, None]) * grid[2] + ix[None, None, :]
            keep = oz[:, None, None] & oy[None, :, None] & ox[None, None, :] & np.isfinite(r)
        else:
            positions = np.indices(r.shape, dtype=np.float64).reshape(3, -1).T
            positions[:, 0] += zs.start
            mapped = np.asarray(reference_positions(positions), dtype=np.float64)
            index = [_cell_index(mapped[:, a], origin[a], step[a], grid[a]) for a in range(3)]
            flat = ((index[0][0] * grid[1] + index[1][0]) * grid[2] + index[2][0]).reshape(r.shape)
            inside = (index[0][1] & index[1][1] & index[2][1]).reshape(r.shape)
            keep = inside & np.isfinite(r)
        sums += np.bincount(flat[keep], weights=r[keep], minlength=n_cells)
        counts += np.bincount(flat[keep], minlength=n_cells)
    return sums.reshape(grid), counts.reshape(grid)


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
