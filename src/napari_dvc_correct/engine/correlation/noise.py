"""The scans' imaging noise, the ZNCC a perfect match reaches at it, and the uncertainty bound.

A low ZNCC on a noisy scan is not a failed match: these rules turn the noise the matches
themselves reveal into a threshold per POI (:func:`noise_aware_thresholds`) and a bound on the
trusted uncertainty (:func:`uncertainty_bound`), and say in the field's metadata what was used
(:func:`noise_metadata`). Gray levels for variances, voxels for uncertainties.
"""

from __future__ import annotations

import numpy as np

from ..fields.field import GOOD_STATUSES, Status
from .shape_function import n_monomials

_GOOD = np.array([int(s) for s in GOOD_STATUSES])


#: POIs whose perfect-match ZNCC at the scans' noise level (:func:`noise_aware_thresholds`) is
#: below this hold less texture than a ninth of the noise variance: ``LOW_TEXTURE``.
MIN_PERFECT_ZNCC = 0.1

#: Fitting ``m`` shape-function parameters to pure noise over ``n`` voxels reaches a ZNCC of
#: about ``sqrt(m / n)``; a match must exceed this many times that (measured on noise-against-
#: noise subvolumes, 15³, first order: 0.05-0.09, the floor is 0.15).
ZNCC_SIGNIFICANCE = 2.5


def zncc_floor(order: int, subvolume: int) -> float:
    """Lowest ZNCC threshold: :data:`ZNCC_SIGNIFICANCE` times what fitting the shape function of
    ``order`` to noise alone reaches over a ``subvolume³`` subvolume, ``sqrt(3·nb / n)``."""
    nb = n_monomials(order)
    return float(ZNCC_SIGNIFICANCE * np.sqrt(3 * nb / subvolume**3))


#: Mean square of one gradient component of unit white noise through the cubic B-spline
#: interpolant (measured 1.386); with the noise estimate it says how much of ``H`` is noise.
NOISE_GRADIENT_GAIN = 1.39
#: The uncertainty measures the sensitivity ``A`` from the deformed scan
#: (:func:`.icgn_uncertainty.subvolume_statistics`) where the noise is more than this fraction of ``H``.
SENSITIVITY_FRACTION = 0.02

#: Uncertainty bound (voxels, :func:`uncertainty_bound`): matches whose predicted uncertainty
#: along some axis exceeds ``min(MAX_UNCERTAINTY, max(MIN_UNCERTAINTY_BOUND, UNCERTAINTY_RATIO
#: × the median of the matched POIs))`` are not trusted and become ``LOW_ZNCC``.
MAX_UNCERTAINTY = 1.0
MIN_UNCERTAINTY_BOUND = 0.1
UNCERTAINTY_RATIO = 10.0


def uncertainty_bound(sigma, status):
    """The uncertainty (voxels) above which a match is not trusted, and the POIs above it.

    A match the images do not pin down has a large uncertainty: on noise-free scans that is one
    far above the field's typical value (measured: 0.2-2.6 voxels against 1e-4 for the subvolumes
    that straddle a region that one scan lacks, all 1-8 voxels off), on noisy scans one above a
    voxel. The bound is ``min(1, max(0.1, 10 × median))`` over the matched POIs' largest
    component.

    Returns
    -------
    bound : float
    unsure : ndarray of bool (N,)
        Matched POIs (good status) whose largest component exceeds the bound (or is infinite).
    """
    largest = np.max(sigma, axis=1)
    matched = np.isin(status, _GOOD)
    known = matched & np.isfinite(largest)
    typical = float(np.median(largest[known])) if known.any() else 0.0
    bound = min(MAX_UNCERTAINTY, max(MIN_UNCERTAINTY_BOUND, UNCERTAINTY_RATIO * typical))
    with np.errstate(invalid="ignore"):
        unsure = matched & (largest > bound)
    return bound, unsure


