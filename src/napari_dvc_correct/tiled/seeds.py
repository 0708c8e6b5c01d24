"""The seed pass of tiled correlation: the initial guess's seeds matched once for the whole grid.

The in-memory initial guess (:func:`..engine.correlation.guided_repair.seed_guesses`) searches a sparse
sub-grid of seed POIs laid out on whole-grid indices (:func:`..engine.correlation.guided_repair.seed_axes`)
and carries every good seed's warp to its nearest POIs. Here the seeds are matched first, one
Dask task per batch box that holds seeds (:func:`match_seeds`, reading only its seeds' region),
judged once on the whole seed grid as in memory (:func:`give_seeds`), and every batch receives
the seeds its POIs need (:class:`..engine.correlation.guided_repair.GivenSeeds`), so each POI starts IC-GN
from the in-memory guess.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..engine.correlation.correlate import correlate_seeds
from ..engine.correlation.guided_repair import GivenSeeds, judge_seeds, nearest_seeds, seed_axes
from ..engine.correlation.params import CorrelationParams
from ..engine.correlation.shape_function import n_monomials
from ..engine.fields.field import Status
from .memory import _region, halo


# --- the seed pass ------------------------------------------------------------------------------
@dataclass
class SeedJob:
    """The seeds of the initial guess that fall in one batch's box (small, like :class:`.batches.BatchJob`)."""

    params: CorrelationParams
    rows: np.ndarray  # (S,) rows of these seeds in the whole grid's seed table
    centers: np.ndarray  # (S, 3) int voxels of the whole volume
    region_low: np.ndarray  # (3,) region [low, high) in voxels
    region_high: np.ndarray
    levels: int
    shift: np.ndarray
    texture_std: dict
    threads: int | None = None
    use_mask: bool = False
    device: str = "cpu"


def match_seeds(job: SeedJob, reference, deformed, mask=None):
    """Match one box's seeds in its region (:func:`.correlate.correlate_seeds`).

    Returns ``(rows, params, zncc, status, centers)``: ``centers`` at the coarsest level, in
    binned voxels of the whole volume.
    """
    if job.threads:
        import numba

        numba.set_num_threads(max(1, min(int(job.threads), numba.config.NUMBA_NUM_THREADS)))
    lo, hi = job.region_low, job.region_high
    region = tuple(slice(int(a), int(b)) for a, b in zip(lo, hi))
    f = 2**job.levels
    m = mask.read_region(region) != 0 if job.use_mask and mask is not None else None
    if m is not None and not m.any():  # no material here: the seeds are masked
        n = len(job.rows)
        nb = 3 * n_monomials(job.params.order)
        coarse = np.rint((job.centers - (f - 1) / 2.0) / f).astype(np.int64)
        status = np.full(n, int(Status.MASKED), np.int64)
        return job.rows, np.full((n, nb), np.nan), np.full(n, np.nan), status, coarse
    g = reference.read_region(region)
    d = deformed.read_region(region)
    params, zncc, status, centers = correlate_seeds(
        g,
        d,
        job.params,
        job.centers - lo,
        levels=job.levels,
        rigid_shift=job.shift,
        mask=m,
        texture_std=job.texture_std,
        device=job.device,
    )
    return job.rows, params, zncc, status, centers + lo // f


def seed_jobs(batches, params, shape, grid, levels, whole, options):
    """One :class:`SeedJob` per batch box holding seeds; the seeds' whole-grid flat indices."""
    origin, step, grid_shape = grid
    stride = max(1, int(round(params.subvolume / params.step)))
    axes = seed_axes(grid_shape, stride)
    seed_flat = np.ravel_multi_index(np.meshgrid(*axes, indexing="ij"), grid_shape).ravel()
    rows = np.arange(len(seed_flat)).reshape([len(a) for a in axes])
    reaches = halo(params, levels)
    jobs = []
    for core_ranges in batches:
        picks = [np.flatnonzero((a >= b0) & (a < b1)) for a, (b0, b1) in zip(axes, core_ranges)]
        if min(len(p) for p in picks) == 0:
            continue
        index = np.stack(np.meshgrid(*[a[p] for a, p in zip(axes, picks)], indexing="ij"), -1)
        centers = origin + step * index.reshape(-1, 3)
        lo, hi = _region(
            centers.min(0), centers.max(0), whole.shift, whole.shift, reaches, 2**levels, shape
        )
        jobs.append(
            SeedJob(
                params=params,
                rows=rows[np.ix_(*picks)].ravel(),
                centers=centers,
                region_low=lo,
                region_high=hi,
                levels=levels,
                shift=whole.shift,
                texture_std=whole.texture_std,
                **options,
            )
        )
    return jobs, seed_flat, [len(a) for a in axes]


def give_seeds(jobs, results, seed_flat, seed_shape, grid_shape, levels, params):
    """Judge the whole grid's seeds as in memory and hand each batch the seeds it needs."""
    n = len(seed_flat)
    nb3 = results[0][1].shape[1]
    seed_params = np.full((n, nb3), np.nan)
    zncc = np.full(n, np.nan)
    status = np.full(n, int(Status.NOT_COMPUTED), np.int64)
    centers = np.zeros((n, 3), np.int64)
    for rows, p, z, s, c in results:
        seed_params[rows], zncc[rows], status[rows], centers[rows] = p, z, s, c
    good = judge_seeds(seed_params, zncc, status, seed_shape, params.order, params)
    f = 2**levels
    if not good.any():
        for job in jobs:
            job.seeds = GivenSeeds(levels, seed_params[:0], centers[:0], None)
        return 0
    good_grid = np.zeros(grid_shape, bool)
    good_grid.reshape(-1)[seed_flat[good]] = True
    lookup = np.full(int(np.prod(grid_shape)), -1)
    lookup[seed_flat] = np.arange(n)
    source = lookup[nearest_seeds(good_grid)].reshape(grid_shape)
    del good_grid, lookup
    for job in jobs:
        window = tuple(slice(a, a + b) for a, b in zip(job.grid_anchor[0], job.sub_shape))
        rows, inverse = np.unique(source[window].ravel(), return_inverse=True)
        local = centers[rows] - job.region_low // f
        job.seeds = GivenSeeds(levels, seed_params[rows], local, inverse.reshape(-1))
    return int(good.sum())
