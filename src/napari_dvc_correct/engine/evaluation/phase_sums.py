"""The gray residual with eq. 1's same-phase sums in one pass over the voxels.

``r = |own - moved|`` (gray levels, float32, NaN where ``moved`` is undefined), the phases of
``moved`` from the other state's thresholds (:func:`.phases.label_phases`' convention:
``thresholds[k-1] <= value < thresholds[k]`` is phase ``k``, :data:`~.phases.NO_PHASE` where not
finite), and per phase of ``own`` the sum and count of the finite residual where both phases
agree: the numbers the background residual of the paper's eq. 1 needs
(:func:`.accuracy_blocks.background_residual`), without the float64 copies, digitising and
bincounts of the volume that computing them one by one makes. Arrays are ``(nz, ny, nx)``.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit, prange

from .._numba_setup import KERNEL_OPTIONS
from .phases import NO_PHASE


class ResidualPhaseSums(NamedTuple):
    """What :func:`residual_phase_sums` returns.

    Attributes
    ----------
    residual : ndarray, float32
        ``|own - moved|``, NaN where either is not finite.
    mapped : ndarray, uint8
        Phases of ``moved`` (:data:`~.phases.NO_PHASE` where not finite).
    same_sums : ndarray (NO_PHASE,) float64
        Per phase of ``own``: the sum of the finite residual where ``mapped`` is that phase too.
    same_counts : ndarray (NO_PHASE,) int64
        The voxels of those sums.
    residual_sum : float
        Sum of the finite residual (float64), over all voxels.
    residual_count : int
        Its voxels.
    max_label : int
        Largest defined phase in ``own_labels`` (-1: none).
    """

    residual: np.ndarray
    mapped: np.ndarray
    same_sums: np.ndarray
    same_counts: np.ndarray
    residual_sum: float
    residual_count: int
    max_label: int

    @property
    def same_phase_mean(self) -> float:
        """Eq. 1's pooled background residual ``r0`` of these voxels (NaN if no voxel agrees)."""
        count = int(self.same_counts.sum())
        return float(self.same_sums.sum() / count) if count else float("nan")


@njit(parallel=True, **KERNEL_OPTIONS)
def _residual_phase_planes(own, moved, own_labels, thresholds, residual, mapped, sums, counts):
    """Per z-plane: residual, mapped phases, same-phase sums and counts (rows of ``sums`` /
    ``counts``), the finite residual's sum and count and the largest own phase (last columns)."""
    nz, ny, nx = own.shape
    n_thresholds = thresholds.shape[0]
    for iz in prange(nz):
        total = 0.0
        finite = 0
        largest = -1
        for iy in range(ny):
            for ix in range(nx):
                value = moved[iz, iy, ix]
                r = np.float32(abs(np.float32(own[iz, iy, ix]) - value))
                residual[iz, iy, ix] = r
                label = NO_PHASE
                if np.isfinite(value):
                    label = 0
                    for k in range(n_thresholds):
                        if value >= thresholds[k]:
                            label = k + 1
                mapped[iz, iy, ix] = label
                own_label = own_labels[iz, iy, ix]
                if own_label < NO_PHASE and own_label > largest:
                    largest = own_label
                if np.isfinite(r):
                    total += r
                    finite += 1
                    if own_label == label and own_label < NO_PHASE:
                        sums[iz, own_label] += r
                        counts[iz, own_label] += 1
        sums[iz, NO_PHASE] = total
        counts[iz, NO_PHASE] = finite
        counts[iz, NO_PHASE + 1] = largest


def residual_phase_sums(own, moved, own_labels, thresholds_moved) -> ResidualPhaseSums:
    """Residual, phases of ``moved`` and eq. 1's same-phase sums in one pass.

    Parameters
    ----------
    own : ndarray, shape (nz, ny, nx)
        The state the residual lives on (``G`` for ``|F(X + u(X)) - G(X)|``), any real dtype.
    moved : ndarray of float32, same shape
        The other state brought onto ``own``'s voxels, NaN where undefined.
    own_labels : ndarray of uint8, same shape
        Phases of ``own`` (:func:`.phases.label_phases`).
    thresholds_moved : sequence of float
        Increasing phase thresholds of the other state.
    """
    rows = PhaseRows(np.shape(own)[0] if np.ndim(own) == 3 else 0)
    planes = slice(0, rows.sums.shape[0])
    residual, mapped = rows.add(planes, own, moved, own_labels, thresholds_moved)
    return rows.total(residual, mapped)


class PhaseRows:
    """The per-plane sums of :func:`residual_phase_sums` for a volume given slab by slab along
    z: each :meth:`add` fills its planes' rows, :meth:`total` adds the rows up as
    :func:`residual_phase_sums` does, so the same numbers come out to the bit whatever the slabs,
    without the whole volume's residual."""

    def __init__(self, nz: int) -> None:
        self.sums = np.zeros((int(nz), NO_PHASE + 1))
        self.counts = np.zeros((int(nz), NO_PHASE + 2), np.int64)

    def add(self, zs: slice, own, moved, own_labels, thresholds_moved):
        """The planes ``zs`` (arrays of the slab's shape, as :func:`residual_phase_sums`'s);
        returns their ``(residual, mapped)``."""
        own = np.asarray(own)
        moved = np.ascontiguousarray(moved, dtype=np.float32)
        own_labels = np.asarray(own_labels, dtype=np.uint8)
        if not (own.shape == moved.shape == own_labels.shape) or own.ndim != 3:
            raise ValueError(
                f"own {own.shape}, moved {moved.shape} and labels {own_labels.shape} must be the "
                "same 3-D shape"
            )
        if zs.stop - zs.start != own.shape[0]:
            raise ValueError(f"planes {zs} do not match the slab's {own.shape[0]} planes")
        thresholds = np.atleast_1d(np.asarray(thresholds_moved, dtype=np.float64))
        residual = np.empty(own.shape, np.float32)
        mapped = np.empty(own.shape, np.uint8)
        _residual_phase_planes(
            own, moved, own_labels, thresholds, residual, mapped, self.sums[zs], self.counts[zs]
        )
        return residual, mapped

    def total(self, residual=None, mapped=None) -> ResidualPhaseSums:
        """The sums over every plane added (``residual`` and ``mapped``: what to return as the
        volume's, if held)."""
        sums, counts = self.sums, self.counts
        return ResidualPhaseSums(
            residual=residual,
            mapped=mapped,
            same_sums=sums[:, :NO_PHASE].sum(axis=0),
            same_counts=counts[:, :NO_PHASE].sum(axis=0),
            residual_sum=float(sums[:, NO_PHASE].sum()),
            residual_count=int(counts[:, NO_PHASE].sum()),
            max_label=int(counts[:, NO_PHASE + 1].max()) if len(counts) else -1,
        )
