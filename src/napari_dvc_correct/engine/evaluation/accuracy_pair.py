"""What an accuracy evaluation measures once per scan pair: the gray-level map and ``r0``.

The background residual ``r0`` of eq. 1 estimates the imaging noise, and the gray-level map
(:mod:`.gray_levels`) the brightness change between the scans: both belong to the pair of scans,
not to a field (the paper's Table 1 gives one per scan). A wrong field adds misplaced texture to
its same-phase residual and bends a map fitted through it, so both are measured with the *best
field available* on the pair: each candidate field (every field known on the pair, whichever of
them are evaluated) brings the loaded scan back (``F~ = F(X + u(X))``), a map is fitted through
it, and the candidate whose gray-level-corrected same-phase residual is smallest gives the pair's
map and ``r0``. Every field of the pair is then judged with that map and against that ``r0``, so
a field's numbers do not depend on which other fields are evaluated with it.

Residuals here are in the reference frame, ``|map(F~) - G|`` on reference voxels, in the
reference's gray levels; the reference's phase thresholds phase both sides.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..fields.field_spline import FieldSpline
from .accuracy_blocks import BackgroundResidual
from .gray_levels import (
    DEFAULT_CELL,
    CellSums,
    GrayLevelMap,
    block_sums,
    cells_shape,
    fit_from_passes,
    start_map,
)
from .gray_noise import noise_box, pair_noise, scan_noises
from .noise_correlation import NoiseCorrelation, measure_noise_correlation
from .phase_sums import residual_phase_sums
from .phases import otsu_stride

#: z-slab of the in-memory passes (voxels).
SLAB = 32


@dataclass(frozen=True)
class PairStatistics:
    """The scan pair's gray-level map and background residual.

    Attributes
    ----------
    gray_levels : GrayLevelMap
        ``G ≈ contrast(X) · F~ + offset(X)`` (identity when the evaluation is asked for the raw
        residual).
    background : BackgroundResidual
        ``r0`` of eq. 1 with that map, reference gray levels.
    measured_with : str
        Name of the field both were measured with.
    candidates : dict of str -> float
        Each candidate field's same-phase residual (the smallest was kept).
    noise_correlation : NoiseCorrelation or None
        The scans' noise correlation in space, measured on that field's residual
        (:mod:`.noise_correlation`; None: not measured, taken as white).
    """

    gray_levels: GrayLevelMap
    background: BackgroundResidual
    measured_with: str
    candidates: dict
    noise_correlation: NoiseCorrelation | None = None

    def noise_text(self) -> str:
        """The scans' noise correlation in words ("" where not measured)."""
        return "" if self.noise_correlation is None else self.noise_correlation.describe()

    def to_dict(self) -> dict:
        """JSON-ready (reports, layer metadata)."""
        out = {
            "background_residual": float(self.background.mean),
            "background_voxels": int(self.background.voxels),
            "measured_with": self.measured_with,
            "candidates": {k: float(v) for k, v in self.candidates.items()},
            "gray_levels": self.gray_levels.to_dict(),
        }
        if self.noise_correlation is not None:
            out["noise_correlation"] = self.noise_correlation.to_dict()
        return out


def background_from_sums(same_sums, same_counts, max_label) -> BackgroundResidual:
    count = int(np.sum(same_counts))
    if count == 0:
        return BackgroundResidual(float("inf"), 0, ())
    per_phase = tuple(
        (k, float(same_sums[k] / same_counts[k]) if same_counts[k] else np.nan, int(same_counts[k]))
        for k in range(max_label + 1)
    )
    return BackgroundResidual(float(np.sum(same_sums) / count), count, per_phase)


def pair_start_map(reference_sample, deformed_sample) -> GrayLevelMap:
    """The first guess of the map from lattice samples of ``G`` and ``F`` (the scans' own
    histograms: :func:`.gray_levels.start_map`), the same in memory and block by block."""
    return start_map(reference_sample, deformed_sample)


def lattice(volume) -> np.ndarray:
    """The lattice sample ``volume[::s, ::s, ::s]`` of multi-Otsu (:func:`.phases.otsu_stride`)."""
    stride = otsu_stride(np.shape(volume))
    return np.asarray(volume[::stride, ::stride, ::stride]).ravel()


def same_phase_block(reference_block, moved_block, labels_block, thresholds, gray, region):
    """Eq. 1's same-phase sums of one block: ``(sums, counts, max_label)`` of
    ``|gray(moved) - G|`` where both sides hold the same phase."""
    sums = residual_phase_sums(
        reference_block, gray.apply(moved_block, region), labels_block, thresholds
    )
    return sums.same_sums, sums.same_counts, sums.max_label


def choose_best(candidates: dict) -> PairStatistics:
    """The candidate (name -> (map, BackgroundResidual)) with the smallest ``r0``."""
    name = min(candidates, key=lambda k: candidates[k][1].mean)
    gray, background = candidates[name]
    if not np.isfinite(background.mean):
        raise ValueError(
            "no voxel holds the same phase in both states with a finite residual for any field: "
            "the background residual is undefined (check the thresholds and the fields)"
        )
    values = {k: float(v[1].mean) for k, v in candidates.items()}
    return PairStatistics(gray, background, name, values)


