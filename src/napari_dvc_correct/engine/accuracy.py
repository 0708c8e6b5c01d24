"""Accuracy of a displacement field without ground truth (paper section 2.2, eqs. 1–2, Table 1).

The pieces, in the order the paper uses them:

1. **Phases.** Each volume is split into ``N`` phases by ``N - 1`` increasing gray thresholds
   (multi-Otsu by default, as the paper's soil / quartz split; any ``N >= 2``). Label ``k`` holds
   the voxels with ``T_k <= gray < T_{k+1}`` (``T_0 = -inf``, ``T_N = +inf``). The per-phase gray
   range and mean gray of each state make the paper's Table 1 (:func:`phase_table`).
2. **Background residual (eq. 1).** The gray residual ``r(X) = |F(X + u(X)) - G(X)|`` is computed
   by :func:`napari_dvc_correct.engine.warp.gray_residual`. At voxels where the phase of ``G`` and
   the phase of ``F`` mapped by the field agree, the residual is (ideally) imaging noise only; its
   mean over those voxels is the background residual ``r0`` (:func:`background_residual`), and
   ``r' = r - r0`` is the corrected residual.
3. **Accuracy index (eq. 2).** ``p = 1 - mean(r') / |g1 - g2|`` with ``g1, g2`` the mean grays of
   the two phases (:func:`accuracy_index`, :func:`phase_contrast`). For ``N > 2`` phases the two
   *most abundant* phases of the reference are used by default (they make most of the texture the
   matcher sees and most of the phase boundaries a misplaced voxel lands on); any pair can be
   chosen.
4. **Curves against equivalent strain** (paper Figs. 10–11, :func:`bin_residual_by_strain`). The
   equivalent strain lives on the POI grid; each voxel takes the strain of its *nearest node*
   (the node's cell of ``step`` voxels around it), which is the same as binning the POI
   neighbourhoods' residual sums. Voxels farther than half a step outside the grid hull are left
   out (the field is extrapolated there).

All functions take plain arrays (residual volume, label volumes) so they can be used with any
residual; :func:`evaluate_fields` runs the whole chain for one or several fields.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from .field import DisplacementField, Status

#: Voxels per slab when a volume is processed piecewise (bounds the temporary memory).
SLAB_VOXELS = 1 << 22
#: Most voxels fed to multi-Otsu (larger volumes are subsampled on a regular lattice).
OTSU_SAMPLES = 1 << 22
#: Histogram bins for multi-Otsu.
OTSU_BINS = 256
MAX_PHASES = 8


def _slabs(shape, voxels: int = SLAB_VOXELS):
    """``slice`` objects along z covering a volume with about ``voxels`` voxels each."""
    plane = max(1, int(shape[1]) * int(shape[2]))
    depth = max(1, voxels // plane)
    for start in range(0, int(shape[0]), depth):
        yield slice(start, min(int(shape[0]), start + depth))


def _check_volume(volume, name: str) -> np.ndarray:
    volume = np.asanyarray(volume)
    if volume.ndim != 3 or min(volume.shape) < 1:
        raise ValueError(f"{name} must be a non-empty 3-D volume (z, y, x), got {volume.shape}")
    if volume.dtype.kind not in "uif":
        raise ValueError(f"{name} must hold real gray values, got dtype {volume.dtype}")
    return volume


def gray_range(volume: np.ndarray) -> tuple[float, float]:
    """``(min, max)`` of the finite gray values of ``volume`` (read slab by slab)."""
    low, high = np.inf, -np.inf
    for zs in _slabs(volume.shape):
        slab = np.asarray(volume[zs])
        if slab.dtype.kind == "f":
            slab = slab[np.isfinite(slab)]
        if slab.size:
            low, high = min(low, float(slab.min())), max(high, float(slab.max()))
    return low, high


# --- grid quantities ready to display -------------------------------------------------------------
def zncc_volume(field: DisplacementField) -> tuple[np.ndarray, dict, str]:
    """The per-POI ZNCC as a grid image, ready for napari (``(data, kwargs, "image")``).

    Returns
    -------
    data : ndarray, shape (nz, ny, nx), float32
        ZNCC in [-1, 1], NaN where no match was made.
    kwargs : dict
        ``name``, ``scale`` (= step) and ``translate`` (= origin) so the grid overlays the volume,
        ``colormap`` and ``contrast_limits``.
    layer_type : str
        ``"image"``.
    """
    data = np.asarray(field.zncc, dtype=np.float32).copy()
    kwargs = {"name": "ZNCC", "colormap": "viridis", "contrast_limits": (0.0, 1.0)}
    kwargs.update(field.layer_kwargs())
    return data, kwargs, "image"


def status_volume(field: DisplacementField) -> tuple[np.ndarray, dict, str]:
    """The per-POI :class:`Status` codes as a grid label image (``(data, kwargs, "labels")``).

    Returns
    -------
    data : ndarray, shape (nz, ny, nx), uint8
        Status code + 1, so that CONVERGED (code 0) is not the transparent background label 0.
    kwargs : dict
        ``name``, ``scale``, ``translate`` and ``metadata["status_names"]`` mapping each label
        value to its readable status name.
    layer_type : str
        ``"labels"``.
    """
    data = field.status.astype(np.uint8) + np.uint8(1)
    names = {int(s) + 1: s.label for s in Status}
    kwargs = {"name": "status", "metadata": {"status_names": names}}
    kwargs.update(field.layer_kwargs())
    return data, kwargs, "labels"


def check_field_fits(field: DisplacementField, volume_shape, name: str = "field") -> None:
    """Raise ``ValueError`` unless every node of ``field`` lies inside a volume of ``volume_shape``.

    A field computed on another volume (other size, other crop) would silently produce residuals
    of the wrong material; this catches it before any work is done.
    """
    volume_shape = tuple(int(n) for n in volume_shape)
    for axis, (coords, n) in enumerate(zip(field.axis_coordinates(), volume_shape)):
        if coords[0] < -0.5 or coords[-1] > n - 0.5:
            raise ValueError(
                f"{name}'s grid does not fit the volume: along axis {'zyx'[axis]} its nodes span "
                f"{coords[0]:g}..{coords[-1]:g} voxels but the volume has {n} voxels "
                f"(0..{n - 1}); was the field computed on another volume?"
            )


# --- phases ---------------------------------------------------------------------------------------
def auto_thresholds(volume: np.ndarray, n_phases: int = 2) -> np.ndarray:
    """``n_phases - 1`` gray thresholds by multi-Otsu (``skimage.filters.threshold_multiotsu``).

    Volumes larger than :data:`OTSU_SAMPLES` voxels are subsampled on a regular lattice first.

    Returns
    -------
    ndarray, shape (n_phases - 1,), float64, increasing
    """
    from skimage.filters import threshold_multiotsu

    volume = _check_volume(volume, "volume")
    n_phases = _check_n_phases(n_phases)
    stride = max(1, int(np.ceil((volume.size / OTSU_SAMPLES) ** (1.0 / 3.0))))
    sample = np.asarray(volume[::stride, ::stride, ::stride], dtype=np.float64).ravel()
    sample = sample[np.isfinite(sample)]
    if sample.size == 0 or sample.min() == sample.max():
        raise ValueError("the volume has a single gray value: it cannot be split into phases")
    counts, edges = np.histogram(sample, bins=OTSU_BINS)
    centers = 0.5 * (edges[:-1] + edges[1:])
    try:
        found = threshold_multiotsu(hist=(counts, centers), classes=n_phases)
    except ValueError as error:
        raise ValueError(
            f"multi-Otsu could not find {n_phases - 1} thresholds ({error}); give the thresholds "
            "yourself or ask for fewer phases"
        ) from error
    # skimage returns the centre of the last bin of the lower class ("upper class: gray > t");
    # our phases start *at* their threshold, so move each threshold to that bin's upper edge,
    # which keeps every gray of that bin in the lower phase.
    index = np.searchsorted(centers, np.asarray(found, dtype=np.float64))
    return edges[np.clip(index, 0, OTSU_BINS - 1) + 1].astype(np.float64)


def _check_n_phases(n_phases) -> int:
    if not isinstance(n_phases, (int, np.integer)) or not 2 <= n_phases <= MAX_PHASES:
        raise ValueError(
            f"the number of phases must be an integer in 2..{MAX_PHASES}, got {n_phases!r}"
        )
    return int(n_phases)


def validate_thresholds(thresholds, value_range: tuple[float, float], name: str = "volume"):
    """Check user thresholds: finite, strictly increasing, strictly inside the gray range.

    Parameters
    ----------
    thresholds : sequence of float
        ``N - 1`` thresholds for ``N`` phases (1 to 7 values).
    value_range : (float, float)
        ``(min, max)`` gray value of the volume they apply to.
    name : str
        Volume name for the error messages.

    Returns
    -------
    ndarray, shape (N - 1,), float64

    Raises
    ------
    ValueError
        Naming the offending threshold and what to change.
    """
    values = np.atleast_1d(np.asarray(thresholds, dtype=np.float64))
    if values.ndim != 1 or not 1 <= values.size <= MAX_PHASES - 1:
        raise ValueError(
            f"give 1 to {MAX_PHASES - 1} gray thresholds (N - 1 for N phases), got {thresholds!r}"
        )
    if not np.all(np.isfinite(values)):
        raise ValueError(f"gray thresholds must be finite numbers, got {thresholds!r}")
    if np.any(np.diff(values) <= 0):
        raise ValueError(
            "gray thresholds must be strictly increasing, got "
            + ", ".join(f"{v:g}" for v in values)
        )
    low, high = value_range
    for value in values:
        if not low < value <= high:
            raise ValueError(
                f"gray threshold {value:g} is outside the gray range of the {name} "
                f"({low:g}..{high:g}): choose thresholds inside it"
            )
    return values


def phase_thresholds(volume: np.ndarray, phases="auto", n_phases: int = 2, name: str = "volume"):
    """Thresholds for ``volume``: multi-Otsu when ``phases`` is ``"auto"``/None, else validated.

    Parameters
    ----------
    volume : ndarray, shape (nz, ny, nx)
    phases : "auto", None or sequence of float
        ``"auto"`` for ``n_phases`` multi-Otsu phases, or the ``N - 1`` user thresholds.
    n_phases : int
        Number of phases for ``"auto"``.

    Returns
    -------
    ndarray, shape (N - 1,), float64
    """
    volume = _check_volume(volume, name)
    if phases is None or (isinstance(phases, str) and phases == "auto"):
        return auto_thresholds(volume, n_phases)
    if isinstance(phases, str):
        raise ValueError(f"phases must be 'auto' or a list of thresholds, got {phases!r}")
    return validate_thresholds(phases, gray_range(volume), name)


def segment_phases(volume: np.ndarray, thresholds, name: str = "volume") -> np.ndarray:
    """Label volume of phases ``0 .. N-1`` from ``N - 1`` increasing thresholds.

    Voxel ``X`` gets label ``k`` when ``thresholds[k-1] <= volume[X] < thresholds[k]``.

    Parameters
    ----------
    volume : ndarray, shape (nz, ny, nx)
        Gray values (any real dtype; read slab by slab, so memory maps stay lazy).
    thresholds : sequence of float
        Strictly increasing.
    name : str
        Volume name for the error messages.

    Returns
    -------
    ndarray, shape (nz, ny, nx), uint8

    Raises
    ------
    ValueError
        If the thresholds are not strictly increasing or a phase holds no voxel.
    """
    volume = _check_volume(volume, name)
    values = np.atleast_1d(np.asarray(thresholds, dtype=np.float64))
    if values.ndim != 1 or values.size < 1 or np.any(np.diff(values) <= 0):
        raise ValueError(f"gray thresholds must be strictly increasing, got {thresholds!r}")
    labels = np.empty(volume.shape, np.uint8)
    counts = np.zeros(values.size + 1, np.int64)
    for zs in _slabs(volume.shape):
        slab = np.digitize(np.asarray(volume[zs], dtype=np.float64), values).astype(np.uint8)
        labels[zs] = slab
        counts += np.bincount(slab.ravel(), minlength=values.size + 1)[: values.size + 1]
    empty = np.flatnonzero(counts == 0)
    if empty.size:
        phase = int(empty[0])
        low = "-inf" if phase == 0 else f"{values[phase - 1]:g}"
        high = "+inf" if phase == values.size else f"{values[phase]:g}"
        raise ValueError(
            f"phase {phase} (gray {low} .. {high}) has no voxel in the {name}: move the "
            "thresholds or ask for fewer phases"
        )
    return labels


@dataclass(frozen=True)
class PhaseStats:
    """One row of the paper's Table 1 for one state.

    Attributes
    ----------
    phase : int
        Label value.
    lower, upper : float
        Gray range of the phase: from the lower threshold (or the volume's minimum) to the upper
        threshold (or the volume's maximum).
    mean_gray : float
        Mean gray value of its voxels.
    voxels : int
        Number of voxels.
    fraction : float
        Share of the volume's voxels.
    """

    phase: int
    lower: float
    upper: float
    mean_gray: float
    voxels: int
    fraction: float


def phase_table(volume: np.ndarray, labels: np.ndarray, thresholds) -> list[PhaseStats]:
    """Gray range, mean gray and size of each phase (paper Table 1, one state).

    Parameters
    ----------
    volume : ndarray, shape (nz, ny, nx)
        Gray values.
    labels : ndarray, shape (nz, ny, nx), integer
        Phases from :func:`segment_phases` with the same ``thresholds``.
    thresholds : sequence of float
        The ``N - 1`` thresholds.

    Returns
    -------
    list of PhaseStats, one per phase, in label order.
    """
    values = np.atleast_1d(np.asarray(thresholds, dtype=np.float64))
    n = values.size + 1
    if labels.shape != volume.shape:
        raise ValueError(f"labels {labels.shape} and volume {volume.shape} differ in shape")
    sums = np.zeros(n)
    counts = np.zeros(n, np.int64)
    for zs in _slabs(volume.shape):
        lab = np.asarray(labels[zs]).ravel()
        gray = np.asarray(volume[zs], dtype=np.float64).ravel()
        sums += np.bincount(lab, weights=gray, minlength=n)[:n]
        counts += np.bincount(lab, minlength=n)[:n]
    low, high = gray_range(volume)
    bounds = [low, *values.tolist(), high]
    total = max(1, int(counts.sum()))
    return [
        PhaseStats(
            phase=k,
            lower=float(bounds[k]),
            upper=float(bounds[k + 1]),
            mean_gray=float(sums[k] / counts[k]) if counts[k] else float("nan"),
            voxels=int(counts[k]),
            fraction=float(counts[k] / total),
        )
        for k in range(n)
    ]


# --- background residual, eq. 1, and accuracy index, eq. 2 ----------------------------------------
@dataclass(frozen=True)
class BackgroundResidual:
    """Mean gray residual where both states hold the same phase (the imaging-noise estimate).

    Attributes
    ----------
    mean : float
        ``r0`` of eq. 1: the mean residual over every voxel whose phase agrees in both states
        (pooled over phases), gray levels.
    voxels : int
        Number of such voxels with a finite residual.
    per_phase : tuple of (phase, mean, voxels)
        The same, phase by phase (mean NaN for a phase with no agreeing voxel).
    """

    mean: float
    voxels: int
    per_phase: tuple


def background_residual(
    residual: np.ndarray, labels_reference: np.ndarray, labels_mapped: np.ndarray
) -> BackgroundResidual:
    """Background (imaging-noise) residual, paper eq. 1.

    Parameters
    ----------
    residual : ndarray, shape (nz, ny, nx), float
        Gray residual volume ``r`` (NaN where undefined).
    labels_reference : ndarray, shape (nz, ny, nx), integer
        Phases of the state the residual's voxels belong to (``G`` for the reference-frame
        residual ``|F(X + u) - G(X)|``).
    labels_mapped : ndarray, shape (nz, ny, nx), integer
        Phases of the other state brought onto the same voxels by the field (phases of
        ``F(X + u(X))``).

    Returns
    -------
    BackgroundResidual

    Raises
    ------
    ValueError
        If the shapes differ or no voxel has the same phase in both states with a finite
        residual (the field cannot be this wrong, or the phases were mislabelled).
    """
    residual = np.asanyarray(residual)
    if not (residual.shape == labels_reference.shape == labels_mapped.shape):
        raise ValueError(
            f"residual {residual.shape}, reference labels {labels_reference.shape} and mapped "
            f"labels {labels_mapped.shape} must have the same shape"
        )
    n = int(max(np.max(labels_reference), np.max(labels_mapped))) + 1
    sums = np.zeros(n)
    counts = np.zeros(n, np.int64)
    for zs in _slabs(residual.shape):
        r = np.asarray(residual[zs], dtype=np.float64)
        a = np.asarray(labels_reference[zs])
        keep = (a == np.asarray(labels_mapped[zs])) & np.isfinite(r)
        sums += np.bincount(a[keep], weights=r[keep], minlength=n)[:n]
        counts += np.bincount(a[keep], minlength=n)[:n]
    total = int(counts.sum())
    if total == 0:
        raise ValueError(
            "no voxel holds the same phase in both states with a finite residual: the "
            "background residual is undefined (check the thresholds and the field)"
        )
    per_phase = tuple(
        (k, float(sums[k] / counts[k]) if counts[k] else float("nan"), int(counts[k]))
        for k in range(n)
    )
    return BackgroundResidual(mean=float(sums.sum() / total), voxels=total, per_phase=per_phase)


def corrected_residual(residual: np.ndarray, background: BackgroundResidual | float) -> np.ndarray:
    """Corrected residual ``r' = r - r0`` (eq. 1), float32, same shape; may be negative."""
    r0 = background.mean if isinstance(background, BackgroundResidual) else float(background)
    return (np.asarray(residual, dtype=np.float32) - np.float32(r0)).astype(np.float32)


def default_phase_pair(stats: Sequence[PhaseStats]) -> tuple[int, int]:
    """The two most abundant phases, in label order (the pair eq. 2 uses for ``N > 2``)."""
    if len(stats) < 2:
        raise ValueError("the accuracy index needs at least two phases")
    order = sorted(stats, key=lambda s: (-s.voxels, s.phase))
    return tuple(sorted((order[0].phase, order[1].phase)))


def phase_contrast(
    reference_stats: Sequence[PhaseStats],
    deformed_stats: Sequence[PhaseStats] | None = None,
    pair: tuple[int, int] | None = None,
) -> tuple[float, tuple[int, int]]:
    """Gray contrast ``|g1 - g2|`` between two phases, the denominator of eq. 2.

    Parameters
    ----------
    reference_stats, deformed_stats : list of PhaseStats
        :func:`phase_table` of the reference and of the deformed state. With both, the contrast
        is the mean of the two states' contrasts (the paper's Table 1 lists both states; gray
        levels drift a little between scans); with only the first, that state's contrast.
    pair : (int, int), optional
        Phases to use; default :func:`default_phase_pair` of the reference.

    Returns
    -------
    contrast : float
        Gray levels, > 0.
    pair : (int, int)
    """
    pair = default_phase_pair(reference_stats) if pair is None else tuple(int(p) for p in pair)
    if len(pair) != 2 or pair[0] == pair[1]:
        raise ValueError(f"the phase pair must name two different phases, got {pair}")
    contrasts = []
    for stats in (reference_stats, deformed_stats):
        if stats is None:
            continue
        means = {s.phase: s.mean_gray for s in stats}
        missing = [p for p in pair if p not in means]
        if missing:
            raise ValueError(f"phase {missing[0]} does not exist (phases: {sorted(means)})")
        contrasts.append(abs(means[pair[0]] - means[pair[1]]))
    contrast = float(np.mean(contrasts))
    if not np.isfinite(contrast) or contrast <= 0:
        raise ValueError(f"phases {pair} have the same mean gray: the accuracy index is undefined")
    return contrast, pair


def accuracy_index(mean_residual, background: BackgroundResidual | float, contrast: float):
    """Accuracy index, eq. 2: ``p = 1 - (mean(r) - r0) / |g1 - g2|``.

    Parameters
    ----------
    mean_residual : float or ndarray
        Mean gray residual ``mean(r)`` over a region (the whole volume, or each strain bin).
    background : BackgroundResidual or float
        ``r0`` (eq. 1).
    contrast : float
        ``|g1 - g2|`` from :func:`phase_contrast`.

    Returns
    -------
    float or ndarray
        1 for a residual at the noise level; it falls by 0.1 for every tenth of the phase
        contrast the mean residual rises above the noise. It can exceed 1 slightly where a region's
        residual is below the volume's average noise (it is not clipped).
    """
    r0 = background.mean if isinstance(background, BackgroundResidual) else float(background)
    if not contrast > 0:
        raise ValueError(f"the phase contrast must be > 0, got {contrast}")
    result = 1.0 - (np.asarray(mean_residual, dtype=np.float64) - r0) / float(contrast)
    return float(result) if result.ndim == 0 else result


# --- curves against equivalent strain -------------------------------------------------------------
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
    for zs in _slabs(residual.shape):
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
