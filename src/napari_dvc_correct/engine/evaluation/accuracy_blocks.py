"""The accuracy evaluation block by block: one code for in-memory slabs and out-of-core blocks.

:func:`.accuracy.evaluate_iter` walks the volume in z-slabs and
:mod:`napari_dvc_correct.tiled.evaluation` in 3-D blocks read from lazy volumes; both call
:func:`field_block` on every box of voxels and add what it returns into a
:class:`FieldAccumulator`, so they compute every number of an evaluation the same way:

- the mean residual: the float64 sum and the count of the finite residual voxels;
- the background residual (eq. 1): per-phase sums and counts where the two states' phases agree;
- the curves against strain (Figs. 10–11): residual sums and counts of every node's cell
  (:func:`.binning.cell_sums_block`);
- the local residual: residual sums and counts over every node's ``(2M + 1)^3`` box
  (:func:`.binning.node_box_sums_nested`, from an integral image of the block).

A block's node and cell sums cover only the sub-grid the block touches (:class:`GridPart`), so a
block's result stays small on a large grid. Whole-volume statistics that are not sums (the
multi-Otsu thresholds) are computed from a lattice subsample that blocks collect exactly
(:func:`.phases.lattice_sample`). Positions are ``(z, y, x)`` voxels, residuals gray levels.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..fields.field import DisplacementField
from ..fields.field_spline import FieldSpline
from ..fields.inverse_lattice import LatticeInverter
from ..fields.warp import (
    INVERSE_ACCURACY,
    INVERT_MAX_ITERATIONS,
    INVERT_TOLERANCE,
    box_shape,
    pull_back_block,
)
from ..slabs import iter_slabs
from .binning import GridPart, cell_sums_block, node_box_sums_nested
from .error_moments import MOMENTS, ErrorMoments, moment_volumes
from .gray_levels import GrayLevelMap
from .phase_sums import residual_phase_sums
from .phases import NO_PHASE, label_phases

Sampler = Callable[[np.ndarray], np.ndarray]


# --- background residual, eq. 1 ----------------------------------------------------------------
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
        Phases ``0 .. 254`` of the state the residual's voxels belong to (``G`` for the
        reference-frame residual ``|F(X + u) - G(X)|``); :data:`~.phases.NO_PHASE` (255) where
        undefined.
    labels_mapped : ndarray, shape (nz, ny, nx), integer
        Phases of the other state brought onto the same voxels by the field (phases of
        ``F(X + u(X))``), same convention.

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
    sums = np.zeros(NO_PHASE)
    counts = np.zeros(NO_PHASE, np.int64)
    n = 0  # phases present in the reference labels
    for zs in iter_slabs(residual.shape):
        r = np.asarray(residual[zs], dtype=np.float64)
        a = np.asarray(labels_reference[zs])
        defined = (a >= 0) & (a < NO_PHASE)
        if defined.any():
            n = max(n, int(a[defined].max()) + 1)
        keep = (a == np.asarray(labels_mapped[zs])) & defined & np.isfinite(r)
        sums += np.bincount(a[keep], weights=r[keep], minlength=NO_PHASE)
        counts += np.bincount(a[keep], minlength=NO_PHASE)
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


def gradient_components(block: np.ndarray) -> np.ndarray:
    """``grad g`` (gray levels per voxel, float32, shape ``(3, *block.shape)``, components
    ``(z, y, x)``) of a block by central differences (one-sided at the block's faces; 0 along an
    axis of length 1), NaN where a neighbour is undefined."""
    values = np.asarray(block, dtype=np.float32)
    out = np.zeros((3, *values.shape), np.float32)
    for axis in range(3):
        if values.shape[axis] >= 2:
            out[axis] = np.gradient(values, axis=axis)
    return out


def halo_gradient(
    read_region, box, shape, gray_levels=None, instrument: bool = False
) -> np.ndarray:
    """:func:`gradient_components` of the block ``box`` read with a one-voxel halo, so that any
    cutting of the volume into blocks gives the whole volume's central differences.

    ``read_region(slices)`` returns the voxels of a region of the state the residual lives on;
    ``gray_levels`` (a map, or None) is applied to them first (the loaded state, mapped). With
    ``instrument``, the block is read with a halo of
    :data:`.error_moments.INSTRUMENT_RADIUS` voxels and the result holds 6 components: the
    central differences, then the smoothed gradient (:func:`.error_moments.smoothed_gradient`),
    both the whole volume's.
    """
    from .error_moments import INSTRUMENT_RADIUS, smoothed_gradient

    reach = max(1, INSTRUMENT_RADIUS) if instrument else 1
    grown = tuple(
        slice(max(0, s.start - reach), min(int(n), s.stop + reach)) for s, n in zip(box, shape)
    )
    values = np.asarray(read_region(grown), dtype=np.float32)
    if gray_levels is not None:
        values = gray_levels.apply(values, grown)
    inner = tuple(slice(s.start - g.start, s.stop - g.start) for s, g in zip(box, grown))
    gradient = gradient_components(values)[(slice(None), *inner)]
    if not instrument:
        return gradient
    return np.concatenate([gradient, smoothed_gradient(values)[(slice(None), *inner)]])


# --- one block of one field -----------------------------------------------------------------------
@dataclass
class BlockTotals:
    """What one block adds to one field's evaluation (see :class:`FieldAccumulator`)."""

    residual_sum: float
    residual_count: int
    same_sums: np.ndarray  # (NO_PHASE,) float64: residual where both states' phases agree
    same_counts: np.ndarray  # (NO_PHASE,) int64
    max_label: int  # largest defined phase of the own state in the block (-1: none)
    cells: GridPart  # residual per node cell of the binning field's grid
    nodes: GridPart  # residual per node box of this field (local residual)
    error_nodes: GridPart | None = None  # residual per node window (the error estimate's region)
    moments: list | None = None  # per window half: GridPart per error_moments.MOMENTS


