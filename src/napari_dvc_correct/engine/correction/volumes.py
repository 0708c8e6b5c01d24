"""The volume operations of the self-correction, behind one small interface.

:func:`.self_correction.correct_volumes_iter` is the one correction loop (clean, judge, warp, correlate,
compose, accept node by node, stop). Everything it does to the *volumes* goes through a
:class:`CorrectionVolumes`; the node arrays (fields) always stay in memory:

* :meth:`~CorrectionVolumes.correlate`: a DVC run (step a, or the correcting DVC of step e on
  the pair :meth:`~CorrectionVolumes.matching_pair` gives);
* :meth:`~CorrectionVolumes.align`: bring the pair together with a field (the forward warp of
  ``G`` in the loaded frame, the pull-back of ``F`` in the reference frame) and the mean gray
  residual of that field;
* :meth:`~CorrectionVolumes.matching_pair`: ``(G', F, warped mask)`` or ``(G, F~, mask)`` for
  the correcting DVC;
* :meth:`~CorrectionVolumes.residuals`: the reference-frame residuals the local acceptance
  (:class:`.acceptance.Judge`) judges nodes by (:class:`.acceptance.ReferenceResiduals`
  in memory);
* :meth:`~CorrectionVolumes.original_matcher`: re-matches of the original pair at chosen nodes
  with given subvolume weights (the oriented step, :mod:`.oriented`);
* :meth:`~CorrectionVolumes.release` and :meth:`~CorrectionVolumes.close`: drop a moved volume
  that is no longer needed, and everything at the end (also on error or cancel).

:class:`InMemoryVolumes` is the in-memory back-end (whole arrays, prefiltered once; the results of
:func:`.self_correction.correct_iter`). The out-of-core back-end, lazily read volumes batch by batch on
Dask, is ``napari_dvc_correct.tiled.correction.TiledVolumes`` (above the engine).
"""

from __future__ import annotations

from collections.abc import Generator

import numpy as np

from ..correlation.correlate import correlate_iter, kept_as_integers
from ..correlation.interpolation import prefilter
from ..correlation.params import CorrelationParams
from ..correlation.pyramid import Prefiltered
from ..evaluation.gray_levels import GrayLevelMap, fit_gray_levels, start_map
from ..evaluation.gray_noise import pair_noise, scan_noises
from ..evaluation.phases import otsu_stride
from ..fields import warp
from ..fields.field import DisplacementField
from ..fields.field_spline import FieldSpline
from ..progress import Progress
from .acceptance import ReferenceResiduals
from .oriented import ArrayMatcher


class CorrectionVolumes:
    """What the correction loop needs of a pair of volumes (the interface; see the module).

    Attributes
    ----------
    frame : {"loaded", "reference"}
        The frame the correcting DVC matches in.
    shape : tuple of 3 ints
        ``(nz, ny, nx)`` of the volumes.
    """

    frame: str
    shape: tuple
    gray_levels: GrayLevelMap | None = None

    def correlate(
        self,
        params: CorrelationParams,
        pair=None,
        *,
        grid=None,
        initial: DisplacementField | None = None,
        active=None,
    ) -> Generator[Progress, None, DisplacementField]:
        """A DVC run: of ``(G, F)`` with the input mask when ``pair`` is None (step a), else of
        ``pair = (g, f, mask)`` from :meth:`matching_pair`, on ``grid`` from ``initial``; only
        the POIs of ``active`` (bool, the grid's shape) when given, the others
        ``Status.NOT_COMPUTED`` (:func:`.correlate.correlate_iter`)."""
        raise NotImplementedError

    def align(self, field: DisplacementField) -> Generator[Progress, None, tuple[object, float]]:
        """The moved volume for the next DVC and the mean gray residual of ``field`` (reference
        gray levels, in the frame's sense: ``|map(F) - G'|`` over the loaded voxels whose
        reference position lies in the grid's hull, or ``|map(F~) - G|`` over the hull, with the
        gray-level map :attr:`gray_levels`, the identity until it is fitted)."""
        raise NotImplementedError

    def matching_pair(self, moved, field: DisplacementField) -> Generator[Progress, None, tuple]:
        """``(reference, deformed, mask)`` for the correcting DVC of step e."""
        raise NotImplementedError

    def fit_gray_levels(self, field: DisplacementField) -> Generator[Progress, None, GrayLevelMap]:
        """Fit the pair's gray-level map with ``field`` (:mod:`.gray_levels`), keep it as
        :attr:`gray_levels` for :meth:`align` and :meth:`residuals`, and return it."""
        raise NotImplementedError

    def residuals(self) -> Generator[Progress, None, object]:
        """The reference-frame residual access of the local acceptance (see
        :class:`.acceptance.ReferenceResiduals` for the methods), with
        :attr:`gray_levels`."""
        raise NotImplementedError

    def release(self, moved) -> None:
        """``moved`` (from :meth:`align`) is no longer needed."""

    def original_matcher(self):
        """A matcher of the original pair ``(G, F)`` with the input mask, for the re-matches of
        :func:`.oriented.oriented_rematch` (see there: ``shape`` and
        ``match(params, initial, active, weights)``); what it holds is let go with it."""
        raise NotImplementedError

    def close(self) -> None:
        """Free what the back-end holds (temporary files, connections); called once at the end."""


