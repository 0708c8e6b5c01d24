"""The gray-level model: how the loaded scan's gray levels map onto the reference's.

Real scans change their gray levels between load steps (the paper's Table 1; a fractured rock
whose mean falls from 113 to 60 and its contrast by 3x). A raw gray residual
``|F(X + u(X)) - G(X)|`` then measures that brightness change, not the field's error, and every
decision taken on it (the correction's acceptance, its noise floor, its flags, eqs. 1-2) goes
wrong. The paper asks for the residual to be corrected for the gray-level change of the target
volume; this module is that correction:

    ``G(X) ≈ contrast(X) · F~(X) + offset(X)``,  ``F~(X) = F(X + u(X))``,

fitted over the voxels where both are defined, first over the whole pair, then in cells of
:data:`DEFAULT_CELL` voxels whose sums are smoothed over the neighbouring cells and shrunk
towards the global line (a smooth local map: beam hardening, drifts of the source). Both scans
are noisy, so least squares of ``G`` on ``F~`` would be diluted by ``F~``'s noise (an unchanged
CT pair at 5 % noise reads a contrast of 0.90, the transformed texture shrinks in every
residual): the lines are fitted with errors in variables, ``F~``'s noise variance (each scan's
own, measured by :mod:`.gray_noise`) taken out of its variance (:data:`FITS` says why not
Deming). The
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
from .gray_map_kernels import apply_local_map, cell_sums
from .gray_noise import PairNoise

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

#: How a map's lines can be fitted, from the same sums:
#:
#: * ``"errors in variables"``: least squares of ``G`` on ``F~`` with ``F~``'s measured noise
#:   variance taken out of its variance, ``a = cov / (var(F~) - σ²(F~))``: not diluted by the
#:   loaded scan's noise, and, as least squares, deaf to whatever ``F~`` does not explain in ``G``
#:   (``G``'s noise, a field's errors, a gray change the map does not model);
#: * ``"deming"``: errors in both with the ratio of the two noises (the reduced major axis where
#:   it is unknown): unbiased on a pair that only differs by noise, but every variance of ``G``
#:   that ``F~`` does not explain is read as noise split by that ratio and tilts the line
#:   (measured: a contrast ramp read 2.3 instead of 0.85 on CT texture);
#: * ``"least squares"``: of ``G`` on ``F~``, diluted by ``F~``'s noise (an unchanged CT pair at
#:   5 % noise: 0.90), the best *prediction* of ``G`` from ``F~``.
FITS = ("errors in variables", "deming", "least squares")
#: The fit of every map unless a caller asks for another.
FIT = "errors in variables"
#: The errors-in-variables fit never counts less than this share of ``F~``'s variance as texture
#: (a cell of air or flat material is mostly noise: its slope must not blow up).
MIN_RELIABILITY = 0.1

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


def _axis_cells(region, volume_shape, cell: int) -> list[np.ndarray]:
    """Per axis, the cell index of every voxel of ``region`` (a tuple of 3 slices)."""
    shape = cells_shape(volume_shape, cell)
    parts = []
    for axis, s in enumerate(region):
        index = np.arange(s.start, s.stop) // cell if cell else np.zeros(s.stop - s.start, int)
        parts.append(np.minimum(index, shape[axis] - 1))
    return parts


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
    shape = cells_shape(volume_shape, cell)
    index = _axis_cells(region, volume_shape, cell)
    mapped, limit = None, 0.0
    if previous is not None:
        mapped, limit = previous.apply(moved_block, region), TRIM_RMS * previous.rms
    return CellSums(*cell_sums(reference_block, moved_block, mapped, limit, index, shape))


def _moments(n, f, g, ff, fg, gg):
    """Means and centred second moments per voxel ``(mf, mg, vf, cov, vg)`` of sums."""
    n = np.maximum(n, 1e-300)
    mf, mg = f / n, g / n
    vf = np.maximum(ff / n - mf * mf, 0.0)
    vg = np.maximum(gg / n - mg * mg, 0.0)
    return mf, mg, vf, fg / n - mf * mg, vg


def deming_slope(vf, cov, vg, ratio):
    """Slope of ``g ≈ a f + b`` with noise in both (Deming regression) from centred moments.

    ``ratio`` is ``δ = var(noise of g) / var(noise of f)``: ``inf`` gives ordinary least squares
    of ``g`` on ``f`` (f exact), 0 the reverse regression (g exact), ``vg / vf`` the reduced major
    axis. Where ``f`` and ``g`` do not co-vary the slope is undefined: 1 is returned there.
    """
    vf, cov, vg = np.broadcast_arrays(*(np.asarray(v, np.float64) for v in (vf, cov, vg)))
    if np.isinf(ratio):
        return np.where(vf > 0, cov / np.where(vf > 0, vf, 1.0), 1.0)
    d = vg - ratio * vf
    root = np.sqrt(d * d + 4.0 * ratio * cov * cov)
    # the two forms are equal; each is the stable one on its side of d = 0
    upper = root - d
    with np.errstate(divide="ignore", invalid="ignore"):
        slope = np.where(
            d < 0, 2.0 * ratio * cov / np.where(upper > 0, upper, 1.0), (d + root) / (2.0 * cov)
        )
    return np.where(np.isfinite(slope) & (cov != 0), slope, 1.0)


def _slope(vf, cov, vg, fit: str, noise: PairNoise | None):
    """Slope of ``g ≈ a f + b`` from centred moments per voxel, by ``fit`` (see :data:`FITS`)."""
    if fit == "least squares" or noise is None:
        return deming_slope(vf, cov, vg, np.inf)
    if fit == "deming":
        return deming_slope(vf, cov, vg, noise.ratio)
    # errors in variables: least squares on the texture of F~, its noise taken out. F~'s noise
    # shows in least squares' residual variance at least as a² σ² (a its slope): a noise
    # estimate above that (texture read as noise on a clean scan) is cut to it
    with np.errstate(divide="ignore", invalid="ignore"):
        plain = np.where(vf > 0, cov / np.where(vf > 0, vf, 1.0), 0.0)
        spread = np.maximum(vg - cov * plain, 0.0)
        moved = np.where(plain != 0, np.minimum(noise.moved, spread / (plain * plain)), 0.0)
    texture = np.maximum(vf - moved, MIN_RELIABILITY * vf)
    return np.where(texture > 0, cov / np.where(texture > 0, texture, 1.0), 1.0)


def _line(n, f, g, ff, fg, gg, prior=None, fit="least squares", noise=None):
    """``g ≈ a f + b`` from sums (``fit`` and ``noise`` as :func:`map_from_sums`), optionally
    pulled towards a prior line: ``prior = (weight, (vf0, cov0, vg0))`` adds ``weight`` voxels
    of the prior's centred moments to each cell's (the slope of those moments alone is the
    prior's). Returns ``a, b, rms`` (rms: of ``g - a f - b``)."""
    mf, mg, vf, cov, vg = _moments(n, f, g, ff, fg, gg)
    fit_vf, fit_cov, fit_vg = vf, cov, vg
    if prior is not None:
        weight, (vf0, cov0, vg0) = prior
        total = np.maximum(n, 0.0) + weight
        fit_vf = (n * vf + weight * vf0) / total
        fit_cov = (n * cov + weight * cov0) / total
        fit_vg = (n * vg + weight * vg0) / total
    a = _slope(fit_vf, fit_cov, fit_vg, fit, noise)
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
    fit : str
        How the lines were fitted (:data:`FITS`): ``"least squares"`` where the scans' noise was
        unknown (and for maps written before the other fits).
    noise : PairNoise, optional
        The scans' noise the fit took out (gray levels², :mod:`.gray_noise`).
    """

    contrast: float = 1.0
    offset: float = 0.0
    rms: float = float("inf")
    cell: int = 0
    local_contrast: np.ndarray | None = None
    local_offset: np.ndarray | None = None
    volume_shape: tuple = (0, 0, 0)
    fitted_voxels: int = 0
    fit: str = "least squares"
    noise: PairNoise | None = None

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
        # the coefficients of :meth:`coefficients` voxel by voxel, in one compiled pass
        return apply_local_map(self.local_contrast, self.local_offset, self.cell, moved, region)

    def describe(self) -> str:
        """One line for panels and reports."""
        sign = "+" if self.offset >= 0 else "−"
        text = f"G ≈ {self.contrast:.3g}·F {sign} {abs(self.offset):.4g}"
        notes = []
        if self.is_local:
            lo, hi = np.nanmin(self.local_contrast), np.nanmax(self.local_contrast)
            notes.append(f"local, {self.cell}-voxel cells: contrast {lo:.3g}–{hi:.3g}")
        if self.fit != "least squares" and not self.is_identity:
            notes.append(f"fit: {self.fit}")  # the scans' noise taken out
        return text + (f" ({'; '.join(notes)})" if notes else "")

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
            "fit": self.fit,
            "noise": None if self.noise is None else self.noise.to_dict(),
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
            fit=str(values.get("fit", "least squares")),  # maps written before the other fits
            noise=PairNoise.from_dict(values.get("noise")),
        )


def _along(weights: np.ndarray, axis: int) -> np.ndarray:
    shape = [1, 1, 1]
    shape[axis] = len(weights)
    return weights.reshape(shape)


def map_from_sums(
    sums: CellSums,
    volume_shape,
    cell: int,
    *,
    noise: PairNoise | None = None,
    fit: str | None = None,
) -> GrayLevelMap:
    """The gray-level map of per-cell sums (see the module): global line, then the smooth local
    one where the volume holds at least :data:`MIN_CELLS` cells along every axis.

    ``fit`` is one of :data:`FITS` (default :data:`FIT`); ``noise`` the scans' noise
    (:func:`.gray_noise.pair_noise`): without it every fit is least squares."""
    fit = FIT if fit is None else fit
    if fit not in FITS:
        raise ValueError(f"fit must be one of {FITS}, got {fit!r}")
    if noise is None:
        fit = "least squares"
    n, f, g, ff, fg, gg = sums.total()
    if n < 2:
        return GrayLevelMap.identity(volume_shape)
    a, b, rms = (float(v) for v in _line(n, f, g, ff, fg, gg, fit=fit, noise=noise))
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
        weight = PRIOR_FRACTION * float(cell) ** 3
        prior = (weight, tuple(float(v) for v in _moments(n, f, g, ff, fg, gg)[2:]))
        local_c, local_o, _ = _line(
            smooth["n"], smooth["f"], smooth["g"], smooth["ff"], smooth["fg"], smooth["gg"],
            prior=prior, fit=fit, noise=noise,
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
        fit=fit,
        noise=noise,
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


def fit_from_passes(
    sums_with,
    start: GrayLevelMap,
    shape,
    cell: int = DEFAULT_CELL,
    *,
    noise: PairNoise | None = None,
    fit: str | None = None,
):
    """The gray-level map from passes over the blocks (as :func:`fit_gray_levels`:
    a fit trimmed by the previous map, twice; ``noise`` and ``fit`` as
    :func:`map_from_sums`). ``sums_with(previous)`` returns the :class:`CellSums` of the whole
    volume with the voxels ``previous`` explains worst left out (a generator: yields progress,
    returns the sums)."""
    previous = start
    for _ in range(2):
        sums = yield from sums_with(previous)
        fitted = map_from_sums(sums, shape, cell, noise=noise, fit=fit)
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
    noise: PairNoise | None = None,
    fit: str | None = None,
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
    noise : PairNoise, optional
        The noise of ``G`` and of ``F~`` (:func:`.gray_noise.pair_noise`); None: least squares
        (the scans' noise unknown).
    fit : str, optional
        One of :data:`FITS`; default :data:`FIT`.

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
    return run_to_completion(fit_from_passes(sums_with, start, shape, cell, noise=noise, fit=fit))
