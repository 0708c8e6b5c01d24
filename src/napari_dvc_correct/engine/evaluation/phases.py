"""Phase segmentation of CT volumes by gray thresholds, and per-phase statistics (paper Table 1).

Each volume is split into ``N`` phases by ``N - 1`` strictly increasing gray thresholds: label
``k`` holds the voxels with ``T_k <= gray < T_{k+1}`` (``T_0 = -inf``, ``T_N = +inf``). The
thresholds come from multi-Otsu (:func:`auto_thresholds`, the default, as the paper's soil /
quartz split) or from the user (:func:`validate_thresholds`); the paper finds them per state, and
so do we. Volumes are read slab by slab, so memory-mapped scans stay lazy.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..slabs import iter_slabs
from .options import MAX_PHASES

#: Most voxels fed to multi-Otsu (larger volumes are subsampled on a regular lattice).
OTSU_SAMPLES = 1 << 22
#: Histogram bins for multi-Otsu.
OTSU_BINS = 256
#: Label of voxels without a gray value (NaN) in :func:`label_phases`.
NO_PHASE = 255


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
    for zs in iter_slabs(volume.shape):
        slab = np.asarray(volume[zs])
        if slab.dtype.kind == "f":
            slab = slab[np.isfinite(slab)]
        if slab.size:
            low, high = min(low, float(slab.min())), max(high, float(slab.max()))
    return low, high


def auto_thresholds(volume: np.ndarray, n_phases: int = 2) -> np.ndarray:
    """``n_phases - 1`` gray thresholds by multi-Otsu (``skimage.filters.threshold_multiotsu``).

    Volumes larger than :data:`OTSU_SAMPLES` voxels are subsampled on a regular lattice first.

    Returns
    -------
    ndarray, shape (n_phases - 1,), float64, increasing
    """
    volume = _check_volume(volume, "volume")
    n_phases = _check_n_phases(n_phases)
    stride = otsu_stride(volume.shape)
    return otsu_thresholds(np.asarray(volume[::stride, ::stride, ::stride]).ravel(), n_phases)


def otsu_stride(shape) -> int:
    """Stride of the regular lattice that :func:`auto_thresholds` samples (<= OTSU_SAMPLES voxels)."""
    size = float(np.prod([int(n) for n in shape]))
    return max(1, int(np.ceil((size / OTSU_SAMPLES) ** (1.0 / 3.0))))


def lattice_sample(block: np.ndarray, box, stride: int) -> np.ndarray:
    """The voxels of ``block`` (at ``box`` in the volume) on the lattice ``volume[::s, ::s, ::s]``.

    Concatenated over blocks that tile the volume, the same values as the whole volume's
    lattice (in another order, which a histogram ignores). Returns a 1-D array, block's dtype.
    """
    picks = tuple(slice((-int(s.start)) % int(stride), None, int(stride)) for s in box)
    return np.asarray(block)[picks].ravel()


def otsu_thresholds(sample: np.ndarray, n_phases: int = 2) -> np.ndarray:
    """Multi-Otsu thresholds of a gray sample (a 256-bin histogram over the sample's range).

    Each threshold is the upper edge of its histogram bin (see :func:`auto_thresholds`).
    """
    from skimage.filters import threshold_multiotsu

    n_phases = _check_n_phases(n_phases)
    sample = np.asarray(sample, dtype=np.float64).ravel()
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


def label_phases(volume: np.ndarray, thresholds) -> np.ndarray:
    """Phase labels ``0 .. N-1`` of ``volume`` (NaN voxels get :data:`NO_PHASE`), no checks.

    Used for volumes resampled by a field (e.g. ``F(X + u(X))``), where a phase may well be
    missing from the region the field covers. See :func:`segment_phases` for the convention.

    Returns
    -------
    ndarray, same shape, uint8
    """
    values = np.atleast_1d(np.asarray(thresholds, dtype=np.float64))
    labels = np.empty(np.shape(volume), np.uint8)
    for zs in iter_slabs(labels.shape):
        slab = np.asarray(volume[zs], dtype=np.float64)
        lab = np.digitize(slab, values).astype(np.uint8)
        lab[~np.isfinite(slab)] = NO_PHASE
        labels[zs] = lab
    return labels


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
    labels = label_phases(volume, values)
    totals = PhaseTotals(values.size + 1)
    for zs in iter_slabs(volume.shape):
        totals.counts += np.bincount(labels[zs].ravel(), minlength=NO_PHASE + 1)
    totals.check_nonempty(values, name)
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


class PhaseTotals:
    """Per-phase gray sums and voxel counts and the gray range of one state, block by block.

    ``add`` a block's grays with its labels, ``merge`` another's totals; :meth:`table` gives
    :func:`phase_table`'s rows and :meth:`check_nonempty` :func:`segment_phases`' check.
    """

    def __init__(self, n_phases: int) -> None:
        self.n = int(n_phases)
        self.sums = np.zeros(self.n)
        self.counts = np.zeros(NO_PHASE + 1, np.int64)
        self.low, self.high = np.inf, -np.inf

    def add(self, gray: np.ndarray, labels: np.ndarray) -> PhaseTotals:
        lab = np.asarray(labels).ravel()
        values = np.asarray(gray, dtype=np.float64).ravel()
        self.sums += np.bincount(lab, weights=values, minlength=self.n)[: self.n]
        self.counts += np.bincount(lab, minlength=NO_PHASE + 1)[: NO_PHASE + 1]
        finite = values[np.isfinite(values)]
        if finite.size:
            self.low = min(self.low, float(finite.min()))
            self.high = max(self.high, float(finite.max()))
        return self

    def merge(self, other: PhaseTotals) -> PhaseTotals:
        self.sums += other.sums
        self.counts += other.counts
        self.low, self.high = min(self.low, other.low), max(self.high, other.high)
        return self

    def check_nonempty(self, thresholds, name: str = "volume") -> None:
        """Raise ``ValueError`` naming the first phase with no voxel."""
        values = np.atleast_1d(np.asarray(thresholds, dtype=np.float64))
        empty = np.flatnonzero(self.counts[: values.size + 1] == 0)
        if empty.size:
            phase = int(empty[0])
            low = "-inf" if phase == 0 else f"{values[phase - 1]:g}"
            high = "+inf" if phase == values.size else f"{values[phase]:g}"
            raise ValueError(
                f"phase {phase} (gray {low} .. {high}) has no voxel in the {name}: move the "
                "thresholds or ask for fewer phases"
            )

    def table(self, thresholds) -> list[PhaseStats]:
        """Table 1 rows of this state (see :func:`phase_table`)."""
        values = np.atleast_1d(np.asarray(thresholds, dtype=np.float64))
        n = self.n
        counts = self.counts[:n]
        bounds = [self.low, *values.tolist(), self.high]
        total = max(1, int(counts.sum()))
        return [
            PhaseStats(
                phase=k,
                lower=float(bounds[k]),
                upper=float(bounds[k + 1]),
                mean_gray=float(self.sums[k] / counts[k]) if counts[k] else float("nan"),
                voxels=int(counts[k]),
                fraction=float(counts[k] / total),
            )
            for k in range(n)
        ]


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
    if labels.shape != volume.shape:
        raise ValueError(f"labels {labels.shape} and volume {volume.shape} differ in shape")
    totals = PhaseTotals(values.size + 1)
    for zs in iter_slabs(volume.shape):
        totals.add(volume[zs], labels[zs])
    return totals.table(values)