def _finite_or_fill(volume: np.ndarray, fill: float) -> np.ndarray:
    """``volume`` (float32, made for the caller: filled in place) with ``fill`` where it is not
    finite."""
    volume = np.asarray(volume, dtype=np.float32)
    volume[~np.isfinite(volume)] = fill
    return volume


def _held(volume) -> np.ndarray:
    """A scan as the correction holds it: as it is where a correlation reads it so
    (:func:`.correlate.kept_as_integers`: every value exact in float32, read as float32 slab by
    slab), else a float32 copy."""
    if kept_as_integers(volume):
        return np.ascontiguousarray(volume)
    return np.ascontiguousarray(volume, dtype=np.float32)


def _float32_mean(volume: np.ndarray) -> float:
    """``np.mean`` of ``volume`` as float32 (float32 sums, as of the float32 copy once held)."""
    return float(np.mean(np.asarray(volume, dtype=np.float32)))


def _hull_mean(difference: np.ndarray, hull) -> float:
    block = difference[hull]
    finite = np.isfinite(block)
    return float(np.mean(block[finite], dtype=np.float64)) if finite.any() else float("nan")


#: The correcting runs' noise hint (:func:`.correlate.correlate_iter`'s ``noise_hint``) is this
#: fraction of the input field's noise variance: a pass's pair ``(G', F)`` measured 0.55–0.87 of
#: it (``G'`` is resampled), and a POI the hint calls noisy wrongly costs only its sensitivity pass.
NOISE_HINT_FRACTION = 0.5


def noise_hint(field) -> float | None:
    """The correcting runs' noise hint from the field being corrected (None where the field
    carries no noise estimate, e.g. another program's)."""
    sigma = (field.metadata.get("noise") or {}).get("sigma")
    if sigma is None or not np.isfinite(sigma) or sigma <= 0.0:
        return None
    return NOISE_HINT_FRACTION * float(sigma) ** 2


#: From this many voxels, warping the pair (:meth:`InMemoryVolumes.align`) lets go of the pull-back
#: the residuals hold for the last field judged: the set-up's peak then holds one volume of float32
#: less. Below, it is kept: a run that ends on that field with flagged nodes would pull it back
#: again for the discontinuity test (one warp, CPU for a volume's worth of memory).
RELEASE_PULL_BACK_FROM = 2**24


