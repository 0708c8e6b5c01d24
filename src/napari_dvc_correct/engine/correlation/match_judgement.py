"""The second half of :func:`.correlate.correlate_iter`: matched POIs judged against the noise.

After the full-resolution IC-GN (:class:`MatchedGrid`), :func:`judge_iter` estimates the scans'
noise (:func:`.noise.noise_aware_thresholds`), marks ``LOW_TEXTURE``, runs the
reliability-guided repair with each POI's threshold, marks ``LOW_ZNCC``, measures the
uncertainties and applies the uncertainty bound (:func:`.noise.uncertainty_bound`), and
assembles the :class:`DisplacementField`.

Two of these steps take a median over the whole run's POIs: the noise estimate and the
uncertainty bound. A run held in parts (:mod:`..tiled`: one :class:`MatchedGrid` per batch)
computes both over all its parts and passes them in (``noise_variance``; ``bound=False`` leaves
the bound to the caller, :func:`.noise.uncertainty_bound` on the assembled arrays), so that every
POI is judged as in memory.
"""

from __future__ import annotations

import time
from collections.abc import Generator
from dataclasses import dataclass, field

import numpy as np

from ..fields.field import GOOD_STATUSES, DisplacementField, Provenance, Status
from ..progress import Progress
from . import shape_function
from .guided_repair import repair
from .noise import (
    MIN_PERFECT_ZNCC,
    NOISE_GRADIENT_GAIN,
    SENSITIVITY_FRACTION,
    noise_aware_thresholds,
    noise_estimates,
    noise_metadata,
    uncertainty_bound,
    zncc_floor,
)
from .params import CorrelationParams

_GOOD = np.array([int(s) for s in GOOD_STATUSES])


@dataclass
class MatchedGrid:
    """A POI grid after the full-resolution IC-GN, before its POIs are judged (:func:`judge_iter`).

    Flat arrays in C order of the grid (N POIs); warps are shape-function parameters at full
    resolution (voxels). Holds no volume: it travels between the two tasks of a tiled batch.

    Attributes
    ----------
    grid : (origin, step, shape)
    centers : ndarray of int, shape (N, 3)
        POI centres (voxels of the volumes matched).
    todo : ndarray of int
        POIs whose subvolume fits in the volume (the others stay ``OUT_OF_BOUNDS``).
    params : ndarray, shape (N, 3·nb)
    zncc, status, iterations : ndarray, shape (N,)
    variance, power : ndarray, shape (N,)
        Gray variance (gray levels²) and gradient power of each reference subvolume.
    sigma : ndarray, shape (N, 3)
        Uncertainty (voxels): NaN until measured (:func:`judge_iter`, or
        :func:`measure_plain_sigma` while the volumes are at hand).
    sigma_plain : ndarray of bool, shape (N,), optional
        POIs whose ``sigma`` already holds the noise-free-``H`` estimate (``σ_r² (H⊥⁻¹)_kk``) at
        their current match; :func:`judge_iter` keeps it where that estimate is the one it
        would make (the POI is not noisy at the run's noise and was not repaired).
    sigma_sensitive : ndarray of bool, shape (N,), optional
        POIs whose ``sigma`` already holds the estimate with the sensitivity pass at their
        current match (IC-GN's kernel, given a noise hint); kept where the POI is noisy at the
        run's noise and was not repaired.
    metadata : dict
        The field's metadata so far (volume shape, global shift, pyramid levels, timings...).
    started : float
        ``time.perf_counter()`` when the run started.
    """

    grid: tuple
    centers: np.ndarray
    todo: np.ndarray
    params: np.ndarray
    zncc: np.ndarray
    status: np.ndarray
    iterations: np.ndarray
    variance: np.ndarray
    power: np.ndarray
    sigma: np.ndarray
    metadata: dict = field(default_factory=dict)
    started: float = 0.0
    sigma_plain: np.ndarray | None = None
    sigma_sensitive: np.ndarray | None = None

    def noise_estimates(self, index=None) -> np.ndarray:
        """:func:`.noise.noise_estimates` of the POIs at ``index`` (default all)."""
        index = slice(None) if index is None else index
        return noise_estimates(self.variance[index], self.zncc[index], self.status[index])


def measure_plain_sigma(fine, matched: MatchedGrid, order) -> None:
    """Measure ``sigma`` from ``H⊥`` alone (no sensitivity pass) for the POIs good so far.

    For a tiled batch's first task, which holds its volumes: the judge (second task) then needs
    the volumes again only for POIs that are noisy at the whole run's noise or are repaired.
    """
    good = np.isin(matched.status, _GOOD)
    plain = good.copy()
    if matched.sigma_plain is not None:  # measured by IC-GN already (the same numbers)
        good &= ~matched.sigma_plain
    good = np.flatnonzero(good)
    fine.statistics(
        matched.centers[good],
        matched.params[good],
        matched.zncc[good],
        order,
        np.zeros(len(good), bool),
        (None, None, matched.sigma),
        good,
    )
    matched.sigma_plain = plain
    matched.sigma_sensitive = None  # overwritten by the plain estimate above


