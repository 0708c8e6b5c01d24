"""The image pyramid of a correlation: the per-level arrays IC-GN reads, and the per-level rule.

Level ``lev`` bins both volumes by ``2**lev``; its subvolume half-size and search reach follow
from the run's parameters by one rule, :func:`level_reach`, which the tiled back-end's halo
(:func:`..tiled.memory.halo`) uses too."""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from ..fields.field import Status
from . import icgn, icgn_reference, icgn_uncertainty, icgn_weighted, shape_function
from .initial_guess import bin_volume
from .interpolation import prefilter
from .params import CorrelationParams
from .pyramid_rule import level_reach

#: From this many voxels a CPU level keeps ``G``'s B-spline coefficients (4 bytes per voxel)
#: instead of ``∇G`` (12), and the kernels compute each subvolume's ``∇G`` from them
#: (:func:`.icgn_reference.gradient_source`; the same values bit for bit). Below, where memory
#: is not short, the stored ``∇G`` saves that work: each voxel's gradient is read by every
#: subvolume over it (about 18 at subvolume 21, step 8).
GRADIENT_ON_DEMAND_FROM = 2**24


def _read_only(volume: np.ndarray) -> np.ndarray:
    """A read-only view: the kernels then see one array type whether the volume came from a
    read-only memory map or was computed, so numba compiles (and loads) one signature, not two."""
    view = volume.view()
    view.flags.writeable = False
    return view


class Prefiltered(NamedTuple):
    """Full-resolution arrays a caller already holds for the pair it correlates.

    The self-correction matches every pass against one unchanged volume: ``F`` in the loaded
    frame (its coefficients), ``G`` in the reference frame (its gradient), so it computes them
    once. ``None`` entries are computed from the volumes as usual.

    Attributes
    ----------
    gradient : ndarray (3, nz, ny, nx) float32, optional
        ``∇G`` of the reference's B-spline interpolant (:func:`.icgn_reference.gradient_volume`).
    coef_deformed : ndarray (nz, ny, nx) float32, optional
        ``F``'s B-spline coefficients (:func:`.interpolation.prefilter`).
    """

    gradient: np.ndarray | None = None
    coef_deformed: np.ndarray | None = None

    def check(self, shape) -> None:
        shape = tuple(shape)
        if self.gradient is not None and tuple(self.gradient.shape) != (3, *shape):
            raise ValueError(f"gradient {self.gradient.shape} does not fit volumes {shape}")
        if self.coef_deformed is not None and tuple(self.coef_deformed.shape) != shape:
            raise ValueError(f"coefficients {self.coef_deformed.shape} do not fit volumes {shape}")


