"""One check of a (pair, field, mask) before any work, shared by every command that takes them.

Every function raises :class:`ValueError` with a one-line message that says what to change, and
returns nothing. Pure numpy: no io, so the engine and the commands can both call it.
"""

from __future__ import annotations

import numpy as np

from .correlation.params import MIN_SUBVOLUME
from .validation import validate_volume


def largest_subvolume_advice(volume_shape) -> str:
    """What to say when a subvolume does not fit a volume of ``volume_shape``."""
    smallest = min(int(n) for n in volume_shape)
    if smallest < MIN_SUBVOLUME:
        return (
            f"the volume is too thin for DVC: every axis needs at least {MIN_SUBVOLUME} voxels "
            f"(the smallest subvolume), it has {smallest}"
        )
    return f"use a subvolume of at most {smallest - (1 - smallest % 2)}"


def _all_finite(volume: np.ndarray) -> bool:
    if volume.dtype.kind not in "fc":
        return True
    slab = max(1, int(2**24 // max(1, volume.shape[1] * volume.shape[2])))
    return all(
        np.all(np.isfinite(volume[start : start + slab]))
        for start in range(0, volume.shape[0], slab)
    )


def check_volume(volume, name: str, check_finite: bool = True) -> np.ndarray:
    """A non-empty 3-D real volume with finite values (:func:`~.validation.validate_volume`)."""
    return validate_volume(volume, name, check_finite=check_finite)


def check_pair(reference, deformed, mask=None, check_finite: bool = True) -> None:
    """Both volumes 3-D, finite and of one shape; the mask (if any) of that shape, finite, not empty.

    A NaN in a mask would count as material (``NaN != 0``), so it is refused, not guessed.
    ``check_finite=False`` skips the pass over the volumes' values (for volumes the readers have
    checked already); the mask is always checked.
    """
    reference = check_volume(reference, "reference volume", check_finite)
    deformed = check_volume(deformed, "deformed volume", check_finite)
    if reference.shape != deformed.shape:
        raise ValueError(
            f"reference {reference.shape} and deformed {deformed.shape} volumes must have the "
            "same shape"
        )
    if mask is not None:
        mask = np.asanyarray(mask)
        if mask.shape != reference.shape:
            raise ValueError(f"mask shape {mask.shape} differs from the volume {reference.shape}")
        if not _all_finite(mask):
            raise ValueError(
                "the mask contains NaN or infinite values: use 0 = outside, 1 = material"
            )
        if not np.any(mask):
            raise ValueError("the mask is empty: no voxel is selected")


def absurd_nodes(field, volume_shape) -> np.ndarray:
    """The usable nodes (or points) whose displacement no match in this volume can give.

    Parameters
    ----------
    field : DisplacementField or ScatteredField
        Its ``u`` is ``(..., 3)`` in voxels, ``(uz, uy, ux)``; its ``status`` and
        ``valid`` says which values are usable (:func:`~.field.usable_nodes`).
    volume_shape : tuple of 3 int
        Shape ``(nz, ny, nx)`` of the reference volume, voxels.

    Returns
    -------
    ndarray of bool, the shape of ``field.status``
        True where a usable node's displacement along an axis is larger than the volume along
        that axis (it maps outside the volume): a diverged match written as converged (spam's
        ``ldic`` leaves a few such nodes at 10^3-10^6 voxels), or a field of another pair.
    """
    u = np.asarray(field.u, dtype=np.float64)
    usable = np.asarray(field.valid)
    limit = np.asarray([int(n) for n in volume_shape], dtype=np.float64)
    with np.errstate(invalid="ignore"):
        beyond = np.any(np.abs(u) > limit, axis=-1)
    return usable & beyond


def absurd_message(name: str, field, absurd: np.ndarray, volume_shape) -> str:
    """One line: the largest absurd displacement, its axis, and how many nodes are absurd."""
    usable = np.asarray(field.valid)
    largest = np.abs(np.asarray(field.u)[absurd]).max(axis=0)
    axis = int(np.argmax(largest / np.asarray(volume_shape, dtype=np.float64)))
    return (
        f"{name} has displacements up to {largest[axis]:.3g} voxels along {'zyx'[axis]}, larger "
        f"than the volume ({int(volume_shape[axis])} voxels), at {int(absurd.sum())} of "
        f"{int(usable.sum())} usable nodes"
    )


def check_search_radius(params, volume_shape, available_bytes: int | None = None) -> None:
    """A search radius that fits the volume and the memory, checked before any work.

    Parameters
    ----------
    params : CorrelationParams
        Its ``effective_search_radius`` (voxels) and ``subvolume`` (voxels).
    volume_shape : tuple of 3 int
        Shape ``(nz, ny, nx)`` of the volumes, voxels.
    available_bytes : int, optional
        Memory the search may use; None skips that check.

    Raises
    ------
    ValueError
        If a radius given (``search_radius``) is larger than the volume's largest edge (no
        displacement in this pair is that large), or one POI's search window needs more than
        ``available_bytes``.
    """
    from .correlation.pyramid_rule import search_window_bytes

    radius = int(params.effective_search_radius)
    largest = max(int(n) for n in volume_shape)
    if params.search_radius is not None and radius > largest:  # the default adapts
        raise ValueError(
            f"search radius {radius} voxels is larger than the volume {tuple(volume_shape)}: no "
            f"displacement of this pair is that large; use a search radius of at most {largest}"
        )
    need = search_window_bytes(params, volume_shape)
    if available_bytes is not None and need > available_bytes:
        raise ValueError(
            f"search radius {radius} voxels needs about {need / 2**30:.1f} GiB for one "
            f"subvolume's search window, {available_bytes / 2**30:.1f} GiB are available: use a "
            "smaller search radius (or a subvolume of 19 or more, searched coarse to fine)"
        )


def check_field_on_volume(field, volume_shape, name: str = "the field") -> None:
    """The field belongs to volumes of ``volume_shape``: recorded shape, grid inside, plausible |u|.

    Parameters
    ----------
    field : DisplacementField
    volume_shape : tuple of 3 int
        Shape ``(nz, ny, nx)`` of the reference volume, voxels.
    name : str
        How the message names the field (e.g. ``"field 'corrected'"``).

    Raises
    ------
    ValueError
        If ``field.metadata["volume_shape"]`` is recorded and differs; if a node lies outside
        the volume (more than half a voxel); or if most usable nodes (more than half) are
        displaced by more than the volume along an axis (:func:`absurd_nodes`: the field is not
        from this pair, or is in other units). A few such nodes are not refused: they are failed
        matches, which :func:`.absurd_nodes.flag_absurd_nodes` marks as failed for cleaning to replace.
    """
    volume_shape = tuple(int(n) for n in volume_shape)
    recorded = field.metadata.get("volume_shape")
    if recorded is not None and tuple(int(n) for n in recorded) != volume_shape:
        raise ValueError(
            f"{name} was measured on volumes of shape {tuple(int(n) for n in recorded)}, not "
            f"{volume_shape}: give the volumes it came from"
        )
    for axis, (coords, n) in enumerate(zip(field.axis_coordinates(), volume_shape)):
        if coords[0] < -0.5 or coords[-1] > n - 0.5:
            raise ValueError(
                f"{name}: its grid does not fit the volume: along axis {'zyx'[axis]} its nodes span "
                f"{coords[0]:g}..{coords[-1]:g} voxels but the volume has {n} voxels "
                f"(0..{n - 1}); was the field computed on another volume?"
            )
    check_mostly_plausible(field, volume_shape, name)


def check_mostly_plausible(field, volume_shape, name: str = "the field") -> None:
    """Refuse a field (grid or points) whose usable nodes are mostly :func:`absurd_nodes`.

    Raises
    ------
    ValueError
        If more than half of the usable nodes are displaced by more than the volume along an
        axis: it is not a field of this pair (or not in voxels).
    """
    volume_shape = tuple(int(n) for n in volume_shape)
    absurd = absurd_nodes(field, volume_shape)
    usable = int(np.asarray(field.valid).sum())
    if absurd.any() and 2 * int(absurd.sum()) > usable:
        raise ValueError(
            absurd_message(name, field, absurd, volume_shape)
            + ": it is not a field of this pair (or not in voxels)"
        )


def check_pair_and_fields(
    reference, deformed, fields, mask=None, check_finite: bool = True
) -> None:
    """:func:`check_pair`, then :func:`check_field_on_volume` for every field.

    ``fields`` is one :class:`~.field.DisplacementField` or a dict of name -> field.
    """
    check_pair(reference, deformed, mask, check_finite)
    items = fields.items() if isinstance(fields, dict) else [("", fields)]
    shape = np.shape(reference)
    for key, field in items:
        check_field_on_volume(field, shape, f"field {key!r}" if key else "the field")
