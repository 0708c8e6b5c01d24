"""Volumes warped by a displacement field (paper step d, and the self-correction's pull-back).

* :func:`pull_back` resamples the deformed volume into the reference frame,
  ``F~(X) = F(X + u(X))`` (no inversion needed);
* :func:`warp_forward` moves the reference volume to the loaded state, ``G'(X + u(X)) = G(X)``
  (paper step d), solving ``X + u(X) = x`` for every loaded voxel ``x``: Newton on a coarse
  lattice, checked interpolation between its nodes, Newton per voxel where the check fails
  (:class:`.inverse_lattice.LatticeInverter`, within :data:`INVERSE_ACCURACY` of per-voxel Newton,
  :meth:`.field_spline.FieldSpline.invert`, which ``accuracy=None`` asks for);
* :func:`warp_forward_with_residual` does the forward warp and the loaded-state mean gray residual
  with one inversion (what a correction pass needs).

One pair of block helpers, :func:`pull_back_block` and :func:`warp_forward_block`, does the work
for any box of voxels and any sampler of the volume: the functions here call them on the whole
volume (positions made and sampled slab by slab) with the in-memory B-spline sampler,
:mod:`.residual` for the gray residuals, and :mod:`napari_dvc_correct.tiled.volumes` block by block with a sampler that reads a lazy volume.

Volumes are sampled with the tricubic B-spline of :mod:`.interpolation`. All positions are
``(z, y, x)`` in reference voxels.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from ..correlation.interpolation import prefilter, sample
from ..slabs import iter_slabs
from .field import DisplacementField
from .field_spline import (
    DEFAULT_CHUNK_VOXELS,
    FieldSpline,
    as_field_spline,
    check_shape,
    inside_hull,
)
from .inverse_lattice import LatticeInverter
from .pull_back_fill import pull_back_box

#: A sampler of a volume: positions ``(N, 3)`` ``(z, y, x)`` in voxels -> float32 values ``(N,)``,
#: NaN outside the volume.
Sampler = Callable[[np.ndarray], np.ndarray]

#: Newton iterations and step tolerance (voxels) of the inverse map, unless told otherwise.
INVERT_MAX_ITERATIONS = 50
INVERT_TOLERANCE = 1e-4

#: Largest error (voxels) of the forward warp's inverse map against per-voxel Newton (see
#: :func:`.inverse_lattice.invert_lattice`): 1e-3 voxel moves gray values by 1e-3 times their
#: gradient, far below the DVC's own uncertainty (0.01 - 0.05 voxel), so a correction computed on
#: the warped volume is not biased by it.
INVERSE_ACCURACY = 1e-3


def box_axes(box: tuple[slice, slice, slice]) -> list[np.ndarray]:
    """Voxel coordinates (float64) along z, y and x of a box given as three slices."""
    return [np.arange(s.start, s.stop, dtype=np.float64) for s in box]


def box_lattice(box: tuple[slice, slice, slice]) -> np.ndarray:
    """Voxel positions ``(N, 3)`` ``(z, y, x)`` of every voxel of ``box``, in C order."""
    grids = np.meshgrid(*box_axes(box), indexing="ij")
    return np.stack([g.reshape(-1) for g in grids], axis=1)


def whole_box(shape) -> tuple[slice, slice, slice]:
    """The box of every voxel of a volume of ``shape``."""
    return tuple(slice(0, int(n)) for n in shape)


def box_shape(box: tuple[slice, slice, slice]) -> tuple[int, int, int]:
    return tuple(s.stop - s.start for s in box)


def pull_back_block(
    sample_deformed: Sampler, spline: FieldSpline, box, outside: str = "extrapolate"
) -> np.ndarray:
    """``F(X + u(X))`` at every voxel ``X`` of ``box``, shape ``box_shape(box)``, float32.

    NaN where ``X + u(X)`` falls outside ``F`` or, with ``outside="nan"``, where ``X`` is outside
    the grid's hull. A :class:`SplineSampler` is sampled in one pass (:func:`.pull_back_box`); a
    sampler with a ``pull_back(spline, box, outside)`` method (``tiled.volumes.LazySampler``)
    does it itself; any other callable gets the positions of every voxel.
    """
    if isinstance(sample_deformed, SplineSampler):  # in memory: one pass, no positions array
        return pull_back_box(sample_deformed.coefficients, spline, box, outside)
    own = getattr(sample_deformed, "pull_back", None)  # a sampler that knows better (out of core)
    if own is not None:
        return own(spline, box, outside)
    dense = spline.lattice(*box_axes(box), outside=outside)
    points = box_lattice(box) + dense.reshape(-1, 3)
    return np.asarray(sample_deformed(points), np.float32).reshape(dense.shape[:3])


def warp_forward_block(
    sample_reference: Sampler,
    spline: FieldSpline,
    box,
    max_iterations: int = INVERT_MAX_ITERATIONS,
    tolerance: float = INVERT_TOLERANCE,
    accuracy: float | None = INVERSE_ACCURACY,
    chunk_voxels: int = DEFAULT_CHUNK_VOXELS,
    inverter: LatticeInverter | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """``G(X)`` with ``X + u(X) = x`` at every loaded-state voxel ``x`` of ``box``.

    ``X`` comes from :class:`.inverse_lattice.LatticeInverter` (within ``accuracy`` voxels of
    Newton's answer in the grid's hull and 10 times that beyond it, and the same whichever boxes
    a volume is cut into), or with ``accuracy=None`` from Newton at every voxel
    (:meth:`.field_spline.FieldSpline.invert`, several times slower). Positions are computed and
    sampled ``chunk_voxels`` at a time (whole z planes); the coarse stage runs once per box. With
    a :class:`SplineSampler` and ``accuracy`` set, the whole box is sampled as its positions are
    made (:meth:`.inverse_lattice.LatticeInverter.warp`; the same values to float32 rounding); a
    sampler with a ``warp_forward(inverter)`` method (``tiled.volumes.LazySampler``) does it
    itself. ``inverter``: the coarse stage already built for this spline and box (with these
    settings; :func:`forward_inverter`), to warp another volume with the same field.

    Returns
    -------
    values : ndarray, shape ``box_shape(box)``, float32
        NaN where the inversion did not converge or ``X`` falls outside ``G``.
    in_hull : ndarray of bool, same shape
        Where ``X`` lies in the grid's hull (where the field was measured).
    """
    shape = box_shape(box)
    values = np.empty(shape, np.float32)
    in_hull = np.empty(shape, np.bool_)
    if accuracy is not None:
        if inverter is None:
            inverter = LatticeInverter(spline, box, max_iterations, tolerance, accuracy)
        if isinstance(sample_reference, SplineSampler):
            return inverter.warp(sample_reference.coefficients)
        own = getattr(sample_reference, "warp_forward", None)  # e.g. tiled.volumes.LazySampler
        if own is not None:
            return own(inverter)
    for planes in iter_slabs(shape, chunk_voxels):
        if accuracy is None:
            sub = (
                slice(box[0].start + planes.start, box[0].start + planes.stop),
                box[1],
                box[2],
            )
            source, converged = spline.invert(box_lattice(sub), max_iterations, tolerance)
            hull = inside_hull(spline, source)
        else:
            source, converged, hull, _ = inverter.solve(planes)
        sampled = np.asarray(sample_reference(source), np.float32)
        sampled[~converged] = np.nan
        values[planes] = sampled.reshape(-1, *shape[1:])
        in_hull[planes] = hull.reshape(-1, *shape[1:])
    return values, in_hull


def coefficients_of(volume, coefficients, name: str) -> np.ndarray:
    """``coefficients`` checked against ``volume``'s shape, or the prefilter of ``volume``."""
    if coefficients is not None:
        coefficients = np.asarray(coefficients)
        if coefficients.shape != np.shape(volume):
            raise ValueError(
                f"{name} coefficients have shape {coefficients.shape}, "
                f"the volume has {np.shape(volume)}"
            )
        return coefficients
    volume = np.asarray(volume)
    if volume.ndim != 3:
        raise ValueError(f"{name} must be a 3-D volume (z, y, x), got shape {volume.shape}")
    return prefilter(volume)


