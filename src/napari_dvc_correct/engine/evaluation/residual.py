"""Gray residuals: how well a displacement field explains the pair (paper eqs. 1-2).

``r(X) = |F(X + u(X)) - G(X)|`` at every reference voxel (the pull-back, no inversion), or the
paper's ``r(x) = |F(x) - G'(x)|`` at every voxel of the loaded state (the forward warp of
:mod:`.warp`). :func:`gray_residual` gives the volume, :func:`mean_gray_residual` its mean without
building it, and :func:`moved_and_residual` the moved volume with its residual from one warp (what
the accuracy evaluation needs). Volumes are sampled with the tricubic B-spline of
:mod:`.interpolation`; positions are ``(z, y, x)`` voxels, residuals gray levels.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from ..fields.field import DisplacementField
from ..fields.field_spline import DEFAULT_CHUNK_VOXELS, FieldSpline, as_field_spline
from ..fields.warp import (
    coefficients_of,
    pull_back_block,
    slab_boxes,
    spline_sampler,
    warp_forward_block,
)

MODES = ("reference", "loaded")
REGIONS = ("hull", "volume")


def _iter_moved(
    reference,
    deformed,
    field,
    mode: str,
    region: str,
    coefficients: tuple,
    chunk_voxels: int,
) -> Iterator[tuple[slice, np.ndarray, np.ndarray]]:
    """Yield ``(z, moved, residual)`` slab by slab; NaN where undefined (see :func:`gray_residual`)."""
    if mode not in MODES:
        raise ValueError(f"mode must be 'reference' or 'loaded', got {mode!r}")
    if region not in REGIONS:
        raise ValueError(f"region must be 'hull' or 'volume', got {region!r}")
    reference = np.asanyarray(reference)
    deformed = np.asanyarray(deformed)
    for name, volume in (("reference", reference), ("deformed", deformed)):
        if volume.ndim != 3:
            raise ValueError(f"{name} must be a 3-D volume (z, y, x), got shape {volume.shape}")
    spline = as_field_spline(field)
    reference_coefficients, deformed_coefficients = coefficients
    if mode == "reference":
        sampler = spline_sampler(coefficients_of(deformed, deformed_coefficients, "deformed"))
        outside = "nan" if region == "hull" else "extrapolate"
        for z, box in slab_boxes(reference.shape, chunk_voxels):
            moved = pull_back_block(sampler, spline, box, outside)
            yield z, moved, np.abs(moved - reference[z].astype(np.float32))
    else:
        sampler = spline_sampler(coefficients_of(reference, reference_coefficients, "reference"))
        # one box: the inverse's coarse stage runs once, its positions slab by slab
        whole = tuple(slice(0, int(n)) for n in deformed.shape)
        moved_all, in_hull_all = warp_forward_block(
            sampler, spline, whole, chunk_voxels=chunk_voxels
        )
        for z, _ in slab_boxes(deformed.shape, chunk_voxels):
            moved, in_hull = moved_all[z], in_hull_all[z]
            if region == "hull":
                moved[~in_hull] = np.nan
            yield z, moved, np.abs(deformed[z].astype(np.float32) - moved)


def moved_and_residual(
    reference: np.ndarray,
    deformed: np.ndarray,
    field: DisplacementField | FieldSpline,
    mode: str = "reference",
    *,
    region: str = "hull",
    reference_coefficients: np.ndarray | None = None,
    deformed_coefficients: np.ndarray | None = None,
    chunk_voxels: int = DEFAULT_CHUNK_VOXELS,
) -> tuple[np.ndarray, np.ndarray]:
    """The moved volume and the gray residual volume from one warp.

    ``mode="reference"``: ``(F~, |F~ - G|)`` with ``F~(X) = F(X + u(X))`` on the reference's
    lattice; ``mode="loaded"``: ``(G', |F - G'|)`` with the forward warp ``G'`` on the deformed
    volume's lattice. Both float32, NaN where undefined (as :func:`gray_residual`). Equal to
    :func:`.warp.pull_back` / :func:`.warp.warp_forward` with ``outside="nan"`` (for
    ``region="hull"``) and :func:`gray_residual`, at the cost of one of them.
    """
    coefficients = (reference_coefficients, deformed_coefficients)
    shape = np.shape(reference) if mode == "reference" else np.shape(deformed)
    moved = np.empty(shape, np.float32)
    residual = np.empty(shape, np.float32)
    for z, moved_block, residual_block in _iter_moved(
        reference, deformed, field, mode, region, coefficients, chunk_voxels
    ):
        moved[z] = moved_block
        residual[z] = residual_block
    return moved, residual


def gray_residual(
    reference: np.ndarray,
    deformed: np.ndarray,
    field: DisplacementField | FieldSpline,
    mode: str = "reference",
    *,
    region: str = "hull",
    reference_coefficients: np.ndarray | None = None,
    deformed_coefficients: np.ndarray | None = None,
    chunk_voxels: int = DEFAULT_CHUNK_VOXELS,
) -> np.ndarray:
    """Gray residual volume of a displacement field (the paper's residual maps).

    Parameters
    ----------
    reference : ndarray, shape (nz, ny, nx)
        ``G``, the undeformed volume (any real dtype).
    deformed : ndarray, shape (nz, ny, nx)
        ``F``, the deformed volume.
    field : DisplacementField or FieldSpline
        Lagrangian displacement ``u(X)`` in voxels on a grid; nodes must be finite (clean it
        first). It is densified by cubic splines (:func:`.field_spline.densify`).
    mode : {"reference", "loaded"}
        ``"reference"``: ``r(X) = |F(X + u(X)) - G(X)|`` at every reference voxel ``X``
        (pull-back, no inversion; the residual volume has the reference's shape).
        ``"loaded"``: the paper's ``r(x) = |F(x) - G'(x)|`` at every voxel ``x`` of the loaded
        state, with ``G'`` the forward warp of ``G`` (:func:`.warp.warp_forward`; has the deformed
        volume's shape).
    region : {"hull", "volume"}
        ``"hull"`` (default): the residual is defined only where the reference position lies in
        the box spanned by the grid nodes (where the field was measured); ``"volume"``:
        everywhere, with the field extrapolated beyond the hull.
    reference_coefficients, deformed_coefficients : ndarray, optional
        ``interpolation.prefilter`` of the volumes, to reuse across calls.
    chunk_voxels : int
        Voxels processed at a time (memory stays at a few arrays of this size).

    Returns
    -------
    ndarray, float32, gray levels
        NaN where undefined: outside the hull (``region="hull"``), where the displaced position
        falls outside the other volume, or where the inverse map did not converge.

    See Also
    --------
    mean_gray_residual : the mean without building the volume.
    """
    reference = np.asanyarray(reference)
    deformed = np.asanyarray(deformed)
    coefficients = (reference_coefficients, deformed_coefficients)
    shape = reference.shape if mode == "reference" else deformed.shape
    result = np.empty(shape, np.float32)
    for z, _, block in _iter_moved(
        reference, deformed, field, mode, region, coefficients, chunk_voxels
    ):
        result[z] = block
    return result


def mean_gray_residual(
    reference: np.ndarray,
    deformed: np.ndarray,
    field: DisplacementField | FieldSpline,
    mode: str = "reference",
    *,
    region: str = "hull",
    reference_coefficients: np.ndarray | None = None,
    deformed_coefficients: np.ndarray | None = None,
    chunk_voxels: int = DEFAULT_CHUNK_VOXELS,
) -> float:
    """Mean of :func:`gray_residual` over the voxels where it is defined (gray levels).

    Computed slab by slab (never holds the residual volume). Returns NaN if it is defined nowhere.
    """
    coefficients = (reference_coefficients, deformed_coefficients)
    total = 0.0
    count = 0
    for _, _, block in _iter_moved(
        reference, deformed, field, mode, region, coefficients, chunk_voxels
    ):
        finite = np.isfinite(block)
        total += float(np.sum(block[finite], dtype=np.float64))
        count += int(finite.sum())
    return total / count if count else float("nan")