class InMemoryVolumes(CorrectionVolumes):
    """The two volumes as arrays with their spline coefficients, prefiltered once for every pass.

    Parameters
    ----------
    reference, deformed : ndarray, shape (nz, ny, nx)
        ``G`` and ``F`` (checked by the caller), any real dtype; held as float32, except large
        8- and 16-bit scans, held as they are (the caller's arrays, no copy) and read as float32
        where used: the same numbers.
    frame : {"loaded", "reference"}
    mask : ndarray, optional
        Reference-space material mask (non-zero = inside).
    """

    def __init__(self, reference, deformed, frame: str, mask=None):
        self._inputs = (reference, deformed, mask)
        self.reference = _held(reference)
        self.deformed = _held(deformed)
        self.shape = self.reference.shape
        self.frame = frame
        self.mask = None if mask is None else np.asarray(mask) != 0
        self._coef_deformed = None
        self._fitted_with = None
        self._noise_hint = None
        self._inverse = None  # (field, its u, the forward warp's coarse stage) of align
        self._residuals = None
        if frame == "reference":
            self.fill = _float32_mean(self.deformed)
            self.coefficients = prefilter(self.deformed)
        else:
            self.fill = _float32_mean(self.reference)
            self.coefficients = prefilter(self.reference)
            self.mask_coefficients = (
                None if self.mask is None else prefilter(self.mask.astype(np.float32))
            )

    def correlate(self, params, pair=None, *, grid=None, initial=None, active=None):
        if pair is None:
            reference, deformed, mask = self._inputs
            return correlate_iter(reference, deformed, params, mask=mask)
        g, f, mask = pair
        if self._residuals is not None:  # the judged field's pull-back is not needed meanwhile
            self._residuals.forget()
        return correlate_iter(
            g, f, params, mask=mask, grid=grid, initial=initial, active=active,
            prefiltered=self._unchanged_side(), noise_hint=self._noise_hint,
        )  # fmt: skip

    def original_matcher(self):
        reference, deformed, mask = self._inputs
        # F's coefficients are the ones held for the residuals (the same numbers as a float32
        # copy's prefilter)
        return ArrayMatcher(reference, deformed, mask, coef_deformed=self._deformed_coefficients())

    def _unchanged_side(self) -> Prefiltered | None:
        """``F``'s coefficients in the loaded frame, whose every pass matches ``(G', F)``: held
        anyway for the residuals, so computed once. In the reference frame (pairs ``(G, F~)``)
        ``∇G`` is recomputed per pass (about 10 ms per million voxels) rather than held
        (12 bytes per voxel) between passes."""
        if self.frame == "reference":
            return None
        return Prefiltered(coef_deformed=self._deformed_coefficients())

    def _deformed_coefficients(self) -> np.ndarray:
        if self.frame == "reference":
            return self.coefficients
        if self._coef_deformed is None:
            self._coef_deformed = prefilter(self.deformed)
        return self._coef_deformed

    def fit_gray_levels(self, field):
        spline = FieldSpline.from_field(field)
        moved = warp.pull_back(
            self.deformed, spline, coefficients=self._deformed_coefficients(), cval=np.nan
        )
        # the first guess from the raw scans' lattice, as the tiled back-end's statistics pass
        lattice = (slice(None, None, otsu_stride(self.shape)),) * 3
        start = start_map(self.reference[lattice], self.deformed[lattice])
        # errors in both scans: each scan's own noise, F's as the pull-back keeps it
        noise = pair_noise(*scan_noises(self.reference, self.deformed), field.displacement)
        self.gray_levels = fit_gray_levels(self.reference, moved, start=start, noise=noise)
        self._fitted_with = (field, moved)  # the residuals' first pull-back (same field)
        self._noise_hint = noise_hint(field)  # for the correcting runs, from the field corrected
        return self.gray_levels
        yield

    def align(self, field):
        if self._residuals is not None and np.prod(self.shape) >= RELEASE_PULL_BACK_FROM:
            self._residuals.forget()
        spline = FieldSpline.from_field(field)
        gray = self.gray_levels
        if self.frame == "reference":
            moved = warp.pull_back(
                self.deformed, spline, coefficients=self.coefficients, cval=np.nan
            )
            mapped = moved if gray is None else gray.apply(moved)
            residual = _hull_mean(
                np.abs(mapped - self.reference), spline.hull_slices(self.reference.shape)
            )
        else:
            # with a mask, the next pass warps it with this field: the inverse's coarse stage
            # is kept for it
            inverter = None if self.mask is None else warp.forward_inverter(spline, self.shape)
            moved, residual = warp.warp_forward_with_residual(
                self.reference, self.deformed, spline, coefficients=self.coefficients,
                gray_levels=gray, inverter=inverter,
            )  # fmt: skip
            self._inverse = None if inverter is None else (field, field.u.copy(), inverter)
        return _finite_or_fill(moved, self.fill), residual
        yield  # a generator without progress: the arrays are at hand

    def matching_pair(self, moved, field):
        if self.frame == "reference":
            return self.reference, moved, self.mask
        mask = None
        if self.mask is not None:
            kept, self._inverse = self._inverse, None
            if kept is not None and kept[0] is field and np.array_equal(kept[1], field.u):
                inverter = kept[2]  # the last aligned field's: the coarse stage done once
            else:
                inverter = warp.forward_inverter(FieldSpline.from_field(field), self.shape)
            # as warp.warp_forward(mask, field, cval=0) > 0.5: undefined voxels are outside
            warped, _ = inverter.warp(self.mask_coefficients)
            mask = warped > 0.5
            if not mask.any():
                mask = None
        return moved, self.deformed, mask
        yield

    def residuals(self):
        residuals = ReferenceResiduals(
            self.reference, self.deformed, self._deformed_coefficients(), self.gray_levels
        )
        if self._fitted_with is not None:
            residuals.remember(*self._fitted_with)
            self._fitted_with = None
        self._residuals = residuals
        return residuals
        yield