class SplineSampler:
    """Sampler of an in-memory volume from its B-spline coefficients (NaN outside).

    :func:`warp_forward_block` recognises it and samples while it inverts the field
    (:meth:`.inverse_lattice.LatticeInverter.warp`), without a positions array.
    """

    def __init__(self, coefficients: np.ndarray) -> None:
        self.coefficients = np.ascontiguousarray(coefficients, dtype=np.float32)

    def __call__(self, points: np.ndarray) -> np.ndarray:
        return sample(self.coefficients, points, cval=np.nan)


def spline_sampler(coefficients: np.ndarray) -> SplineSampler:
    """Sampler of an in-memory volume from its B-spline coefficients (NaN outside)."""
    return SplineSampler(coefficients)


def slab_boxes(shape, chunk_voxels: int = DEFAULT_CHUNK_VOXELS):
    """Whole-plane boxes ``(z, :, :)`` of a volume of ``shape``, about ``chunk_voxels`` each."""
    for z in iter_slabs(shape, chunk_voxels):
        yield z, (z, slice(0, int(shape[1])), slice(0, int(shape[2])))


def pull_back(
    deformed: np.ndarray,
    field: DisplacementField | FieldSpline,
    *,
    shape=None,
    coefficients: np.ndarray | None = None,
    cval: float = np.nan,
    outside: str = "extrapolate",
    chunk_voxels: int = DEFAULT_CHUNK_VOXELS,
) -> np.ndarray:
    """The deformed volume seen from the reference frame: ``F~(X) = F(X + u(X))``.

    Needs no inversion. If the field is right, ``F~ ≈ G``.

    Parameters
    ----------
    deformed : ndarray, shape (nz, ny, nx)
        ``F``, any real dtype (only used to prefilter when ``coefficients`` is None).
    field : DisplacementField or FieldSpline
        Lagrangian displacement ``u(X)`` in voxels; nodes must be finite.
    shape : tuple of 3 ints, optional
        Shape of the reference volume (default: ``deformed.shape``).
    coefficients : ndarray, optional
        ``interpolation.prefilter(deformed)``, to reuse across calls.
    cval : float
        Value where ``X + u(X)`` falls outside ``F`` (or, with ``outside="nan"``, where ``X`` is
        outside the grid's hull).
    outside : {"extrapolate", "nan"}
        Extrapolate the field beyond the grid's hull, or give ``cval`` there.
    chunk_voxels : int
        Voxels processed at a time.

    Returns
    -------
    ndarray, shape ``shape``, float32
    """
    coefficients = coefficients_of(deformed, coefficients, "deformed")
    shape = coefficients.shape if shape is None else check_shape(shape)
    spline = as_field_spline(field)
    sampler = spline_sampler(coefficients)
    result = np.empty(shape, np.float32)
    for z, box in slab_boxes(shape, chunk_voxels):
        values = pull_back_block(sampler, spline, box, outside)
        values[~np.isfinite(values)] = cval
        result[z] = values
    return result