def field_block(
    own_block: np.ndarray,
    sample_other: Sampler,
    spline: FieldSpline,
    box,
    mode: str,
    thresholds_other,
    own_labels: np.ndarray | None,
    bin_field: DisplacementField,
    centers,
    half: int,
    gray_levels: GrayLevelMap | None = None,
    error_half: int | None = None,
    gradient: np.ndarray | None = None,
    region_block: np.ndarray | None = None,
) -> tuple[BlockTotals, np.ndarray, np.ndarray, np.ndarray]:
    """Moved volume, residual and mapped phases of one block, and its totals.

    With ``gray_levels`` (the pair's :class:`.gray_levels.GrayLevelMap`), the loaded scan's gray
    values are first brought into the reference's (``map(F~)`` in reference mode, ``map(F)`` in
    loaded mode), so the residual is ``|map(F~) - G|`` (or ``|map(F) - G'|``) in reference gray
    levels and the reference's thresholds phase both sides: ``thresholds_other`` must then be
    the reference's, and ``own_labels`` None in loaded mode (the phases of ``map(F)`` are
    computed here).

    Parameters
    ----------
    own_block : ndarray, shape box_shape(box)
        The state the residual lives on, read at ``box``: ``G`` (``mode="reference"``) or ``F``
        (``"loaded"``).
    sample_other : callable
        Tricubic B-spline sampler of the other state (positions ``(N, 3)`` -> float32, NaN
        outside): ``F`` in reference mode, ``G`` in loaded mode.
    spline : FieldSpline
        The evaluated field.
    box : tuple of 3 slices
        The block's voxels.
    mode : {"reference", "loaded"}
        ``|F(X + u(X)) - G(X)|`` (pull-back) or ``|F(x) - G'(x)|`` (forward warp, one inversion,
        whose reference positions also place the voxels in the binning cells).
    thresholds_other : ndarray
        Phase thresholds of the other state (for the mapped phases).
    own_labels : ndarray of uint8, shape box_shape(box), or None
        Phases of ``own_block`` (None: computed here with ``thresholds_other``, for a
        gray-level-mapped loaded state).
    bin_field : DisplacementField
        Whose grid's cells bin the residual (the field itself, or ``bin_by``'s).
    centers, half
        Node voxels of the field (:func:`node_voxels`) and the half-size of their regions.
    gray_levels : GrayLevelMap, optional
        The pair's gray-level map (None: the raw residual).
    error_half : int or tuple of int, optional
        Half-size of the boxes of the error estimate (:func:`.error_estimate.error_region_half`;
        default ``half``), or the half-sizes of its windows from the finest to the largest
        (:func:`.error_scales.window_ladder`): the moments are gathered over each, the
        mean residual over the largest.
    gradient : ndarray, shape (3 or 6, *box_shape(box)), optional
        ``grad own`` of the block, and its smoothed gradient (:func:`halo_gradient` with
        ``instrument``; default: from the block alone, one-sided at its faces), with the signed
        residual the error estimate's moments (:func:`.error_moments.moment_volumes`).
    region_block : ndarray of bool, shape box_shape(box), optional
        The specimen region at the block's voxels: outside it the residual is undefined (NaN)
        and takes no part in any number.

    Returns
    -------
    totals : BlockTotals
    moved, residual : ndarray, float32, NaN where undefined (outside the hull, outside the volume,
        inversion not converged)
    mapped : ndarray, uint8, phases of ``moved`` (:data:`~.phases.NO_PHASE` where undefined)
    """
    if mode == "reference":
        moved = pull_back_block(sample_other, spline, box, "nan")
        positions = None
    else:
        # the forward warp's inverse (coarse Newton, checked interpolation), anchored on
        # whole-volume indices: any cutting of the volume into boxes gives the same positions
        inverse = LatticeInverter(
            spline, box, INVERT_MAX_ITERATIONS, INVERT_TOLERANCE, INVERSE_ACCURACY
        ).solve()
        source = inverse.positions
        moved = np.asarray(sample_other(source), np.float32)
        moved[~inverse.converged] = np.nan
        moved[~inverse.in_hull] = np.nan
        moved = moved.reshape(box_shape(box))
        positions = source
    if gray_levels is not None and mode == "reference":
        moved = gray_levels.apply(moved, box)
    elif gray_levels is not None:
        own_block = gray_levels.apply(own_block, box)
    if region_block is not None:
        moved = np.where(region_block, moved, np.float32(np.nan)).astype(np.float32)
    if own_labels is None:
        own_labels = label_phases(own_block, thresholds_other)
    halves = (half,) if error_half is None else tuple(int(h) for h in np.atleast_1d(error_half))
    sums = residual_phase_sums(own_block, moved, own_labels, thresholds_other)
    residual = sums.residual
    # the node windows and the error estimate's (the same numbers as one call each, one pass)
    windows = (half,) if halves[-1] == half else (half, halves[-1])
    node_parts = node_box_sums_nested(residual, box, centers, windows)
    totals = BlockTotals(
        residual_sum=sums.residual_sum,
        residual_count=sums.residual_count,
        same_sums=sums.same_sums,
        same_counts=sums.same_counts,
        max_label=sums.max_label,
        cells=cell_sums_block(residual, box, bin_field, positions),
        nodes=node_parts[0],
        error_nodes=node_parts[-1],
        moments=[[] for _ in halves],
    )
    for volume in moment_volumes(
        np.where(np.isfinite(residual), moved - own_block, np.float32(np.nan)),
        own_block,
        gradient_components(own_block) if gradient is None else gradient,
    ):
        for parts, part in zip(totals.moments, node_box_sums_nested(volume, box, centers, halves)):
            parts.append(part)
    return totals, moved, residual, sums.mapped


