"""Reliability-guided repair of failed POIs and the seed search that starts every POI.

:func:`seed_guesses` searches a sparse set of seed POIs by FFT cross-correlation and gives every
POI the affine warp of its nearest good seed; :func:`repair` re-matches failed and outlying POIs
from their best neighbours, best ZNCC first (Pan 2009). Both work on one pyramid level
(:class:`.correlate.PyramidLevel`, passed in); warps are shape-function parameters (voxels).
"""

from __future__ import annotations

import heapq
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from ..correction.cleaning import normalized_median_test
from ..fields.field import GOOD_STATUSES, Status
from . import shape_function
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


#: The 26 neighbour offsets ``(dz, dy, dx)`` in the order the repair visits them.
_OFFSETS = [
    (a, b, c) for a in (-1, 0, 1) for b in (-1, 0, 1) for c in (-1, 0, 1) if (a, b, c) != (0, 0, 0)
]

#: Re-matches the repair computes in one parallel call (:func:`repair`'s ``batch``).
REPAIR_BATCH = 64


def _neighbour_table(grid_shape):
    """Flat indices of each POI's 26 neighbours in :data:`_OFFSETS` order, -1 outside the grid.

    Returns ndarray of int64, shape (N, 26).
    """
    shape = np.asarray(grid_shape, np.int64)
    index = np.arange(int(np.prod(shape))).reshape(tuple(shape))
    padded = np.pad(index, 1, constant_values=-1)
    n0, n1, n2 = (int(n) for n in shape)
    table = np.empty((*index.shape, len(_OFFSETS)), np.int64)
    for column, (a, b, c) in enumerate(_OFFSETS):
        table[..., column] = padded[1 + a : 1 + a + n0, 1 + b : 1 + b + n1, 1 + c : 1 + c + n2]
    return table.reshape(-1, len(_OFFSETS))


class _Trials:
    """Re-matches of the repair, ``(i, j)``: POI ``j`` from POI ``i``'s final warp, cached.

    A trial's result depends only on ``i``'s warp, which is final once ``i`` is on the repair's
    heap, and on ``j``; so trials may be computed ahead of the order in which the repair reads
    them, many in one parallel call, and the repair reads exactly what it would have computed
    one at a time. A trial computed ahead from the warp ``i`` was expected to get (a POI the
    look-ahead saw repaired) is read only if ``i`` got that warp (:meth:`get`).
    """

    def __init__(self, level, centers, params, order, settings):
        self.level, self.centers, self.params = level, centers, params
        self.order, self.settings = order, settings
        self.nb = shape_function.n_monomials(order)
        self.results = {}
        self.expected = {}  # POI -> warp it gets in the look-ahead (not yet in params)
        self.computed = 0
        self.calls = 0

    def warp(self, i):
        """POI ``i``'s warp: its final one, or the one the look-ahead expects it to get."""
        return self.expected.get(i, self.params[i])

    def get(self, i, j):
        """The computed trial ``(i, j)`` if it started from ``i``'s warp now, else None."""
        result = self.results.get((i, j))
        if result is None or not np.array_equal(result[0], self.params[i]):
            return None
        return result[1:]

    def compute(self, pairs):
        """Match every ``(i, j)`` of ``pairs`` in one call."""
        j = np.array([p[1] for p in pairs], np.int64)
        trial = np.empty((len(pairs), 3 * self.nb))
        sources = []
        for row, (i, k) in enumerate(pairs):
            # u + ∇u·Δ, computed as the one-at-a-time repair computed it (a fresh 3×nb copy and
            # numpy's matrix-vector product, whose last bits depend on the operands' layout)
            source = self.warp(i)
            sources.append(source)
            guess = source.reshape(3, self.nb).copy()
            delta = (self.centers[k] - self.centers[i]).astype(np.float64)
            guess[:, 0] += guess[:, 1:4] @ delta
            trial[row] = guess.reshape(-1)
        t_zncc, t_status, t_its = self.level.match(
            self.centers[j], trial, self.order, self.settings
        )
        for row, pair in enumerate(pairs):
            self.results[pair] = (sources[row], trial[row], t_zncc[row], t_status[row], t_its[row])
        self.computed += len(pairs)
        self.calls += 1


