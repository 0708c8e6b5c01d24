"""Local DVC: ``correlate(G, F, params) -> DisplacementField``.

The pipeline, coarse to fine:

1. prefilter ``F`` into B-spline coefficients and compute the gradient of ``G`` (once per volume);
2. estimate the rigid shift of the whole specimen (phase correlation of binned volumes);
3. on a binned pyramid (when the search radius exceeds a few voxels), search every POI's integer
   displacement by FFT cross-correlation at the coarsest level and refine it with IC-GN level by
   level;
4. run IC-GN at full resolution for every POI in parallel, in batches that report progress;
5. reliability-guided repair: POIs that failed, matched poorly or disagree with their neighbours are
   matched again from the warps of their best converged neighbours, best first.
"""

from __future__ import annotations

import heapq
import time
from collections.abc import Generator
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from . import icgn, icgn_reference, icgn_uncertainty, shape_function
from .backend import select_device
from .cleaning import normalized_median_test
from .field import GOOD_STATUSES, DisplacementField, Provenance, Status, grid_for_volume
from .initial_guess import bin_volume, fft_search, global_shift, pyramid_levels
from .interpolation import prefilter
from .params import CorrelationParams
from .progress import Progress, run_to_completion
from .validation import validate_volume

_GOOD = np.array([int(s) for s in GOOD_STATUSES])


def validate_pair(reference, deformed, params: CorrelationParams, mask=None):
    """Check the inputs of a correlation; return float32 volumes and a boolean mask (or None).

    Raises
    ------
    ValueError
        With a message that says what to change: not 3-D, shapes that differ, NaN or infinite
        values, a subvolume larger than the volume, an empty mask or a mask of another shape.
    """
    reference = validate_volume(reference, "reference volume")
    deformed = validate_volume(deformed, "deformed volume")
    if reference.shape != deformed.shape:
        raise ValueError(
            f"reference {reference.shape} and deformed {deformed.shape} volumes must have the "
            "same shape"
        )
    if params.subvolume > min(reference.shape):
        from .pair_checks import largest_subvolume_advice

        raise ValueError(
            f"subvolume {params.subvolume} is larger than the volume {reference.shape}: "
            + largest_subvolume_advice(reference.shape)
        )
    reference = np.ascontiguousarray(reference, dtype=np.float32)
    deformed = np.ascontiguousarray(deformed, dtype=np.float32)
    if mask is not None:
        mask = np.asarray(mask)
        if mask.shape != reference.shape:
            raise ValueError(f"mask shape {mask.shape} differs from the volume {reference.shape}")
        if mask.dtype.kind == "f" and not np.all(np.isfinite(mask)):  # NaN != 0 is "material"
            raise ValueError(
                "the mask contains NaN or infinite values: use 0 = outside, 1 = material"
            )
        mask = np.ascontiguousarray(mask != 0)
        if not mask.any():
            raise ValueError("the mask is empty: no voxel is selected")
    return reference, deformed, mask


def _grid_centers(grid, volume_shape, half):
    origin, step, shape = grid
    axes = [np.asarray(origin[a]) + np.asarray(step[a]) * np.arange(shape[a]) for a in range(3)]
    zz, yy, xx = np.meshgrid(*axes, indexing="ij")
    points = np.stack([zz.ravel(), yy.ravel(), xx.ravel()], axis=1)
    centers = np.rint(points).astype(np.int64)
    if np.max(np.abs(points - centers), initial=0.0) > 1e-6:
        raise ValueError("POI positions (origin + i * step) must be whole voxels")
    inside = np.all((centers >= half) & (centers <= np.array(volume_shape) - 1 - half), axis=1)
    return centers, inside