class FieldAccumulator:
    """The totals of one field over all blocks; :meth:`result` gives the evaluation's numbers."""

    def __init__(self, field: DisplacementField, bin_field: DisplacementField, halves=None) -> None:
        self.field, self.bin_field = field, bin_field
        self.residual_sum, self.residual_count = 0.0, 0
        self.same_sums = np.zeros(NO_PHASE)
        self.same_counts = np.zeros(NO_PHASE, np.int64)
        self.max_label = -1
        self.cell_sums = np.zeros(bin_field.shape)
        self.cell_counts = np.zeros(bin_field.shape, np.int64)
        self.node_sums = np.zeros(field.shape)
        self.node_counts = np.zeros(field.shape, np.int64)
        # per window half (``halves``: field_block's ``error_half``; None: one window)
        self.halves = (None,) if halves is None else tuple(int(h) for h in np.atleast_1d(halves))
        self.moment_sums = np.zeros((len(self.halves), len(MOMENTS), *field.shape))
        self.moment_counts = np.zeros((len(self.halves), *field.shape), np.int64)
        self.error_sums = np.zeros(field.shape)
        self.error_counts = np.zeros(field.shape, np.int64)

    def add(self, block: BlockTotals) -> None:
        self.residual_sum += block.residual_sum
        self.residual_count += block.residual_count
        self.same_sums += block.same_sums
        self.same_counts += block.same_counts
        self.max_label = max(self.max_label, block.max_label)
        block.cells.add_to(self.cell_sums, self.cell_counts)
        block.nodes.add_to(self.node_sums, self.node_counts)
        if block.moments and len(block.moments) != len(self.moment_sums):
            raise ValueError(
                f"the block has moments over {len(block.moments)} windows, the accumulator "
                f"{len(self.moment_sums)}: give it the same error_half"
            )
        for sums, counts, parts in zip(self.moment_sums, self.moment_counts, block.moments or ()):
            for k, part in enumerate(parts):
                if k == 0:
                    part.add_to(sums[0], counts)
                elif part.sums.size:  # the same voxels: only the sums
                    where = tuple(
                        slice(int(a), int(a) + n) for a, n in zip(part.lo, part.sums.shape)
                    )
                    sums[k][where] += part.sums
        if block.error_nodes is not None:
            block.error_nodes.add_to(self.error_sums, self.error_counts)

    @property
    def mean_residual(self) -> float:
        count = self.residual_count
        return self.residual_sum / count if count else float("nan")

    def background(self) -> BackgroundResidual:
        """Eq. 1 from the same-phase sums (as :func:`.accuracy.background_residual`)."""
        total = int(self.same_counts.sum())
        if total == 0:
            raise ValueError(
                "no voxel holds the same phase in both states with a finite residual: the "
                "background residual is undefined (check the thresholds and the field)"
            )
        sums, counts = self.same_sums, self.same_counts
        per_phase = tuple(
            (k, float(sums[k] / counts[k]) if counts[k] else float("nan"), int(counts[k]))
            for k in range(self.max_label + 1)
        )
        return BackgroundResidual(mean=float(sums.sum() / total), voxels=total, per_phase=per_phase)

    def cell_residual(self) -> np.ndarray:
        """Mean residual over every node's window (the error estimate's region; NaN where it
        holds no finite voxel)."""
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(
                self.error_counts > 0, self.error_sums / np.maximum(self.error_counts, 1), np.nan
            )

    def error_moments(self) -> tuple[ErrorMoments, ...]:
        """Window means of the error estimate's moments (:class:`.error_moments.ErrorMoments`),
        one per window half, in field_block's ``error_half`` order."""
        return tuple(
            ErrorMoments.from_sums(sums, counts, half)
            for sums, counts, half in zip(self.moment_sums, self.moment_counts, self.halves)
        )

    def local_residual(self) -> np.ndarray:
        """Mean residual over every node's box (NaN where it holds no finite voxel)."""
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(
                self.node_counts > 0, self.node_sums / np.maximum(self.node_counts, 1), np.nan
            )


# --- one field's numbers from its totals ------------------------------------------------------
def field_partial(plan, index: int, totals: FieldAccumulator, residual, mapped):
    """One field's numbers that do not depend on ``r0`` or the contrast, from its totals.

    ``plan`` is the :class:`.accuracy.EvaluationPlan`, ``index`` the field's place in it;
    ``residual`` and ``mapped`` are the kept volumes (or None).
    """
    from .binning import bin_cells_by_strain

    name, item = plan.named[index]
    moments = totals.error_moments()
    return dict(
        name=name,
        field=item,
        equivalent_strain=plan.strains[index],
        mean_residual=totals.mean_residual,
        voxels=totals.residual_count,
        background=totals.background(),
        bins=bin_cells_by_strain(
            totals.cell_sums, totals.cell_counts, plan.bin_strains[index], plan.edges
        ),
        local_residual=totals.local_residual(),
        error_moments=moments,
        local_gradient=moments[-1].rms_gradient,
        cell_residual=totals.cell_residual(),
        residual=residual,
        labels_mapped=mapped,
    )