def _lookahead(first, heap, bad, attempts, max_attempts, neighbours, trials, limit):
    """The trials the repair will most likely read next, after ``first`` (uncomputed pairs).

    Runs the repair forward on copies of its state: computed trials count with their results,
    uncomputed ones are collected (at most ``limit``) and their POI is left alone until its
    result is known. The repair reads them unless a POI it repairs meanwhile jumps the queue.
    """
    pairs = list(first)
    pending = {j for _, j in pairs}
    heap = list(heap)  # a copy, already a heap
    bad = bad.copy()
    attempts = attempts.copy()
    trials.expected = {}
    while heap and len(pairs) < limit:
        _, i = heapq.heappop(heap)
        for j in neighbours[i]:
            if j < 0 or not bad[j] or attempts[j] >= max_attempts[j] or j in pending:
                continue
            result = trials.results.get((i, j))
            if result is None or not np.array_equal(result[0], trials.warp(i)):
                pairs.append((i, j))
                pending.add(j)
                if len(pairs) >= limit:
                    break
                continue
            attempts[j] += 1
            if result[3] in _GOOD and result[2] >= trials.thresholds[j]:
                bad[j] = False
                trials.expected[j] = result[1]
                heapq.heappush(heap, (-result[2], j))
    return pairs


def _subvolume_fits(level, centers):
    """POIs (N,) whose ``2·half + 1`` subvolume lies inside ``level``'s reference volume."""
    high = np.asarray(level.reference.shape[:3], np.int64) - 1 - int(level.half)
    return np.all((centers >= int(level.half)) & (centers <= high), axis=1)


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
    *,
    batch=REPAIR_BATCH,
    counts=None,
):
    """Reliability-guided propagation into POIs that failed or are outliers.

    POIs are taken best first (highest ZNCC); each bad 26-neighbour is matched again with the
    popped POI's warp carried over to its position (``u + ∇u·Δ``). A new match replaces the old
    one when it converges above its ZNCC threshold (``thresholds`` (N,): the noise-aware
    ``min_zncc · ZNCC*`` of :func:`.noise.noise_aware_thresholds` at full resolution; default,
    where ``ZNCC*`` is not estimated (the coarse levels of the initial guess),
    ``settings.min_zncc`` itself, the ceiling of those thresholds); it then seeds its own
    neighbours.

    The re-matches are computed ``batch`` at a time in one parallel call, ahead of the order in
    which they are read (:func:`_lookahead`); each depends only on its two POIs, so the result
    is the one of matching them one at a time (``batch=1``), in the same order. ``counts``
    (dict, optional) receives ``repair_trials`` (re-matches read), ``repair_matches``
    (computed; the difference was computed ahead and not needed) and ``repair_calls``.
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
    # a POI whose subvolume does not fit in the volume around its centre (a node of a given
    # grid near the border) cannot be matched: the kernels read its subvolume unchecked
    unfit = bad & ~_subvolume_fits(level, centers)
    bad &= ~unfit
    neighbours = _neighbour_table(grid_shape)
    heap = [(-zncc[i], i) for i in np.flatnonzero(good)]
    heapq.heapify(heap)
    attempts = np.zeros(len(centers), np.int64)
    max_attempts = np.where(
        status == int(Status.OUT_OF_BOUNDS),
        settings.repair_attempts_out_of_bounds,
        settings.repair_attempts,
    )
    trials = _Trials(level, centers, params, order, settings)
    trials.thresholds = thresholds
    read = 0
    remaining = int(bad.sum())
    while heap and remaining:
        _, i = heapq.heappop(heap)
        row = neighbours[i]
        row = row[row >= 0]
        todo = row[bad[row] & (attempts[row] < max_attempts[row])]
        if len(todo) == 0:
            continue
        missing = [(i, int(j)) for j in todo if trials.get(i, int(j)) is None]
        if missing:
            trials.compute(
                _lookahead(
                    missing, heap, bad, attempts, max_attempts, neighbours, trials,
                    max(batch, len(missing)),
                )
            )  # fmt: skip
        for j in todo:
            j = int(j)
            attempts[j] += 1
            trial, t_zncc, t_status, t_its = trials.get(i, j)
            del trials.results[(i, j)]
            read += 1
            if t_status in _GOOD and t_zncc >= thresholds[j]:
                params[j] = trial
                zncc[j] = t_zncc
                status[j] = t_status
                iterations[j] = t_its
                bad[j] = False
                remaining -= 1
                heapq.heappush(heap, (-zncc[j], j))
    if counts is not None:
        counts["repair_trials"] = counts.get("repair_trials", 0) + read
        counts["repair_matches"] = counts.get("repair_matches", 0) + trials.computed
        counts["repair_calls"] = counts.get("repair_calls", 0) + trials.calls
    return int(bad.sum() + unfit.sum())


def _whole_seed_axis(total, stride):
    """Seed indices along one axis of the whole grid: every ``stride`` POIs and the last."""
    return np.unique(np.r_[np.arange(0, int(total), stride), int(total) - 1])


def seed_axes(grid_shape, stride, anchor=None):
    """Indices of the seed POIs along each axis of a POI grid, laid out on the whole grid.

    Seeds sit at whole-grid indices ``0, stride, 2·stride…`` and at the whole grid's last index.
    ``anchor`` is ``(offset, whole_shape)`` when the grid is the box of a larger grid that starts
    at whole-grid index ``offset`` (a batch of :mod:`..tiled`); the seeds are then those of the
    whole grid that fall in the box, so every batch uses the in-memory run's seeds. Default: the
    grid is the whole grid.

    Returns
    -------
    list of 3 int ndarrays
        Local indices (into ``grid_shape``), increasing; an axis may be empty in a box narrower
        than ``stride``.
    """
    offset, whole = ((0, 0, 0), grid_shape) if anchor is None else anchor
    axes = []
    for n, first, total in zip(grid_shape, offset, whole):
        first, total = int(first), int(total)
        if not (0 <= first and first + int(n) <= total):
            raise ValueError(f"grid box at {offset} of shape {grid_shape} exceeds the grid {whole}")
        index = _whole_seed_axis(total, stride) - first
        axes.append(index[(index >= 0) & (index < n)])
    return axes


def _testable_seeds(axes, grid_shape, stride, anchor):
    """Seeds whose median test (:func:`neighbour_outliers` on the seeds' sub-grid) sees in the
    box what it sees in the whole grid, and the whole grid's number of seeds.

    The test of a seed reads its 26 neighbours on the seeds' sub-grid, or the values extrapolated
    from the two next seeds where the whole grid ends (:func:`.cleaning.normalized_median_test`):
    a seed at a face of the box that is not a face of the whole grid lacks neighbours there.

    Returns
    -------
    testable : ndarray of bool, shape (n_seeds,)
        C order of the seeds' sub-grid.
    whole_count : int
    """
    offset, whole = ((0, 0, 0), grid_shape) if anchor is None else anchor
    per_axis = []
    whole_count = 1
    for index, first, total in zip(axes, offset, whole):
        full = _whole_seed_axis(total, stride)
        whole_count *= len(full)
        m = len(index)
        ok = np.ones(m, bool)
        complete = m >= 3 or m == len(full)  # the border's extrapolation reads two more seeds
        if m and not (index[0] + first == full[0] and complete):
            ok[0] = False
        if m and not (index[-1] + first == full[-1] and complete):
            ok[-1] = False
        per_axis.append(ok)
    testable = per_axis[0][:, None, None] & per_axis[1][None, :, None] & per_axis[2][None, None, :]
    return testable.reshape(-1), whole_count


@dataclass
class GivenSeeds:
    """Seeds matched and judged on the whole grid, handed to a box of it (:mod:`..tiled`).

    :func:`seed_guesses` then carries these seeds' warps instead of searching its own seeds, so
    every POI of the box starts from the in-memory run's guess.

    Attributes
    ----------
    levels : int
        Pyramid levels of the whole volume (the seeds' level has factor ``2**levels``); the box
        uses these rather than counting levels from its region's size.
    params : ndarray, shape (S, 3·nb)
        Shape-function parameters of the good seeds the box needs, in voxels of that level.
    centers : ndarray of int, shape (S, 3)
        Their centres at that level, in the binned voxels of the volumes given to the box.
    source : ndarray of int, shape (N,), or None
        Row of ``params`` of each POI's nearest good seed on the whole grid (C order of the box);
        None when no seed of the whole grid is good (every POI is then searched).
    """

    levels: int
    params: np.ndarray
    centers: np.ndarray
    source: np.ndarray | None


def search_seeds(level, centers, shift, radius, order, settings):
    """FFT search within ``radius`` around ``shift`` at ``centers`` (level voxels), then IC-GN.

    Returns
    -------
    params : ndarray, shape (S, 3·nb)
    zncc, status : ndarray, shape (S,)
    """
    params = np.ascontiguousarray(_search(level, centers, shift, radius, order))
    zncc, status, _ = level.match(centers, params, order, settings)
    return params, zncc, status


def _search(level, centers, shift, radius, order):
    found, _ = fft_search(
        level.reference,
        level.deformed,
        centers,
        level.half,
        np.tile(shift, (len(centers), 1)),
        radius,
    )
    return shape_function.displacement_to_params(found, None, order)


def judge_seeds(params, zncc, status, seed_shape, order, settings, testable=None, count=None):
    """Good seeds: converged above ``settings.min_zncc`` and not outliers among the seeds.

    The seeds are matched at the coarsest pyramid level, before any noise estimate: there the
    matcher's relative threshold ``min_zncc · ZNCC*`` (:class:`.params.CorrelationParams`) falls
    back to ``min_zncc`` itself, its ceiling (``ZNCC* <= 1``).

    The median test (:func:`neighbour_outliers` on the seeds' sub-grid ``seed_shape``, C order)
    runs when ``count`` (default: the number of good seeds) reaches
    ``settings.median_test_min_pois``; it judges only the ``testable`` seeds (default all).
    """
    good = is_good(status, zncc, settings.min_zncc)
    if (good.sum() if count is None else count) >= settings.median_test_min_pois:
        seed_u = np.full((*seed_shape, 3), np.nan)
        seed_u.reshape(-1, 3)[:] = shape_function.params_to_displacement(params, order)[0]
        outliers = neighbour_outliers(seed_u.reshape(-1, 3), good, seed_u.shape[:3])
        good &= ~(outliers if testable is None else outliers & testable)
    return good


def nearest_seeds(good_grid):
    """Flat index (C order) of the nearest ``True`` node of ``good_grid`` for every node.

    :func:`scipy.ndimage.distance_transform_edt` on the whole grid; ties are broken as it breaks
    them. Memory: about 21 bytes per node.
    """
    nearest = ndimage.distance_transform_edt(
        ~good_grid, return_distances=False, return_indices=True
    )
    return np.ravel_multi_index(tuple(nearest.reshape(3, -1)), good_grid.shape)


def carry_seeds(params, seed_centers, centers, order):
    """Each POI's seed warp (rows ``params``, at ``seed_centers``) carried to ``centers``:
    ``u + ∇u·Δ`` (affine part)."""
    nb = shape_function.n_monomials(order)
    guesses = params.reshape(len(centers), 3, nb).copy()
    delta = (centers - seed_centers).astype(np.float64)
    guesses[:, :, 0] += np.einsum("nkl,nl->nk", guesses[:, :, 1:4], delta)
    return np.ascontiguousarray(guesses.reshape(len(centers), 3 * nb))


def seed_guesses(
    level, centers, grid_shape, shift, radius, order, settings, anchor=None, seeds=None
):
    """Initial warps for every POI from an FFT search at a sparse set of seed POIs.

    Seeds sit on a sub-grid about one subvolume apart (:func:`seed_axes`; ``anchor`` places a
    box of a larger grid on the whole grid's seeds). Each is searched by FFT cross-correlation
    within ``radius`` around the rigid ``shift`` and refined by IC-GN; seeds that fail, correlate
    poorly or disagree with the other seeds are dropped, and every POI receives the affine warp of
    its nearest good seed carried to its position. Falls back to searching every POI when no seed
    survives.

    ``seeds`` (:class:`GivenSeeds`): the seeds were matched and judged on the whole grid already
    (:mod:`..tiled`'s seed pass); each POI takes its given nearest good seed, exactly as in
    memory, and nothing is searched unless no seed is good.

    In a box with ``anchor`` and no ``seeds``, a POI gets the in-memory run's guess when its
    nearest good seed lies in the box (the nearest-seed search,
    :func:`scipy.ndimage.distance_transform_edt`, breaks ties the same way in the box as in the
    whole grid) and the seeds near it are judged as in memory: the median test judges the seeds
    whose neighbour seeds are all in the box (or beyond the whole grid's border); seeds at the
    box's other faces are kept untested, so they differ from the in-memory run only where it
    rejects them as outliers. A box whose margin reaches ``stride // 2`` POIs beyond its own POIs
    (one POI for a stride of 2 or 3) thus reproduces the in-memory guesses of its own POIs
    wherever the seeds near them converge and none is an outlier; where seeds fail, the nearest
    good seed is farther away and the margin must reach it. A box without any good seed falls
    back to searching all its POIs, which the in-memory run does only when no seed of the whole
    grid is good.

    Returns
    -------
    ndarray, shape (N, 3·nb)
        Shape-function parameters at ``level`` (voxels of that level).
    """
    n_points = len(centers)
    if seeds is not None:
        if seeds.source is None:
            return np.ascontiguousarray(_search(level, centers, shift, radius, order))
        source = np.asarray(seeds.source)
        return carry_seeds(seeds.params[source], seeds.centers[source], centers, order)
    stride = max(1, int(round(settings.subvolume / settings.step)))
    axes = seed_axes(grid_shape, stride, anchor)
    seed_grid = np.zeros(grid_shape, bool)
    seed_grid[np.ix_(*axes)] = True
    seed_index = np.flatnonzero(seed_grid)
    seed_params, zncc, status = search_seeds(
        level, centers[seed_index], shift, radius, order, settings
    )
    testable, whole_count = _testable_seeds(axes, grid_shape, stride, anchor)
    # in a box: the whole grid's count of seeds stands for its count of good ones (unknown here)
    good_count = (
        None
        if anchor is None
        else whole_count * bool(is_good(status, zncc, settings.min_zncc).any())
    )
    good = judge_seeds(
        seed_params, zncc, status, [len(a) for a in axes], order, settings, testable, good_count
    )
    if not good.any():
        return np.ascontiguousarray(_search(level, centers, shift, radius, order))
    good_grid = np.zeros(grid_shape, bool)
    good_grid.reshape(-1)[seed_index[good]] = True
    nearest_flat = nearest_seeds(good_grid)
    lookup = np.full(n_points, -1)
    lookup[seed_index] = np.arange(len(seed_index))
    source = lookup[nearest_flat]
    return carry_seeds(seed_params[source], centers[seed_index][source], centers, order)