def residual_box(reference_box, moved_box, gray, box) -> np.ndarray:
    """``map(F~) − G`` on the block ``box`` (float64, NaN where undefined): what the noise
    correlation is measured on (:func:`with_noise_correlation`)."""
    moved = gray.apply(moved_box, box).astype(np.float64)
    return moved - np.asarray(reference_box, np.float64)


def with_noise_correlation(pair: PairStatistics, residuals: dict, reference_box, fields):
    """``pair`` with the scans' noise correlation measured on its best field's residual on the
    central block (``residuals[name]``: :func:`residual_box` on :func:`.gray_noise.noise_box`;
    ``fields[name]``: the field, for the pull-back's fractional parts)."""
    name = pair.measured_with
    correlation = measure_noise_correlation(
        residuals[name], reference_box, fields[name].displacement
    )
    return replace(pair, noise_correlation=correlation)


def _slabs(shape):
    for z0 in range(0, shape[0], SLAB):
        yield (slice(z0, min(z0 + SLAB, shape[0])), slice(0, shape[1]), slice(0, shape[2]))


def measure_pair(
    reference: np.ndarray,
    deformed: np.ndarray,
    candidates: dict,
    thresholds_moved,
    labels_reference: np.ndarray,
    *,
    fit_map: bool = True,
    gray_levels: GrayLevelMap | None = None,
    deformed_coefficients: np.ndarray | None = None,
    cell: int = DEFAULT_CELL,
    region: np.ndarray | None = None,
) -> PairStatistics:
    """The pair's map and ``r0``, measured with the best of ``candidates`` (see the module).

    Parameters
    ----------
    reference, deformed : ndarray, shape (nz, ny, nx)
        ``G`` and ``F``.
    candidates : dict of str -> DisplacementField
        The fields known on the pair (finite at every node).
    thresholds_moved : ndarray, shape (N - 1,)
        The thresholds that phase ``map(F~)``: the reference's with a map (both sides are then
        in its gray levels), the deformed scan's without.
    labels_reference : ndarray of uint8, shape (nz, ny, nx)
        The reference's phases.
    fit_map : bool
        Fit the gray-level map (False: the identity, the raw residual).
    gray_levels : GrayLevelMap, optional
        A map known already (then nothing is fitted: only ``r0`` is measured with it).
    deformed_coefficients : ndarray, optional
        ``interpolation.prefilter(F)``, to reuse.
    cell : int
        Cell of the local map (voxels), as :func:`.gray_levels.fit_gray_levels`.
    region : ndarray of bool, shape (nz, ny, nx), optional
        The specimen: the map and ``r0`` use only its voxels.

    Raises
    ------
    ValueError
        Without candidates, or when no candidate leaves a voxel of the same phase in both
        states.
    """
    from ..correlation.interpolation import prefilter
    from ..fields import warp
    from ..progress import run_to_completion

    if not candidates:
        raise ValueError("measuring the pair's background residual needs at least one field")
    coefficients = prefilter(deformed) if deformed_coefficients is None else deformed_coefficients
    shape = tuple(int(n) for n in reference.shape)
    start = pair_start_map(lattice(reference), lattice(deformed))
    noises = scan_noises(reference, deformed) if fit_map and gray_levels is None else None
    central = noise_box(shape)
    measured, residuals = {}, {}
    for name, field in candidates.items():
        moved = warp.pull_back(
            deformed,
            FieldSpline.from_field(field),
            coefficients=coefficients,
            cval=np.nan,
            outside="nan",  # inside the grid's hull, where the field was measured
        )
        if region is not None:
            moved[~region] = np.nan

        def sums_with(previous, moved=moved):
            total = CellSums.zeros(cells_shape(shape, cell))
            for box in _slabs(shape):
                total.add(block_sums(reference[box], moved[box], box, shape, cell, previous))
            return total
            yield

        if gray_levels is not None:
            gray = gray_levels
        elif fit_map:
            noise = pair_noise(*noises, field.displacement)
            gray = run_to_completion(fit_from_passes(sums_with, start, shape, cell, noise=noise))
        else:
            gray = GrayLevelMap.identity(shape)
        same_sums, same_counts, largest = 0.0, 0, -1
        for box in _slabs(shape):
            s, c, m = same_phase_block(
                reference[box], moved[box], labels_reference[box], thresholds_moved, gray, box
            )
            same_sums, same_counts, largest = same_sums + s, same_counts + c, max(largest, m)
        measured[str(name)] = (gray, background_from_sums(same_sums, same_counts, largest))
        residuals[str(name)] = residual_box(reference[central], moved[central], gray, central)
    fields = {str(k): v for k, v in candidates.items()}
    return with_noise_correlation(choose_best(measured), residuals, reference[central], fields)
