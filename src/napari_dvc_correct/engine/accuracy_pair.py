"""What an accuracy evaluation measures once per scan pair: the gray-level map and ``r0`` (issue 26).

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

from dataclasses import dataclass

import numpy as np

from .accuracy_blocks import BackgroundResidual
from .field_spline import FieldSpline
from .gray_levels import GrayLevelMap, fit_gray_levels
from .phase_sums import residual_phase_sums


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
    """

    gray_levels: GrayLevelMap
    background: BackgroundResidual
    measured_with: str
    candidates: dict

    def to_dict(self) -> dict:
        """JSON-ready (reports, layer metadata)."""
        return {
            "background_residual": float(self.background.mean),
            "background_voxels": int(self.background.voxels),
            "measured_with": self.measured_with,
            "candidates": {k: float(v) for k, v in self.candidates.items()},
            "gray_levels": self.gray_levels.to_dict(),
        }


def _background(sums) -> BackgroundResidual:
    count = int(sums.same_counts.sum())
    if count == 0:
        return BackgroundResidual(float("inf"), 0, ())
    per_phase = tuple(
        (
            k,
            float(sums.same_sums[k] / sums.same_counts[k]) if sums.same_counts[k] else np.nan,
            int(sums.same_counts[k]),
        )
        for k in range(sums.max_label + 1)
    )
    return BackgroundResidual(float(sums.same_sums.sum() / count), count, per_phase)


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

    Raises
    ------
    ValueError
        Without candidates, or when no candidate leaves a voxel of the same phase in both
        states.
    """
    from . import warp
    from .interpolation import prefilter

    if not candidates:
        raise ValueError("measuring the pair's background residual needs at least one field")
    coefficients = prefilter(deformed) if deformed_coefficients is None else deformed_coefficients
    best = None
    values = {}
    for name, field in candidates.items():
        moved = warp.pull_back(
            deformed,
            FieldSpline.from_field(field),
            coefficients=coefficients,
            cval=np.nan,
            outside="nan",  # inside the grid's hull, where the field was measured
        )
        if gray_levels is not None:
            gray = gray_levels
        elif fit_map:
            gray = fit_gray_levels(reference, moved)
        else:
            gray = GrayLevelMap.identity(reference.shape)
        sums = residual_phase_sums(reference, gray.apply(moved), labels_reference, thresholds_moved)
        background = _background(sums)
        values[str(name)] = background.mean
        if best is None or background.mean < best[1].mean:
            best = (gray, background, str(name))
    if not np.isfinite(best[1].mean):
        raise ValueError(
            "no voxel holds the same phase in both states with a finite residual for any field: "
            "the background residual is undefined (check the thresholds and the fields)"
        )
    return PairStatistics(best[0], best[1], best[2], values)