@dataclass
class PyramidLevel:
    """Everything IC-GN needs at one pyramid level."""

    factor: int
    reference: np.ndarray
    deformed: np.ndarray
    gradient: np.ndarray
    coef_deformed: np.ndarray
    mask: np.ndarray
    use_mask: bool
    half: int
    min_std: float
    device: str = "cpu"  # "cuda": IC-GN runs on the GPU (engine.cuda)

    @classmethod
    def build(cls, factor, reference, deformed, mask, half, min_texture, device="cpu", std=None):
        if factor > 1:
            reference = bin_volume(reference, factor)
            deformed = bin_volume(deformed, factor)
            if mask is not None:
                mask = bin_volume(mask.astype(np.float32), factor) >= 0.5
        gradient = icgn_reference.gradient_volume(prefilter(reference))
        if std is None:  # else: the whole volume's, when these are a region of it (tiled)
            std = float(np.std(reference[mask] if mask is not None else reference))
        return cls(
            factor=factor,
            reference=reference,
            deformed=deformed,
            gradient=gradient,
            coef_deformed=prefilter(deformed),
            mask=mask if mask is not None else np.zeros((1, 1, 1), np.bool_),
            use_mask=mask is not None,
            half=half,
            min_std=min_texture * std,
            device=device,
        )

    def centers_from_fine(self, centers):
        """Nearest coarse voxels to fine positions, kept where the subvolume fits."""
        f = self.factor
        coarse = np.rint((centers - (f - 1) / 2.0) / f).astype(np.int64)
        high = np.array(self.reference.shape) - 1 - self.half
        return np.clip(coarse, self.half, np.maximum(high, self.half))

    def statistics(self, centers, warps, zncc, order, sensitivity, out, index):
        """Fill ``out``'s variance, gradient power and sigma at ``index``.

        (:func:`.icgn_uncertainty.subvolume_statistics`; ``out`` is ``(variance, power, sigma)``.)
        """
        if len(centers) == 0:
            return
        var = np.empty(len(centers))
        power = np.empty(len(centers))
        sig = np.empty((len(centers), 3))
        icgn_uncertainty.subvolume_statistics(
            self.reference,
            self.gradient,
            self.coef_deformed,
            self.mask,
            self.use_mask,
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
        out[0][index] = var
        out[1][index] = power
        out[2][index] = sig

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

    def match(self, centers, warps, order, params):
        """IC-GN at ``centers`` from ``warps`` (N, 3·nb), updated in place.

        ``params`` is the run's :class:`CorrelationParams`. Returns ``(zncc, status,
        iterations)``.
        """
        n = len(centers)
        zncc = np.full(n, np.nan)
        status = np.full(n, int(Status.NOT_COMPUTED), np.int64)
        iterations = np.zeros(n, np.int64)
        if n == 0:
            return zncc, status, iterations
        if self.device == "cuda":
            from .cuda import match_many_cuda as kernel  # same arguments as icgn.match_many
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


def _neighbour_outliers(u, usable, grid_shape, threshold=2.0, noise=0.1):
    """Usable POIs (flat mask) that fail the normalised median test over their 26 neighbours."""
    residual = normalized_median_test(
        u.reshape(*grid_shape, 3), usable.reshape(grid_shape), epsilon=noise
    )
    return (np.nan_to_num(residual, nan=0.0) > threshold).reshape(-1) & usable


def _is_good(status, zncc, min_zncc):
    return np.isin(status, _GOOD) & (zncc >= min_zncc)


#: POIs whose perfect-match ZNCC at the scans' noise level (:func:`noise_aware_thresholds`) is
#: below this hold less texture than a ninth of the noise variance: ``LOW_TEXTURE``.
MIN_PERFECT_ZNCC = 0.1

#: Fitting ``m`` shape-function parameters to pure noise over ``n`` voxels reaches a ZNCC of
#: about ``sqrt(m / n)``; a match must exceed this many times that (measured on noise-against-
#: noise subvolumes, 15³, first order: 0.05-0.09, the floor is 0.15).
ZNCC_SIGNIFICANCE = 2.5

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


def noise_aware_thresholds(variance, zncc, status, min_zncc, floor=0.0):
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

    Returns
    -------
    noise_variance : float
        ``σ_n²`` in gray levels² (0 when no POI matched).
    perfect : ndarray (N,)
        ``ZNCC*`` per POI, in [0, 1] (NaN where the variance is unknown).
    thresholds : ndarray (N,)
        ``min_zncc · ZNCC*`` (``min_zncc`` where ``ZNCC*`` is unknown).
    """
    matched = np.isin(status, _GOOD) & np.isfinite(zncc) & np.isfinite(variance)
    estimates = variance[matched] * np.clip(1.0 - zncc[matched], 0.0, None)
    noise_variance = float(np.median(estimates)) if estimates.size else 0.0
    with np.errstate(divide="ignore", invalid="ignore"):
        perfect = np.clip(1.0 - noise_variance / variance, 0.0, 1.0)
    thresholds = np.where(np.isfinite(perfect), min_zncc * perfect, min_zncc)
    thresholds = np.minimum(np.maximum(thresholds, floor), min_zncc)
    return noise_variance, perfect, thresholds


def _repair(
    level,
    centers,
    grid_shape,
    params,
    zncc,
    status,
    iterations,
    order,
    settings,
    thresholds=None,
):
    """Reliability-guided propagation into POIs that failed or are outliers.

    POIs are taken best first (highest ZNCC); each bad 26-neighbour is matched again with the
    popped POI's warp carried over to its position (``u + ∇u·Δ``). A new match replaces the old
    one when it converges above its ZNCC threshold (``thresholds`` (N,), default
    ``settings.min_zncc``); it then seeds its own neighbours.
    """
    if thresholds is None:
        thresholds = np.full(len(centers), float(settings.min_zncc))
    good = _is_good(status, zncc, thresholds)
    try_again = np.isin(status, [int(Status.MASKED), int(Status.LOW_TEXTURE)])
    if good.sum() >= settings.median_test_min_pois:
        good &= ~_neighbour_outliers(
            shape_function.params_to_displacement(params, order)[0], good, grid_shape
        )
    bad = (
        ~good
        & ~try_again
        & np.isin(
            status,
            np.r_[
                _GOOD,
                [
                    int(Status.DIVERGED),
                    int(Status.SINGULAR),
                    int(Status.OUT_OF_BOUNDS),
                    int(Status.LOW_ZNCC),
                ],
            ],
        )
    )
    if not bad.any() or not good.any():
        return int(bad.sum())
    nb = shape_function.n_monomials(order)
    grid_index = np.arange(len(centers)).reshape(grid_shape)
    offsets = [
        (a, b, c)
        for a in (-1, 0, 1)
        for b in (-1, 0, 1)
        for c in (-1, 0, 1)
        if (a, b, c) != (0, 0, 0)
    ]
    heap = [(-zncc[i], i) for i in np.flatnonzero(good)]
    heapq.heapify(heap)
    attempts = np.zeros(len(centers), np.int64)
    max_attempts = np.where(
        status == int(Status.OUT_OF_BOUNDS),
        settings.repair_attempts_out_of_bounds,
        settings.repair_attempts,
    )
    while heap and bad.any():
        _, i = heapq.heappop(heap)
        iz, iy, ix = np.unravel_index(i, grid_shape)
        for a, b, c in offsets:
            jz, jy, jx = iz + a, iy + b, ix + c
            if not (
                0 <= jz < grid_shape[0] and 0 <= jy < grid_shape[1] and 0 <= jx < grid_shape[2]
            ):
                continue
            j = grid_index[jz, jy, jx]
            if not bad[j] or attempts[j] >= max_attempts[j]:
                continue
            attempts[j] += 1
            guess = params[i].reshape(3, nb).copy()
            delta = (centers[j] - centers[i]).astype(np.float64)
            guess[:, 0] += guess[:, 1:4] @ delta
            trial = np.ascontiguousarray(guess.reshape(1, -1))
            t_zncc, t_status, t_its = level.match(centers[j : j + 1], trial, order, settings)
            if t_status[0] in _GOOD and t_zncc[0] >= thresholds[j]:
                params[j] = trial[0]
                zncc[j] = t_zncc[0]
                status[j] = t_status[0]
                iterations[j] = t_its[0]
                bad[j] = False
                heapq.heappush(heap, (-zncc[j], j))
    return int(bad.sum())


def _seed_guesses(level, centers, grid_shape, shift, radius, order, settings):
    """Initial warps for every POI from an FFT search at a sparse set of seed POIs.

    Seeds sit on a sub-grid about one subvolume apart. Each is searched by FFT cross-correlation
    within ``radius`` around the rigid ``shift`` and refined by IC-GN; seeds that fail, correlate
    poorly or disagree with the other seeds are dropped, and every POI receives the affine warp of
    its nearest good seed carried to its position. Falls back to searching every POI when no seed
    survives.

    Returns
    -------
    ndarray, shape (N, 3·nb)
        Shape-function parameters at ``level`` (voxels of that level).
    """
    stride = max(1, int(round(settings.subvolume / settings.step)))
    axes = [np.unique(np.r_[np.arange(0, n, stride), n - 1]) for n in grid_shape]
    seed_grid = np.zeros(grid_shape, bool)
    seed_grid[np.ix_(*axes)] = True
    seeds = np.flatnonzero(seed_grid)
    n_points = len(centers)
    nb = shape_function.n_monomials(order)

    def search(index):
        found, _ = fft_search(
            level.reference,
            level.deformed,
            centers[index],
            level.half,
            np.tile(shift, (len(index), 1)),
            radius,
        )
        return shape_function.displacement_to_params(found, None, order)

    seed_params = np.ascontiguousarray(search(seeds))
    zncc, status, _ = level.match(centers[seeds], seed_params, order, settings)
    good = _is_good(status, zncc, settings.min_zncc)
    if good.sum() >= settings.median_test_min_pois:
        seed_u = np.full((*[len(a) for a in axes], 3), np.nan)
        seed_u.reshape(-1, 3)[:] = shape_function.params_to_displacement(seed_params, order)[0]
        good &= ~_neighbour_outliers(seed_u.reshape(-1, 3), good, seed_u.shape[:3])
    if not good.any():
        return np.ascontiguousarray(search(np.arange(n_points)))
    good_grid = np.zeros(grid_shape, bool)
    good_grid.reshape(-1)[seeds[good]] = True
    nearest = ndimage.distance_transform_edt(
        ~good_grid, return_distances=False, return_indices=True
    )
    nearest_flat = np.ravel_multi_index(tuple(nearest.reshape(3, -1)), grid_shape)
    lookup = np.full(n_points, -1)
    lookup[seeds] = np.arange(len(seeds))
    source = lookup[nearest_flat]
    guesses = seed_params[source].reshape(n_points, 3, nb).copy()
    delta = (centers - centers[seeds][source]).astype(np.float64)
    guesses[:, :, 0] += np.einsum("nkl,nl->nk", guesses[:, :, 1:4], delta)
    return np.ascontiguousarray(guesses.reshape(n_points, 3 * nb))


def correlate_iter(
    reference: np.ndarray,
    deformed: np.ndarray,
    params: CorrelationParams | None = None,
    *,
    mask: np.ndarray | None = None,
    grid: tuple | None = None,
    initial: DisplacementField | None = None,
    rigid_shift=None,
    device="cpu",
    texture_std=None,
) -> Generator[Progress, None, DisplacementField]:
    """Correlate ``reference`` (G) with ``deformed`` (F), yielding progress; returns the field.

    Parameters
    ----------
    reference, deformed : ndarray, shape (nz, ny, nx)
        The two volumes, any real dtype (processed as float32). Axis order (z, y, x).
    params : CorrelationParams, optional
        Subvolume, step, shape-function order, search radius... (defaults if None).
    mask : ndarray of bool, shape (nz, ny, nx), optional
        Reference-space mask of the material: only voxels inside it enter the matching, and POIs
        with less than ``params.min_mask_fraction`` of their subvolume inside get ``MASKED``.
    grid : (origin, step, shape), optional
        POI grid in reference voxels; whole-voxel positions. Default:
        :func:`grid_for_volume` ``(shape, subvolume, step)``.
    initial : DisplacementField, optional
        Initial guess on the same grid (skips the global and FFT searches).
    rigid_shift : array-like of 3 ints, optional
        Rigid shift ``(z, y, x)`` voxels to search around instead of estimating it from these
        volumes: the whole volume's shift when they are a region of larger volumes
        (:mod:`.tiled`).
    texture_std : mapping of int to float, optional
        Gray standard deviation of the whole reference volume (inside the mask) binned by each
        pyramid factor ``1, 2, 4...``, for the low-texture test, when these volumes are a region
        of larger ones (:mod:`.tiled`). Default: computed from these volumes.
    device : {"cpu", "cuda", "auto"} or backend.Device
        Where IC-GN runs (:func:`.backend.select_device`; a missing GPU falls back to the CPU with
        a warning). The field's ``metadata["device"]`` says which was used.

    Yields
    ------
    Progress
        One report per stage and per batch of POIs.

    Returns
    -------
    DisplacementField
        ``u`` in voxels at each POI, with ``zncc``, ``status``, ``iterations`` and the shape
        function's displacement ``gradient``.
    """
    params = CorrelationParams() if params is None else params
    device = select_device(device)
    start_time = time.perf_counter()
    timings = {}
    reference, deformed, mask = validate_pair(reference, deformed, params, mask)
    if grid is None:
        grid = grid_for_volume(reference.shape, params.subvolume, params.step)
    origin, step, grid_shape = grid
    grid_shape = tuple(int(n) for n in grid_shape)
    if min(grid_shape) < 1:
        raise ValueError(f"the POI grid is empty (shape {grid_shape})")
    half = params.half
    centers, inside = _grid_centers(grid, reference.shape, half)
    n_points = len(centers)
    order = params.order
    nb = shape_function.n_monomials(order)
    if initial is not None and initial.shape != grid_shape:
        raise ValueError(
            f"initial field grid {initial.shape} differs from the POI grid {grid_shape}"
        )

    yield Progress("prefilter", 0, 1, "prefiltering the volumes")
    t0 = time.perf_counter()
    fine = PyramidLevel.build(
        1,
        reference,
        deformed,
        mask,
        half,
        params.min_texture,
        device.kind,
        std=None if texture_std is None else texture_std[1],
    )
    timings["prefilter_s"] = time.perf_counter() - t0
    yield Progress("prefilter", 1, 1, "volumes prefiltered")

    t0 = time.perf_counter()
    radius = params.effective_search_radius
    if initial is not None:
        guess_params = shape_function.displacement_to_params(
            initial.displacement,
            None if initial.gradient is None else initial.gradient.reshape(-1, 3, 3),
            order,
        )
        shift = np.zeros(3, np.int64)
        levels = 0
    else:
        yield Progress("initial guess", 0, 1, "estimating the rigid shift")
        shift = (
            global_shift(reference, deformed)
            if rigid_shift is None
            else np.rint(np.asarray(rigid_shift, np.float64)).astype(np.int64).reshape(3)
        )
        levels = pyramid_levels(radius, params.subvolume, reference.shape)
        guess_params = None
        for lev in range(levels, -1, -1):
            level = (
                fine
                if lev == 0
                else PyramidLevel.build(
                    2**lev,
                    reference,
                    deformed,
                    mask,
                    max(4, half // 2**lev),
                    params.min_texture,
                    device.kind,
                    std=None if texture_std is None else texture_std[2**lev],
                )
            )
            level_centers = level.centers_from_fine(centers)
            if guess_params is None:
                coarse_radius = int(np.ceil(radius / 2**lev)) + (1 if lev else 0)
                guess_params = _seed_guesses(
                    level, level_centers, grid_shape, shift / 2**lev, coarse_radius, order, params
                )
                yield Progress("initial guess", 1, levels + 2, f"seeds matched (level {lev})")
            if lev == 0:
                break
            before = guess_params.copy()
            zncc_l, status_l, its_l = level.match(level_centers, guess_params, order, params)
            _repair(
                level,
                level_centers,
                grid_shape,
                guess_params,
                zncc_l,
                status_l,
                its_l,
                order,
                params,
            )
            failed = ~np.isin(status_l, _GOOD)
            guess_params[failed] = before[failed]  # keep the carried guess where matching failed
            shaped = guess_params.reshape(-1, 3, nb)
            shaped[:, :, 0] *= 2.0  # displacement in the next finer voxels
            if nb == 10:
                shaped[:, :, 4:] /= 2.0  # second derivatives scale with 1 / factor
            yield Progress("initial guess", levels - lev + 2, levels + 2, f"level {lev} refined")
    timings["initial_guess_s"] = time.perf_counter() - t0

    # full-resolution IC-GN in batches
    t0 = time.perf_counter()
    params_out = np.ascontiguousarray(guess_params, dtype=np.float64)
    zncc = np.full(n_points, np.nan)
    status = np.full(n_points, int(Status.OUT_OF_BOUNDS), np.int64)
    iterations = np.zeros(n_points, np.int64)
    todo = np.flatnonzero(inside)
    batch = params.batch_size
    for start in range(0, len(todo), batch):
        index = todo[start : start + batch]
        sub_params = np.ascontiguousarray(params_out[index])
        z_b, s_b, i_b = fine.match(centers[index], sub_params, order, params)
        params_out[index] = sub_params
        zncc[index] = z_b
        status[index] = s_b
        iterations[index] = i_b
        yield Progress(
            "IC-GN",
            min(start + batch, len(todo)),
            len(todo),
            f"matched {min(start + batch, len(todo))} of {len(todo)} POIs",
        )
    timings["icgn_s"] = time.perf_counter() - t0
    timings["voxel_iterations"] = int(iterations.sum()) * params.subvolume**3

    # imaging noise and the ZNCC threshold it allows (noise_aware_thresholds)
    t0 = time.perf_counter()
    variance = np.full(n_points, np.nan)
    power = np.full(n_points, np.nan)
    sigma = np.full((n_points, 3), np.nan)
    stats = (variance, power, sigma)
    cheap = np.zeros(len(todo), bool)
    fine.statistics(centers[todo], params_out[todo], zncc[todo], order, cheap, stats, todo)
    floor = ZNCC_SIGNIFICANCE * np.sqrt(3 * nb / params.subvolume**3)
    noise_variance, perfect, thresholds = noise_aware_thresholds(
        variance, zncc, status, params.min_zncc, floor
    )
    textureless = np.isin(status, _GOOD) & (perfect < MIN_PERFECT_ZNCC)
    status[textureless] = int(Status.LOW_TEXTURE)
    timings["noise_s"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    before = params_out.copy()
    yield Progress("repair", 0, 1, "re-matching failed POIs from their neighbours")
    _repair(
        fine, centers, grid_shape, params_out, zncc, status, iterations, order, params, thresholds
    )
    timings["repair_s"] = time.perf_counter() - t0

    low = np.isin(status, _GOOD) & ~(zncc >= thresholds)
    status[low] = int(Status.LOW_ZNCC)
    t0 = time.perf_counter()
    # where the reference's noise is a sizeable part of H, measure the sensitivity A; elsewhere
    # keep the first pass's estimate unless the repair changed the match
    noisy = 3.0 * NOISE_GRADIENT_GAIN * noise_variance > SENSITIVITY_FRACTION * power
    changed = np.any(params_out != before, axis=1)
    measured = np.isin(status, np.r_[_GOOD, [int(Status.LOW_ZNCC)]])
    redo = np.flatnonzero(measured & (noisy | changed))
    fine.statistics(centers[redo], params_out[redo], zncc[redo], order, noisy[redo], stats, redo)
    timings["uncertainty_s"] = time.perf_counter() - t0
    bound, unsure = uncertainty_bound(sigma, status)
    status[unsure] = int(Status.LOW_ZNCC)
    displacement, gradient = shape_function.params_to_displacement(params_out, order)
    failed = ~np.isin(status, np.r_[_GOOD, [int(Status.LOW_ZNCC)]])
    displacement[failed] = np.nan
    gradient[failed] = np.nan
    sigma[failed] = np.nan
    provenance = np.full(n_points, int(Provenance.MEASURED), np.uint8)
    provenance[status == int(Status.MASKED)] = int(Provenance.MASKED)
    timings["total_s"] = time.perf_counter() - start_time
    field = DisplacementField(
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
        metadata={
            "volume_shape": list(reference.shape),
            "global_shift": [int(s) for s in shift],
            "pyramid_levels": int(levels),
            "timings": timings,
            "masked": mask is not None,
            "device": device.description,
            "noise": {
                **_noise_metadata(noise_variance, thresholds, status, params.min_zncc),
                "zncc_threshold_floor": float(floor),
                "uncertainty_bound": bound,
                "uncertain": int(unsure.sum()),
            },
        },
    )
    yield Progress("done", 1, 1, f"{int(np.isin(status, _GOOD).sum())} of {n_points} POIs matched")
    return field


def _noise_metadata(noise_variance, thresholds, status, min_zncc):
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


# correlate repeats correlate_iter's signature (the duplicate finder pairs them): the blocking
# form of the generator keeps the same keywords, spelt out so that help() shows them.
def correlate(
    reference: np.ndarray,
    deformed: np.ndarray,
    params: CorrelationParams | None = None,
    *,
    mask: np.ndarray | None = None,
    grid: tuple | None = None,
    initial: DisplacementField | None = None,
    rigid_shift=None,
    device="cpu",
    texture_std=None,
) -> DisplacementField:
    """Blocking form of :func:`correlate_iter` (same parameters, no progress)."""
    return run_to_completion(
        correlate_iter(
            reference,
            deformed,
            params,
            mask=mask,
            grid=grid,
            initial=initial,
            rigid_shift=rigid_shift,
            device=device,
            texture_std=texture_std,
        )
    )