# pull_back and warp_forward share the shape of their parameter lists and slab loops (the
# duplicate finder pairs them): the work differs, in pull_back_block and warp_forward_block.
def warp_forward(
    reference: np.ndarray,
    field: DisplacementField | FieldSpline,
    *,
    shape=None,
    coefficients: np.ndarray | None = None,
    cval: float = np.nan,
    outside: str = "extrapolate",
    max_iterations: int = INVERT_MAX_ITERATIONS,
    tolerance: float = INVERT_TOLERANCE,
    chunk_voxels: int = DEFAULT_CHUNK_VOXELS,
    accuracy: float | None = INVERSE_ACCURACY,
) -> np.ndarray:
    """The reference volume moved to the loaded state: ``G'(X + u(X)) = G(X)`` (paper step d).

    For each voxel ``x`` of the loaded state the reference position ``X`` with ``X + u(X) = x`` is
    found (Newton on a coarse lattice and checked interpolation, see :func:`warp_forward_block`),
    then ``G'(x) = G(X)``.

    Parameters
    ----------
    reference : ndarray, shape (nz, ny, nx)
        ``G``, any real dtype (only used to prefilter when ``coefficients`` is None).
    field : DisplacementField or FieldSpline
        Lagrangian displacement ``u(X)`` in voxels; nodes must be finite.
    shape : tuple of 3 ints, optional
        Shape of the loaded-state volume (default: ``reference.shape``).
    coefficients : ndarray, optional
        ``interpolation.prefilter(reference)``, to reuse across calls.
    cval : float
        Value where ``X`` falls outside ``G``, where the iteration does not converge, or (with
        ``outside="nan"``) where ``X`` is outside the grid's hull.
    outside : {"extrapolate", "nan"}
        Extrapolate the field beyond the grid's hull, or give ``cval`` there.
    max_iterations, tolerance : int, float
        Fixed-point iteration limit and convergence threshold (voxels).
    chunk_voxels : int
        Voxels processed at a time.
    accuracy : float or None
        Largest error (voxels) of the inverse map against per-voxel Newton in the grid's hull (10
        times that beyond it); None runs Newton at every voxel (several times slower).

    Returns
    -------
    ndarray, shape ``shape``, float32
    """
    coefficients = coefficients_of(reference, coefficients, "reference")
    shape = coefficients.shape if shape is None else check_shape(shape)
    spline = as_field_spline(field)
    sampler = spline_sampler(coefficients)
    # one box: the coarse stage of the inverse runs once, positions are made slab by slab
    values, in_hull = warp_forward_block(
        sampler, spline, whole_box(shape), max_iterations, tolerance, accuracy, chunk_voxels
    )
    bad = ~np.isfinite(values)
    if outside == "nan":
        bad |= ~in_hull
    values[bad] = cval
    return values