def noise_estimates(variance, zncc, status):
    """Each matched POI's estimate ``s² (1 − ZNCC)`` of the noise variance (gray levels²).

    The estimates of :func:`noise_aware_thresholds`, for a run that takes their median over
    POIs it holds in several parts (:mod:`..tiled`): the POIs with a good status and a finite
    ZNCC and variance, in their order.
    """
    matched = np.isin(status, _GOOD) & np.isfinite(zncc) & np.isfinite(variance)
    return variance[matched] * np.clip(1.0 - zncc[matched], 0.0, None)


def noise_aware_thresholds(variance, zncc, status, min_zncc, floor=0.0, noise_variance=None):
    """Imaging noise of the scans and the ZNCC threshold of every POI at that noise.

    With independent noise of variance ``σ_n²`` on both scans and a subvolume whose gray variance
    is ``s² = σ_t² + σ_n²`` (texture plus noise), a perfect match reaches
    ``ZNCC* = σ_t² / (σ_t² + σ_n²) = 1 − σ_n² / s²`` (the residual ``(g − ḡ) − (f − f̄)`` holds
    the two noises, ``Σ r² = 2 n σ_n²``, and ``ZNSSD = Σ r² / (n s²) = 2 (1 − ZNCC)``). So every
    match gives ``s² (1 − ZNCC)`` as an estimate of ``σ_n²``, too large where the match is wrong
    or the shape function cannot follow the deformation; their median over the matched POIs is
    the noise estimate. A POI's threshold is ``min_zncc · ZNCC*``: ``min_zncc`` is read relative
    to what a perfect match can reach, which is ``min_zncc`` itself on noise-free scans. It is
    never below ``floor`` (what fitting the shape function to noise alone reaches,
    ``ZNCC_SIGNIFICANCE · sqrt(3·nb / n)``) nor above ``min_zncc``.

    Parameters
    ----------
    variance : ndarray (N,)
        Gray variance of each POI's reference subvolume (NaN where unknown).
    zncc, status : ndarray (N,)
        Results of the matching.
    min_zncc : float
    floor : float
        Lowest threshold.
    noise_variance : float, optional
        ``σ_n²`` already estimated (the median of :func:`noise_estimates` over the whole run's
        POIs, when these are a part of them): used instead of these POIs' median.

    Returns
    -------
    noise_variance : float
        ``σ_n²`` in gray levels² (0 when no POI matched).
    perfect : ndarray (N,)
        ``ZNCC*`` per POI, in [0, 1] (NaN where the variance is unknown).
    thresholds : ndarray (N,)
        ``min_zncc · ZNCC*`` (``min_zncc`` where ``ZNCC*`` is unknown).
    """
    if noise_variance is None:
        estimates = noise_estimates(variance, zncc, status)
        noise_variance = float(np.median(estimates)) if estimates.size else 0.0
    noise_variance = float(noise_variance)
    with np.errstate(divide="ignore", invalid="ignore"):
        perfect = np.clip(1.0 - noise_variance / variance, 0.0, 1.0)
    thresholds = np.where(np.isfinite(perfect), min_zncc * perfect, min_zncc)
    thresholds = np.minimum(np.maximum(thresholds, floor), min_zncc)
    return noise_variance, perfect, thresholds


def noise_metadata(noise_variance, thresholds, status, min_zncc):
    measured = np.isin(status, np.r_[_GOOD, [int(Status.LOW_ZNCC)]])
    used = thresholds[measured] if measured.any() else np.array([min_zncc])
    return {
        "sigma": float(np.sqrt(noise_variance)),
        "estimator": "median over matched POIs of s² (1 - ZNCC), s² the subvolume's variance",
        "zncc_threshold_rule": "min_zncc * (1 - sigma² / s²)",
        "min_zncc": float(min_zncc),
        "zncc_threshold_min": float(np.min(used)),
        "zncc_threshold_median": float(np.median(used)),
        "zncc_threshold_max": float(np.max(used)),
        "low_texture_rule": f"1 - sigma² / s² < {MIN_PERFECT_ZNCC}",
    }
