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

from . import icgn
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
class _Level:
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
        gradient = icgn.gradient_volume(prefilter(reference))
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

    def match(self, centers, params, order, settings):
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
            self.reference,
            self.gradient,
            self.coef_deformed,
            self.mask,
            self.use_mask,
            np.ascontiguousarray(centers, dtype=np.int64),
            self.half,
            icgn.n_monomials(order),
            params,
            zncc,
            status,
            iterations,
            settings.max_iterations,
            settings.tolerance,
            self.min_std,
            settings.min_mask_fraction,
            float(max(self.half, 4)),
            icgn.PRODUCT_TABLE,
            icgn.QUAD_AXES,
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


def _repair(level, centers, grid_shape, params, zncc, status, iterations, order, settings):
    """Reliability-guided propagation into POIs that failed or are outliers.

    POIs are taken best first (highest ZNCC); each bad 26-neighbour is matched again with the
    popped POI's warp carried over to its position (``u + ∇u·Δ``). A new match replaces the old
    one when it converges above ``min_zncc``; it then seeds its own neighbours.
    """
    good = _is_good(status, zncc, settings.min_zncc)
    try_again = np.isin(status, [int(Status.MASKED), int(Status.LOW_TEXTURE)])
    if good.sum() > 8:
        good &= ~_neighbour_outliers(
            icgn.params_to_displacement(params, order)[0], good, grid_shape
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
    nb = icgn.n_monomials(order)
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
    # a POI whose deformed subvolume left the volume is retried once (its guess may be wrong)
    max_attempts = np.where(status == int(Status.OUT_OF_BOUNDS), 1, 3)
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
            if t_status[0] in _GOOD and t_zncc[0] >= settings.min_zncc:
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
    nb = icgn.n_monomials(order)

    def search(index):
        found, _ = fft_search(
            level.reference,
            level.deformed,
            centers[index],
            level.half,
            np.tile(shift, (len(index), 1)),
            radius,
        )
        return icgn.displacement_to_params(found, None, order)

    seed_params = np.ascontiguousarray(search(seeds))
    zncc, status, _ = level.match(centers[seeds], seed_params, order, settings)
    good = _is_good(status, zncc, settings.min_zncc)
    if good.sum() > 8:
        seed_u = np.full((*[len(a) for a in axes], 3), np.nan)
        seed_u.reshape(-1, 3)[:] = icgn.params_to_displacement(seed_params, order)[0]
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
    nb = icgn.n_monomials(order)
    if initial is not None and initial.shape != grid_shape:
        raise ValueError(
            f"initial field grid {initial.shape} differs from the POI grid {grid_shape}"
        )

    yield Progress("prefilter", 0, 1, "prefiltering the volumes")
    t0 = time.perf_counter()
    fine = _Level.build(
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
        guess_params = icgn.displacement_to_params(
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
                else _Level.build(
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

    t0 = time.perf_counter()
    yield Progress("repair", 0, 1, "re-matching failed POIs from their neighbours")
    _repair(fine, centers, grid_shape, params_out, zncc, status, iterations, order, params)
    timings["repair_s"] = time.perf_counter() - t0

    low = np.isin(status, _GOOD) & ~(zncc >= params.min_zncc)
    status[low] = int(Status.LOW_ZNCC)
    displacement, gradient = icgn.params_to_displacement(params_out, order)
    failed = ~np.isin(status, np.r_[_GOOD, [int(Status.LOW_ZNCC)]])
    displacement[failed] = np.nan
    gradient[failed] = np.nan
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
        params=params.to_dict(),
        metadata={
            "volume_shape": list(reference.shape),
            "global_shift": [int(s) for s in shift],
            "pyramid_levels": int(levels),
            "timings": timings,
            "masked": mask is not None,
            "device": device.description,
        },
    )
    yield Progress("done", 1, 1, f"{int(np.isin(status, _GOOD).sum())} of {n_points} POIs matched")
    return field


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