def judge_iter(
    matched: MatchedGrid,
    fine,
    params: CorrelationParams,
    *,
    noise_variance: float | None = None,
    bound: bool = True,
) -> Generator[Progress, None, tuple[DisplacementField, np.ndarray]]:
    """Judge ``matched``'s POIs at the noise, repair the failed ones, build the field.

    Parameters
    ----------
    matched : MatchedGrid
        Updated in place.
    fine : correlate.PyramidLevel
        The full-resolution level the POIs were matched at (the repair matches again).
    params : CorrelationParams
    noise_variance : float, optional
        The whole run's ``σ_n²`` (gray levels²) when ``matched`` is a part of it. Default: the
        median of these POIs' estimates.
    bound : bool
        Apply the uncertainty bound of these POIs (default); False leaves it to the caller
        (the field's ``metadata["noise"]`` then lacks ``uncertainty_bound``).

    Returns
    -------
    field : DisplacementField
    thresholds : ndarray, shape (N,)
        Each POI's ZNCC threshold.
    """
    order = params.order
    origin, step, grid_shape = matched.grid
    centers, params_out = matched.centers, matched.params
    zncc, status, iterations = matched.zncc, matched.status, matched.iterations
    variance, power, sigma = matched.variance, matched.power, matched.sigma
    timings = matched.metadata["timings"]
    n_points = len(centers)

    # imaging noise and the ZNCC threshold it allows (noise_aware_thresholds)
    t0 = time.perf_counter()
    floor = zncc_floor(order, params.subvolume)
    noise_variance, perfect, thresholds = noise_aware_thresholds(
        variance, zncc, status, params.min_zncc, floor, noise_variance=noise_variance
    )
    textureless = np.isin(status, _GOOD) & (perfect < MIN_PERFECT_ZNCC)
    status[textureless] = int(Status.LOW_TEXTURE)
    timings["noise_s"] = timings.get("noise_s", 0.0) + time.perf_counter() - t0

    t0 = time.perf_counter()
    yield Progress("repair", 0, 1, "re-matching failed POIs from their neighbours")
    before = params_out.copy()
    counts = {}
    repair(
        fine, centers, grid_shape, params_out, zncc, status, iterations, order, params, thresholds,
        counts=counts,
    )  # fmt: skip
    for name, value in counts.items():
        timings[f"{name}_fine"] = value
    repaired = np.any(params_out != before, axis=1)
    timings["repair_s"] = time.perf_counter() - t0

    low = np.isin(status, _GOOD) & ~(zncc >= thresholds)
    status[low] = int(Status.LOW_ZNCC)
    t0 = time.perf_counter()
    # once per measured POI, at its final match: where the reference's noise is a sizeable part
    # of H, with the sensitivity A measured from the deformed scan, elsewhere from H⊥ alone
    noisy = 3.0 * NOISE_GRADIENT_GAIN * noise_variance > SENSITIVITY_FRACTION * power
    measured = np.isin(status, np.r_[_GOOD, [int(Status.LOW_ZNCC)]])
    if matched.sigma_plain is not None:  # already measured as this judge would: keep it
        sigma[matched.sigma_plain & ~measured] = np.nan  # e.g. found textureless since
        kept = matched.sigma_plain & ~noisy
        if matched.sigma_sensitive is not None:
            sigma[matched.sigma_sensitive & ~measured] = np.nan
            kept |= matched.sigma_sensitive & noisy
        measured &= ~(kept & ~repaired)
    measured = np.flatnonzero(measured)
    stats = (None, None, sigma)  # variance and power: measured by match_iter
    fine.statistics(
        centers[measured],
        params_out[measured],
        zncc[measured],
        order,
        noisy[measured],
        stats,
        measured,
    )
    timings["uncertainty_s"] = time.perf_counter() - t0
    noise = {
        **noise_metadata(noise_variance, thresholds, status, params.min_zncc),
        "zncc_threshold_floor": float(floor),
    }
    if bound:
        limit, unsure = uncertainty_bound(sigma, status)
        status[unsure] = int(Status.LOW_ZNCC)
        noise.update(uncertainty_bound=limit, uncertain=int(unsure.sum()))
    displacement, gradient = shape_function.params_to_displacement(params_out, order)
    failed = ~np.isin(status, np.r_[_GOOD, [int(Status.LOW_ZNCC)]])
    displacement[failed] = np.nan
    gradient[failed] = np.nan
    sigma[failed] = np.nan
    provenance = np.full(n_points, int(Provenance.MEASURED), np.uint8)
    provenance[status == int(Status.MASKED)] = int(Provenance.MASKED)
    timings["total_s"] = time.perf_counter() - matched.started
    result = DisplacementField(
        origin=origin,
        step=step,
        u=displacement.reshape(*grid_shape, 3),
        zncc=zncc.reshape(grid_shape).astype(np.float32),
        status=status.reshape(grid_shape).astype(np.uint8),
        iterations=iterations.reshape(grid_shape).astype(np.int32),
        provenance=provenance.reshape(grid_shape),
        gradient=gradient.reshape(*grid_shape, 3, 3),
        uncertainty=sigma.reshape(*grid_shape, 3),
        params=params.to_dict(),
        metadata={**matched.metadata, "noise": noise},
    )
    yield Progress("done", 1, 1, f"{int(np.isin(status, _GOOD).sum())} of {n_points} POIs matched")
    return result, thresholds
