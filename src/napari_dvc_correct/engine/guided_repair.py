"""Reliability-guided repair of failed POIs and the seed search that starts every POI.

:func:`seed_guesses` searches a sparse set of seed POIs by FFT cross-correlation and gives every
POI the affine warp of its nearest good seed; :func:`repair` re-matches failed and outlying POIs
from their best neighbours, best ZNCC first (Pan 2009). Both work on one pyramid level
(:class:`.correlate.PyramidLevel`, passed in); warps are shape-function parameters (voxels).
"""

from __future__ import annotations

import heapq

import numpy as np
from scipy import ndimage

from . import shape_function
from .cleaning import normalized_median_test
from .field import GOOD_STATUSES, Status
from .initial_guess import fft_search

_GOOD = np.array([int(s) for s in GOOD_STATUSES])


def neighbour_outliers(u, usable, grid_shape, threshold=2.0, noise=0.1):
    """Usable POIs (flat mask) that fail the normalised median test over their 26 neighbours."""
    residual = normalized_median_test(
        u.reshape(*grid_shape, 3), usable.reshape(grid_shape), epsilon=noise
    )
    return (np.nan_to_num(residual, nan=0.0) > threshold).reshape(-1) & usable


def is_good(status, zncc, min_zncc):
    return np.isin(status, _GOOD) & (zncc >= min_zncc)


def repair(
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
    good = is_good(status, zncc, thresholds)
    try_again = np.isin(status, [int(Status.MASKED), int(Status.LOW_TEXTURE)])
    if good.sum() >= settings.median_test_min_pois:
        good &= ~neighbour_outliers(
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


def seed_guesses(level, centers, grid_shape, shift, radius, order, settings):
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
    good = is_good(status, zncc, settings.min_zncc)
    if good.sum() >= settings.median_test_min_pois:
        seed_u = np.full((*[len(a) for a in axes], 3), np.nan)
        seed_u.reshape(-1, 3)[:] = shape_function.params_to_displacement(seed_params, order)[0]
        good &= ~neighbour_outliers(seed_u.reshape(-1, 3), good, seed_u.shape[:3])
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
