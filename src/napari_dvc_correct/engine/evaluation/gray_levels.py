"""The gray-level model: how the loaded scan's gray levels map onto the reference's.

Real scans change their gray levels between load steps (the paper's Table 1; a fractured rock
whose mean falls from 113 to 60 and its contrast by 3x). A raw gray residual
``|F(X + u(X)) - G(X)|`` then measures that brightness change, not the field's error, and every
decision taken on it (the correction's acceptance, its noise floor, its flags, eqs. 1-2) goes
wrong. The paper asks for the residual to be corrected for the gray-level change of the target
volume; this module is that correction:

    ``G(X) ≈ contrast(X) · F~(X) + offset(X)``,  ``F~(X) = F(X + u(X))``,

fitted by least squares over the voxels where both are defined, first over the whole pair, then
in cells of :data:`DEFAULT_CELL` voxels whose sums are smoothed over the neighbouring cells and
shrunk towards the global line (a smooth local map: beam hardening, drifts of the source). The
fit starts from the scans' medians and interquartile ranges (:func:`start_map`) and leaves out,
twice, the voxels the last map explains worst (cracks, voids that opened: they must stay in the
residual, not bend the map). The map is a property of the scan pair: it is
fitted once, with the best field at hand, and the same map judges every candidate field.

Every residual is then ``|map(F~) - G|`` in the **reference's gray levels**, in both frames
(loaded frame: ``|map(F) - G'|``, the map read at the loaded voxel; the map is smooth over tens of
voxels and the field moves a few, so the difference is negligible).

Everything here works on sums per cell (:class:`CellSums`), so a volume held in blocks
(``napari_dvc_correct.tiled``) fits the same map as one held whole. Arrays are ``(z, y, x)``;
cells are aligned with the volume's voxel ``(0, 0, 0)``; cell ``c`` covers voxels
``[c * cell, (c + 1) * cell)`` and its centre is ``(c + 0.5) * cell - 0.5``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from ..progress import run_to_completion

#: Edge of a cell of the local map (voxels): a few subvolumes, far larger than a crack's width.
DEFAULT_CELL = 32

#: Gaussian smoothing of the cells' sums (cells): the local map varies smoothly.
CELL_SMOOTHING = 0.5

#: Weight of the global line in a cell's fit, as a fraction of a whole cell's voxels: a cell
#: whose own texture is weak (air, a flat inclusion) takes the global contrast.
PRIOR_FRACTION = 0.25

#: The second fit leaves out voxels whose residual under the first exceeds this many RMS.
TRIM_RMS = 3.0

#: Smallest volume edge (voxels) for a local map: below two cells per axis it is the global line.
MIN_CELLS = 2

_SUMS = ("n", "f", "g", "ff", "fg", "gg")


@dataclass
class CellSums:
    """Sums of ``1, f, g, f², fg, g²`` per cell (float64 arrays of the cells' shape)."""

    n: np.ndarray
    f: np.ndarray
    g: np.ndarray
    ff: np.ndarray
    fg: np.ndarray
    gg: np.ndarray

    @classmethod
    def zeros(cls, cells_shape) -> CellSums:
        return cls(*(np.zeros(tuple(cells_shape)) for _ in _SUMS))

    def add(self, other: CellSums) -> CellSums:
        """In place, and returns self."""
        for name in _SUMS:
            getattr(self, name)[...] += getattr(other, name)
        return self

    def total(self) -> tuple[float, ...]:
        """The whole volume's sums ``(n, f, g, ff, fg, gg)``."""
        return tuple(float(np.sum(getattr(self, name))) for name in _SUMS)


def cells_shape(volume_shape, cell: int) -> tuple[int, int, int]:
    """Number of cells per axis for a volume of ``volume_shape`` (1 per axis for ``cell=0``)."""
    if not cell:
        return (1, 1, 1)
    return tuple(max(1, int(np.ceil(int(n) / cell))) for n in volume_shape)


def _cell_index(region, volume_shape, cell: int) -> np.ndarray:
    """Flat cell index of every voxel of ``region`` (a tuple of 3 slices of the volume)."""
    shape = cells_shape(volume_shape, cell)
    parts = []
    for axis, s in enumerate(region):
        index = np.arange(s.start, s.stop) // cell if cell else np.zeros(s.stop - s.start, int)
        parts.append(np.minimum(index, shape[axis] - 1))
    return (
        parts[0][:, None, None] * (shape[1] * shape[2])
        + parts[1][None, :, None] * shape[2]
        + parts[2][None, None, :]
    )


def block_sums(
    reference_block: np.ndarray,
    moved_block: np.ndarray,
    region,
    volume_shape,
    cell: int,
    previous: GrayLevelMap | None = None,
) -> CellSums:
    """Per-cell sums of one block (``region`` of the volume, a tuple of 3 slices).

    Voxels where either value is not finite are left out; with ``previous`` (the first fit), so
    are the voxels whose residual under it exceeds :data:`TRIM_RMS` times its RMS.
    """
    g = np.asarray(reference_block, dtype=np.float64)
    f = np.asarray(moved_block, dtype=np.float64)
    keep = np.isfinite(f) & np.isfinite(g)
    if previous is not None:
        residual = np.abs(previous.apply(moved_block, region) - g)
        keep &= residual <= TRIM_RMS * previous.rms
    index = _cell_index(region, volume_shape, cell)[keep]
    f, g = f[keep], g[keep]
    shape = cells_shape(volume_shape, cell)
    size = int(np.prod(shape))
    values = (None, f, g, f * f, f * g, g * g)
    sums = [
        np.bincount(index, weights=v, minlength=size).reshape(shape)
        if v is not None
        else np.bincount(index, minlength=size).astype(np.float64).reshape(shape)
        for v in values
    ]
    return CellSums(*sums)


def _line(n, f, g, ff, fg, gg, prior=None):
    """Least-squares ``g ≈ a f + b`` from sums, optionally pulled towards ``prior = (a0, w, v0)``
    (the contrast ``a0`` weighted as ``w`` voxels of variance ``v0``). Returns ``a, b, rms``."""
    n = np.maximum(n, 1e-300)
    mf, mg = f / n, g / n
    vf = np.maximum(ff / n - mf * mf, 0.0)
    vg = np.maximum(gg / n - mg * mg, 0.0)
    cov = fg / n - mf * mg
    if prior is None:
        a = np.where(vf > 0, cov / np.where(vf > 0, vf, 1.0), 1.0)
    else:
        a0, weight, v0 = prior
        a = (n * cov + weight * v0 * a0) / (n * vf + weight * v0)
    b = mg - a * mf
    rms = np.sqrt(np.maximum(vg - 2 * a * cov + a * a * vf, 0.0))
    return a, b, rms


@dataclass(frozen=True)
class GrayLevelMap:
    """``G ≈ contrast(X) · F~ + offset(X)``: the loaded scan's gray levels in the reference's.

    Attributes
    ----------
    contrast, offset : float
        The global least-squares line (dimensionless; reference gray levels).
    rms : float
        RMS residual of the global line over the voxels fitted (reference gray levels).
    cell : int
        Edge of the local map's cells (voxels); 0 for a global map only.
    local_contrast, local_offset : ndarray, shape (cz, cy, cx), optional
        The smooth local map at the cells' centres (None for a global map).
    volume_shape : tuple of 3 ints
        ``(nz, ny, nx)`` of the volumes the map was fitted on.
    fitted_voxels : int
        Voxels of the final fit (after trimming).
    """

    contrast: float = 1.0
    offset: float = 0.0
    rms: float = float("inf")
    cell: int = 0
    local_contrast: np.ndarray | None = None
    local_offset: np.ndarray | None = None
    volume_shape: tuple = (0, 0, 0)
    fitted_voxels: int = 0

    @classmethod
    def identity(cls, volume_shape=(0, 0, 0)) -> GrayLevelMap:
        """No change of gray levels (the raw residual ``|F~ - G|``)."""
        return cls(volume_shape=tuple(int(n) for n in volume_shape))

    @property
    def is_local(self) -> bool:
        return self.local_contrast is not None

    @property
    def is_identity(self) -> bool:
        return not self.is_local and self.contrast == 1.0 and self.offset == 0.0

    def _interpolate(self, values: np.ndarray, region) -> np.ndarray:
        """Trilinear interpolation of cell-centre ``values`` at the voxels of ``region``."""
        out = values
        for axis, s in enumerate(region):
            n_cells = values.shape[axis]
            position = (np.arange(s.start, s.stop) + 0.5) / self.cell - 0.5
            position = np.clip(position, 0.0, n_cells - 1)
            low = np.minimum(np.floor(position).astype(int), max(n_cells - 2, 0))
            high = np.minimum(low + 1, n_cells - 1)
            weight = position - low
            out = np.take(out, low, axis=axis) * _along(1.0 - weight, axis) + np.take(
                out, high, axis=axis
            ) * _along(weight, axis)
        return out

    def coefficients(self, region) -> tuple:
        """``(contrast, offset)`` at the voxels of ``region`` (arrays, or floats for a global
        map)."""
        if not self.is_local:
            return self.contrast, self.offset
        return (
            self._interpolate(self.local_contrast, region).astype(np.float32),
            self._interpolate(self.local_offset, region).astype(np.float32),
        )

    def apply(self, moved: np.ndarray, region=None) -> np.ndarray:
        """``contrast · moved + offset`` (float32), ``moved`` being the loaded scan's gray levels
        at the voxels of ``region`` (default: the whole volume; NaN stays NaN)."""
        moved = np.asarray(moved, dtype=np.float32)
        if region is None:
            region = tuple(slice(0, int(n)) for n in moved.shape)
        if self.is_identity:
            return moved
        if not self.is_local:
            return (np.float32(self.contrast) * moved + np.float32(self.offset)).astype(
                np.float32, copy=False
            )
        out = np.empty(moved.shape, np.float32)
        # slab by slab along z: the coefficients of a slab at a time
        z0 = region[0].start
        for start in range(0, moved.shape[0], 16):
            stop = min(start + 16, moved.shape[0])
            sub = (slice(z0 + start, z0 + stop), region[1], region[2])
            a, b = self.coefficients(sub)
            out[start:stop] = a * moved[start:stop] + b
        return out

    def describe(self) -> str:
        """One line for panels and reports."""
        sign = "+" if self.offset >= 0 else "−"
        text = f"G ≈ {self.contrast:.3g}·F {sign} {abs(self.offset):.4g}"
        if self.is_local:
            lo, hi = np.nanmin(self.local_contrast), np.nanmax(self.local_contrast)
            text += f" (local, {self.cell}-voxel cells: contrast {lo:.3g}–{hi:.3g})"
        return text

    def to_dict(self) -> dict:
        """JSON-ready (``metadata["gray_levels"]``)."""
        return {
            "model": "local affine" if self.is_local else "affine",
            "contrast": float(self.contrast),
            "offset": float(self.offset),
            "rms": float(self.rms),
            "cell": int(self.cell),
            "local_contrast": None
            if self.local_contrast is None
            else np.round(self.local_contrast, 6).tolist(),
            "local_offset": None
            if self.local_offset is None
            else np.round(self.local_offset, 4).tolist(),
            "volume_shape": [int(n) for n in self.volume_shape],
            "fitted_voxels": int(self.fitted_voxels),
            "description": self.describe(),
        }

    @classmethod
    def from_dict(cls, values: dict | None) -> GrayLevelMap:
        """Read a map back from metadata (None or {}: the identity)."""
        if not values:
            return cls.identity()
        local_c, local_o = values.get("local_contrast"), values.get("local_offset")
        return cls(
            contrast=float(values.get("contrast", 1.0)),
            offset=float(values.get("offset", 0.0)),
            rms=float(values.get("rms", float("inf"))),
            cell=int(values.get("cell", 0)),
            local_contrast=None if local_c is None else np.asarray(local_c, np.float64),
            local_offset=None if local_o is None else np.asarray(local_o, np.float64),
            volume_shape=tuple(int(n) for n in values.get("volume_shape", (0, 0, 0))),
            fitted_voxels=int(values.get("fitted_voxels", 0)),
        )


def _along(weights: np.ndarray, axis: int) -> np.ndarray:
    shape = [1, 1, 1]
    shape[axis] = len(weights)
    return weights.reshape(shape)


def map_from_sums(sums: CellSums, volume_shape, cell: int) -> GrayLevelMap:
    """The gray-level map of per-cell sums (see the module): global line, then the smooth local
    one where the volume holds at least :data:`MIN_CELLS` cells along every axis."""
    n, f, g, ff, fg, gg = sums.total()
    if n < 2:
        return GrayLevelMap.identity(volume_shape)
    a, b, rms = (float(v) for v in _line(n, f, g, ff, fg, gg))
    if not (np.isfinite(a) and np.isfinite(b)):
        return GrayLevelMap.identity(volume_shape)
    shape = tuple(int(s) for s in volume_shape)
    local_c = local_o = None
    use_local = cell and all(int(np.ceil(s / cell)) >= MIN_CELLS for s in shape)
    if use_local:
        smooth = {
            name: ndimage.gaussian_filter(getattr(sums, name), CELL_SMOOTHING, mode="nearest")
            for name in _SUMS
        }
        vf = max(ff / n - (f / n) ** 2, 0.0)
        weight = PRIOR_FRACTION * float(cell) ** 3
        local_c, local_o, _ = _line(
            smooth["n"], smooth["f"], smooth["g"], smooth["ff"], smooth["fg"], smooth["gg"],
            prior=(a, weight, vf),
        )  # fmt: skip
        empty = smooth["n"] < 1.0
        local_c[empty], local_o[empty] = a, b
    return GrayLevelMap(
        contrast=a,
        offset=b,
        rms=rms if np.isfinite(rms) and rms > 0 else float("inf"),
        cell=int(cell) if use_local else 0,
        local_contrast=local_c,
        local_offset=local_o,
        volume_shape=shape,
        fitted_voxels=int(n),
    )


def start_map(reference_sample: np.ndarray, deformed_sample: np.ndarray) -> GrayLevelMap:
    """A robust first guess of the map from the two scans' gray-level distributions alone.

    Their medians and interquartile ranges (a motion of a few voxels barely changes a scan's
    histogram, and neither does a crack of a few percent of the voxels): ``contrast`` =
    IQR(G) / IQR(F), the medians matched; ``rms`` = G's robust standard deviation, the scale
    the first fit trims at. Samples may be any subsets (a lattice of the volumes).
    """
    g = np.asarray(reference_sample, dtype=np.float64).ravel()
    f = np.asarray(deformed_sample, dtype=np.float64).ravel()
    g, f = g[np.isfinite(g)], f[np.isfinite(f)]
    if g.size < 2 or f.size < 2:
        return GrayLevelMap.identity()
    g25, g50, g75 = np.percentile(g, [25, 50, 75])
    f25, f50, f75 = np.percentile(f, [25, 50, 75])
    if not (f75 > f25 and g75 > g25):
        return GrayLevelMap(contrast=1.0, offset=float(g50 - f50), rms=float("inf"))
    contrast = (g75 - g25) / (f75 - f25)
    return GrayLevelMap(
        contrast=float(contrast),
        offset=float(g50 - contrast * f50),
        rms=float((g75 - g25) / 1.349),
    )


def fit_from_passes(sums_with, start: GrayLevelMap, shape, cell: int = DEFAULT_CELL):
    """The gray-level map from passes over the blocks (as :func:`fit_gray_levels`:
    least squares trimmed by the previous map, twice). ``sums_with(previous)`` returns the
    :class:`CellSums` of the whole volume with the voxels ``previous`` explains worst left out
    (a generator: yields progress, returns the sums)."""
    previous = start
    for _ in range(2):
        sums = yield from sums_with(previous)
        fitted = map_from_sums(sums, shape, cell)
        if fitted.fitted_voxels < 2 or not np.isfinite(fitted.rms):
            return fitted if previous.is_identity else previous
        previous = fitted
    return previous


def fit_gray_levels(
    reference: np.ndarray,
    moved: np.ndarray,
    *,
    cell: int = DEFAULT_CELL,
    slab: int = 32,
    start: GrayLevelMap | None = None,
) -> GrayLevelMap:
    """Fit ``G ≈ contrast(X) · F~ + offset(X)`` on two whole volumes (see the module).

    Parameters
    ----------
    reference : ndarray, shape (nz, ny, nx)
        ``G`` (reference gray levels).
    moved : ndarray, shape (nz, ny, nx)
        ``F~(X) = F(X + u(X))``, the loaded scan brought back by the best field at hand (NaN
        where undefined).
    cell : int
        Edge of the local map's cells (voxels); 0: the global line only.
    start : GrayLevelMap, optional
        The first guess (:func:`start_map`); default: from the two volumes' lattice samples.

    Returns
    -------
    GrayLevelMap
        The identity where nothing could be fitted (fewer than two defined voxels).
    """
    reference = np.asarray(reference)
    moved = np.asarray(moved)
    if reference.shape != moved.shape or reference.ndim != 3:
        raise ValueError(
            f"reference {reference.shape} and moved {moved.shape} must be 3-D of one shape"
        )
    if cell < 0:
        raise ValueError(f"cell must be >= 0 voxels, got {cell}")
    shape = reference.shape
    lattice = tuple(slice(None, None, max(1, n // 64)) for n in shape)

    def sums_with(previous):
        sums = CellSums.zeros(cells_shape(shape, cell))
        for z0 in range(0, shape[0], slab):
            region = (slice(z0, min(z0 + slab, shape[0])), slice(0, shape[1]), slice(0, shape[2]))
            sums.add(block_sums(reference[region], moved[region], region, shape, cell, previous))
        return sums
        yield  # a generator without progress: the arrays are at hand

    start = start_map(reference[lattice], moved[lattice]) if start is None else start
    return run_to_completion(fit_from_passes(sums_with, start, shape, cell))
