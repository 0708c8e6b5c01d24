"""Diverged matches in a field: nodes displaced by more than the volume, marked as failed.

Other tools write a few diverged matches as converged (spam's ``ldic`` leaves nodes at 10^3-10^6
voxels); such a node is what the self-correction is for, so it is flagged as a failed match for
cleaning to replace, not a reason to refuse the field. A field mostly made of them belongs to
another pair (or is not in voxels) and is refused (:func:`.pair_checks.check_mostly_plausible`).
"""

from __future__ import annotations

import numpy as np

from ..pair_checks import absurd_message, absurd_nodes, check_mostly_plausible
from .field import Provenance, Status


def flag_absurd_nodes(field, volume_shape, name: str = "the field"):
    """Mark a minority of absurd nodes as failed matches, so cleaning replaces them.

    Parameters
    ----------
    field : DisplacementField or ScatteredField
        A field in voxels, ``u`` in ``(uz, uy, ux)`` order.
    volume_shape : tuple of 3 int
        Shape ``(nz, ny, nx)`` of the reference volume, voxels.
    name : str
        How messages name the field.

    Returns
    -------
    field : DisplacementField or ScatteredField
        ``field`` itself when no node is absurd; else a copy in which every
        :func:`absurd_nodes` node has ``Status.DIVERGED``, ``Provenance.MEASURED`` and NaN
        displacement, gradient and uncertainty, with ``metadata["absurd_nodes"]`` = the count.
    note : str or None
        One line saying what was done (None when nothing was).

    Raises
    ------
    ValueError
        If most usable nodes are absurd (:func:`check_mostly_plausible`).
    """
    check_mostly_plausible(field, volume_shape, name)
    absurd = absurd_nodes(field, volume_shape)
    if not absurd.any():
        return field, None
    note = (
        absurd_message(name, field, absurd, volume_shape)
        + ": treated as failed matches (cleaned, then corrected)"
    )
    flagged = field.copy()
    flagged.u = np.array(flagged.u, dtype=np.float64)
    flagged.u[absurd] = np.nan
    flagged.status = np.array(flagged.status)
    flagged.status[absurd] = int(Status.DIVERGED)
    flagged.provenance = np.array(flagged.provenance)
    flagged.provenance[absurd] = int(Provenance.MEASURED)
    for attribute in ("gradient", "uncertainty"):
        value = getattr(flagged, attribute, None)
        if value is not None:
            value = np.array(value, dtype=np.float64)
            value[absurd] = np.nan
            setattr(flagged, attribute, value)
    flagged.metadata["absurd_nodes"] = int(absurd.sum())
    return flagged, note
