"""How a correcting match becomes the corrected field: the update (the sum or the composition of paper step f), where
each node reads its correction, and the quality arrays the corrected nodes carry."""

from __future__ import annotations

import numpy as np

from ..fields.compose import compose
from ..fields.field import GOOD_STATUSES, DisplacementField, Provenance


def updated_field(current: DisplacementField, delta: DisplacementField, frame: str, update: str):
    if update == "sum":
        return compose(current, delta, mode="sum")
    if frame == "reference":
        return compose(delta, current)
    return compose(current, delta)


def zero_start(grid) -> DisplacementField:
    """The zero start of a correcting DVC on ``grid`` (origin, step, shape)."""
    zero = DisplacementField.zeros(*grid)
    zero.gradient = np.zeros((*grid[2], 3, 3))
    return zero


def update_read_points(current: DisplacementField, frame: str, update: str) -> np.ndarray:
    """Where each node's update reads ``ΔD``: ``X + D(X)`` (loaded frame, exact), else ``X``."""
    if frame == "loaded" and update == "exact":
        return current.points + current.u.reshape(-1, 3)
    return current.points


def good_nodes(field: DisplacementField) -> np.ndarray:
    return np.isin(field.status, [int(s) for s in GOOD_STATUSES])


def nearest_match(delta: DisplacementField, read_points: np.ndarray, shape) -> tuple:
    """Index into ``delta``'s grid of the node nearest to each read point (``shape``: the
    corrected field's grid)."""
    index = np.rint((read_points - np.asarray(delta.origin)) / np.asarray(delta.step))
    index = np.nan_to_num(index, nan=0.0)
    return tuple(
        np.clip(index[:, a], 0, delta.shape[a] - 1).astype(np.intp).reshape(shape) for a in range(3)
    )


def correction_sigma(delta: DisplacementField, read_points: np.ndarray, shape) -> np.ndarray:
    """Uncertainty (voxels, norm over the 3 components) of each node's correcting match; NaN
    where unknown (an interpolated match, or a field without uncertainties)."""
    if delta.uncertainty is None:
        return np.full(shape, np.nan)
    return np.linalg.norm(delta.uncertainty[nearest_match(delta, read_points, shape)], axis=-1)


def finish_pass(
    candidate: DisplacementField,
    delta: DisplacementField,
    input_field: DisplacementField,
    masked: np.ndarray,
    read_points: np.ndarray,
) -> DisplacementField:
    """Quality arrays of a corrected field: those of the correcting match; masked nodes kept.

    A node's correcting match is the node of ``delta`` nearest to where its update reads ``ΔD``
    (``read_points``: its displaced position in the loaded frame, itself otherwise). Nodes where
    that match failed or was masked (its value interpolated from the neighbours' by the
    cleaning) are ``REPLACED``, the others ``CORRECTED``. A corrected node's uncertainty is
    its correcting match's (NaN where ``REPLACED``).
    """
    nearest = nearest_match(delta, read_points, candidate.shape)
    candidate.zncc = delta.zncc[nearest].copy()
    candidate.status = delta.status[nearest].copy()
    candidate.iterations = delta.iterations[nearest].copy()
    candidate.provenance = np.full(candidate.shape, Provenance.CORRECTED, np.uint8)
    interpolated = np.isin(delta.provenance[nearest], [Provenance.REPLACED, Provenance.MASKED])
    candidate.provenance[interpolated] = Provenance.REPLACED
    candidate.provenance[masked] = Provenance.MASKED
    candidate.status[masked] = input_field.status[masked]
    if delta.uncertainty is not None:
        # a correcting match re-measures the node on the same images: its noise replaces the
        # node's, it does not add to it (the composition's quadrature sum is for independent
        # increments); an interpolated match measured nothing
        uncertainty = delta.uncertainty[nearest].copy()
        uncertainty[interpolated] = np.nan
        if input_field.uncertainty is not None:
            uncertainty[masked] = input_field.uncertainty[masked]
        candidate.uncertainty = uncertainty
    return candidate