@dataclass
class PyramidLevel:
    """Everything IC-GN needs at one pyramid level."""

    factor: int
    reference: np.ndarray
    deformed: np.ndarray
    gradient: np.ndarray  # ∇G (3, nz, ny, nx), or G's coefficients (1, nz, ny, nx): see build
    coef_deformed: np.ndarray
    mask: np.ndarray
    use_mask: bool
    half: int
    min_std: float
    device: str = "cpu"  # "cuda": IC-GN runs on the GPU (engine.cuda)
    #: weights of the subvolume's voxels, (edge³,) float64 (:mod:`.icgn_weighted`, on the CPU
    #: whatever ``device``); None: unweighted
    weights: np.ndarray | None = None

    @classmethod
    def build(
        cls, factor, reference, deformed, mask, half, min_texture, device="cpu", std=None,
        prefiltered=None, weights=None,
    ):  # fmt: skip
        """The level of binning ``factor``; ``prefiltered`` (:class:`Prefiltered`, factor 1 only)
        gives ``∇G`` and ``F``'s coefficients already computed for these volumes; ``weights``
        (``(2·half + 1,)*3``, optional) weigh the subvolumes' voxels (:mod:`.icgn_weighted`).

        On the CPU a level of at least :data:`GRADIENT_ON_DEMAND_FROM` voxels holds, as
        ``gradient``, ``G``'s B-spline coefficients with a leading axis of one (1, nz, ny, nx)
        rather than ``∇G`` (3, nz, ny, nx); the kernels compute each subvolume's ``∇G`` from them.
        """
        if weights is not None:
            weights = icgn_weighted.check_weights(weights, half)
        if factor > 1:
            reference = bin_volume(reference, factor)
            deformed = bin_volume(deformed, factor)
            if mask is not None:
                mask = bin_volume(mask.astype(np.float32), factor) >= 0.5
            prefiltered = None
        if std is None:  # else: the whole volume's, when these are a region of it (tiled)
            # before the level's arrays exist: np.std makes a temporary copy of the volume;
            # of float32 values (a reference of integers kept as it is gives the same std)
            values = reference[mask] if mask is not None else reference
            std = float(np.std(np.asarray(values, dtype=np.float32)))
            del values
        prefiltered = Prefiltered() if prefiltered is None else prefiltered
        prefiltered.check(reference.shape)
        gradient = prefiltered.gradient
        if gradient is None:
            coefficients = prefilter(reference)
            if device != "cuda" and reference.size >= GRADIENT_ON_DEMAND_FROM:
                gradient = coefficients[None]
            else:
                gradient = icgn_reference.gradient_volume(coefficients)
            del coefficients
        coef_deformed = prefiltered.coef_deformed
        if coef_deformed is None:
            coef_deformed = prefilter(deformed)
        return cls(
            factor=factor,
            reference=_read_only(reference),
            deformed=deformed,
            gradient=gradient,
            coef_deformed=coef_deformed,
            mask=mask if mask is not None else np.zeros((1, 1, 1), np.bool_),
            use_mask=mask is not None,
            half=half,
            min_std=min_texture * std,
            device=device,
            weights=weights,
        )

    def centers_from_fine(self, centers):
        """Nearest coarse voxels to fine positions, kept where the subvolume fits."""
        f = self.factor
        coarse = np.rint((centers - (f - 1) / 2.0) / f).astype(np.int64)
        high = np.array(self.reference.shape) - 1 - self.half
        return np.clip(coarse, self.half, np.maximum(high, self.half))

    def statistics(self, centers, warps, zncc, order, sensitivity, out, index):
        """Fill ``out``'s variance, gradient power and sigma at ``index``.

        (:func:`.icgn_uncertainty.subvolume_statistics`; ``out`` is ``(variance, power, sigma)``,
        an entry None where not wanted.)
        """
        if len(centers) == 0:
            return
        var = np.empty(len(centers))
        power = np.empty(len(centers))
        sig = np.empty((len(centers), 3))
        kernel, weighted = icgn_uncertainty.subvolume_statistics, ()
        if self.weights is not None:
            kernel, weighted = icgn_weighted.weighted_statistics, (self.weights,)
        kernel(
            self.reference,
            self.gradient,
            self.coef_deformed,
            self.mask,
            self.use_mask,
            *weighted,
            np.ascontiguousarray(centers, dtype=np.int64),
            self.half,
            shape_function.n_monomials(order),
            np.ascontiguousarray(warps, dtype=np.float64),
            np.ascontiguousarray(zncc, dtype=np.float64),
            np.ascontiguousarray(sensitivity, dtype=np.bool_),
            var,
            power,
            sig,
        )
        for target, values in zip(out, (var, power, sig)):
            if target is not None:  # None: not wanted
                target[index] = values

    def moments(self, centers, order, out, index):
        """Fill ``out = (variance, power)`` at ``index`` (:func:`.icgn_uncertainty.subvolume_moments`)."""
        var = np.full(len(centers), np.nan)
        power = np.full(len(centers), np.nan)
        if len(centers):
            kernel, weighted = icgn_uncertainty.subvolume_moments, ()
            if self.weights is not None:
                kernel, weighted = icgn_weighted.weighted_moments, (self.weights,)
            kernel(
                self.reference,
                self.gradient,
                self.mask,
                self.use_mask,
                *weighted,
                np.ascontiguousarray(centers, dtype=np.int64),
                self.half,
                shape_function.n_monomials(order),
                var,
                power,
            )
        out[0][index] = var
        out[1][index] = power

    def inputs(self, order, params: CorrelationParams) -> icgn.MatchInputs:
        """The kernels' argument bundle at this level for ``params``."""
        return icgn.MatchInputs(
            reference=self.reference,
            gradient=self.gradient,
            coef_deformed=self.coef_deformed,
            mask=self.mask,
            use_mask=bool(self.use_mask),
            half=int(self.half),
            nb=shape_function.n_monomials(order),
            max_iterations=int(params.max_iterations),
            tolerance=float(params.tolerance),
            min_std=float(self.min_std),
            min_mask_fraction=float(params.min_mask_fraction),
            max_update=float(max(self.half, params.min_max_update)),
            noise_fraction=float(params.noise_tolerance),
        )

    def match(self, centers, warps, order, params, sigma=None, noise_power=0.0):
        """IC-GN at ``centers`` from ``warps`` (N, 3·nb), updated in place.

        ``params`` is the run's :class:`CorrelationParams`. Returns ``(zncc, status,
        iterations)``. ``sigma`` (N, 4) float64, optional, out: on the CPU, each good match's
        uncertainty from the match's own reference terms, noise-free-``H`` where ``sigma[:, 3]``
        is 1, with the sensitivity pass where it is 2 (the POIs whose gradient power is below
        ``noise_power``) (:func:`.icgn.match_many_sigma`); left at 0 (not measured) on the GPU.
        """
        n = len(centers)
        zncc = np.full(n, np.nan)
        status = np.full(n, int(Status.NOT_COMPUTED), np.int64)
        iterations = np.zeros(n, np.int64)
        if n == 0:
            return zncc, status, iterations
        if sigma is not None:
            sigma[:] = 0.0
        if self.weights is not None:
            icgn_weighted.match_many_weighted(
                self.inputs(order, params),
                self.weights,
                np.ascontiguousarray(centers, dtype=np.int64),
                warps,
                zncc,
                status,
                iterations,
                np.zeros((n, 4)) if sigma is None else sigma,
                float(noise_power),
            )
            return zncc, status, iterations
        if sigma is not None and self.device != "cuda":
            icgn.match_many_sigma(
                self.inputs(order, params),
                np.ascontiguousarray(centers, dtype=np.int64),
                warps,
                zncc,
                status,
                iterations,
                sigma,
                float(noise_power),
            )
            return zncc, status, iterations
        if self.device == "cuda":
            from ..cuda import match_many_cuda as kernel  # same arguments as icgn.match_many
        else:
            kernel = icgn.match_many
        kernel(
            self.inputs(order, params),
            np.ascontiguousarray(centers, dtype=np.int64),
            warps,
            zncc,
            status,
            iterations,
        )
        return zncc, status, iterations


def build_level(lev, reference, deformed, mask, params, device_kind, texture_std):
    """:class:`PyramidLevel` ``lev`` (factor ``2**lev``) as :func:`correlate_iter` builds it."""
    reach = level_reach(params, lev)
    return PyramidLevel.build(
        reach.factor,
        reference,
        deformed,
        mask,
        reach.half,
        params.min_texture,
        device_kind,
        std=None if texture_std is None else texture_std[reach.factor],
    )