def warp_forward_with_residual(
    reference: np.ndarray,
    deformed: np.ndarray,
    field: DisplacementField | FieldSpline,
    *,
    coefficients: np.ndarray | None = None,
    cval: float = np.nan,
    max_iterations: int = INVERT_MAX_ITERATIONS,
    tolerance: float = INVERT_TOLERANCE,
    chunk_voxels: int = DEFAULT_CHUNK_VOXELS,
    accuracy: float | None = INVERSE_ACCURACY,
    gray_levels=None,
    inverter: LatticeInverter | None = None,
) -> tuple[np.ndarray, float]:
    """:func:`warp_forward` (field extrapolated) and the loaded-state mean gray residual at once.

    One inversion serves both: ``G'`` everywhere (``cval`` where undefined) and the mean of
    ``|F - G'|`` where the reference position lies in the grid's hull, i.e.
    ``residual.mean_gray_residual(reference, deformed, field, "loaded")``; with ``gray_levels``
    (a :class:`.gray_levels.GrayLevelMap`) the mean of ``|map(F) - G'|`` (reference gray levels).
    ``inverter``: :func:`forward_inverter` of ``field`` and this shape, built by the caller to warp
    another volume (a mask) with the same inverse.

    Returns
    -------
    moved : ndarray, shape ``deformed.shape``, float32
    mean_residual : float
        Gray levels; NaN if defined nowhere.
    """
    coefficients = coefficients_of(reference, coefficients, "reference")
    deformed = np.asanyarray(deformed)
    shape = check_shape(deformed.shape)
    spline = as_field_spline(field)
    sampler = spline_sampler(coefficients)
    whole = None
    if accuracy is None:  # Newton at every voxel, over the whole box
        whole = warp_forward_block(
            sampler, spline, whole_box(shape), max_iterations, tolerance, None, chunk_voxels
        )
    elif inverter is None:
        inverter = LatticeInverter(spline, whole_box(shape), max_iterations, tolerance, accuracy)
    # else the coarse stage once, then G' sampled slab by slab (the same values as the whole
    # box's): no whole-volume hull mask
    result = np.empty(shape, np.float32) if whole is None else whole[0]
    total, count = 0.0, 0
    for z in iter_slabs(shape, chunk_voxels):
        if whole is None:
            values, in_hull = inverter.warp(sampler.coefficients, z)
            result[z] = values
            values = result[z]
        else:
            values, in_hull = result[z], whole[1][z]
        defined = np.isfinite(values)
        own = deformed[z].astype(np.float32)
        if gray_levels is not None:
            own = gray_levels.apply(own, (z, slice(0, shape[1]), slice(0, shape[2])))
        difference = np.abs(own - values)[defined & in_hull]
        total += float(np.sum(difference, dtype=np.float64))
        count += int(difference.size)
        values[~defined] = cval
    return result, (total / count if count else float("nan"))


def forward_inverter(spline: FieldSpline, shape) -> LatticeInverter:
    """The coarse stage of the whole-volume forward warp by ``spline`` with the default settings
    (what :func:`warp_forward` and :func:`warp_forward_with_residual` build), to be shared by
    several volumes warped with the same field (its :meth:`~.LatticeInverter.warp`)."""
    return LatticeInverter(
        spline, whole_box(check_shape(shape)), INVERT_MAX_ITERATIONS, INVERT_TOLERANCE,
        INVERSE_ACCURACY,
    )  # fmt: skip
