"""Regions and memory of tiled correlation (:mod:`.tiled`).

- :func:`halo`: how far a batch's region reaches beyond its POIs, at every pyramid level, so the
  batch sees what the whole volume would show it (subvolume, search radius, strain allowance,
  B-spline support and prefilter margin);
- :func:`estimate_peak_memory` and :func:`choose_batch_shape`: the peak memory of a run, and the
  largest batch that fits a budget (calibrated on measured resident memory);
- :func:`memory_budget` and :func:`refuse_blocks_over`: what a run may use, and the refusal of
  block-by-block work (warps, residuals) over it;
- :func:`available_memory`, :func:`parse_memory`, :func:`format_bytes`, :class:`MemoryBudgetError`.
"""

from __future__ import annotations

import inspect
import math

import numpy as np

from ..engine.correlation.initial_guess import fft_search, pyramid_levels
from ..engine.correlation.params import CorrelationParams
from ..engine.correlation.pyramid_rule import level_reach
from ..engine.fields.field import grid_for_volume
from ..engine.run_options import MAX_MEMORY_BYTES
from ..io.sizes import available_memory  # noqa: F401  (re-exported: part of this API)

#: Voxels read at a time by the whole-volume pass of :mod:`.tiled`.
SHIFT_BLOCK_VOXELS = 1 << 23

#: Voxels kept beyond every needed voxel so the region's B-spline coefficients equal the whole
#: volume's (the prefilter's error decays as |z1|^d = 0.268^d; 12 voxels reach float32 rounding).
PREFILTER_MARGIN = 12

#: The same margin at the coarse pyramid levels, in binned voxels. Those levels only provide the
#: starting guesses of the next level, so 6 binned voxels suffice (coefficient error below 1e-4
#: of the gray range at the region's edge, far less for most POIs) and keep regions smaller.
COARSE_PREFILTER_MARGIN = 6

#: Taps of the cubic B-spline beyond a sampled position.
SPLINE_SUPPORT = 2

#: Largest row sum of |du/dX| the halo allows for the deformed subvolume (25 % strain).
STRAIN_ALLOWANCE = 0.25

#: Bytes per region voxel while a batch correlates (calibrated by sampling the resident memory
#: of correlate on 96³–160³ regions: G and F as float32, the gradient of G, the coefficients of
#: F, a prefilter output and the coarse level; the stored block is counted apart).
BYTES_PER_REGION_VOXEL = 44

#: Bytes per POI of a batch (guesses, shape-function parameters, the batch's field).
BYTES_PER_BATCH_POINT = 1200

#: Bytes per POI of the assembled field (u, gradient, zncc, status... and the collected results).
BYTES_PER_FIELD_POINT = 400

#: Bytes per matched POI held between a batch's two tasks (:func:`.batches.match_batch`: the
#: shape-function parameters, up to 240 bytes at second order, ZNCC, status, iterations, centre,
#: variance, power and uncertainty), for every POI of the grid and its batch's margin.
BYTES_PER_HELD_POINT = 400

#: Bytes per POI of the seed pass's hand-out (:mod:`.correlate`): the nearest-seed search on the
#: whole grid (about 21) and the seed row of every POI (8), with some room.
BYTES_PER_SEED_POINT = 40


def _fft_search_bytes() -> int:
    """Memory of the stacked FFTs of the integer search (its ``batch_bytes`` default, doubled)."""
    try:
        default = inspect.signature(fft_search).parameters["batch_bytes"].default
        return 2 * int(default)
    except (KeyError, TypeError, ValueError):  # older signature: 128 POIs per batch
        return 256 * 2**20


class MemoryBudgetError(MemoryError, ValueError):
    """The estimated peak memory of a run exceeds what it may use (a ``ValueError`` too: the
    input asks for too much, and the command line reports it as bad input)."""


# --- memory ------------------------------------------------------------------------------------
def format_bytes(n: float) -> str:
    """Human-readable size, ``1536 -> '1.50 KiB'``."""
    for unit in ("B", "KiB", "MiB", "GiB"):
        if abs(n) < 1024:
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.2f} {unit}"
        n /= 1024.0
    return f"{n:.2f} TiB"


def parse_memory(size) -> int:
    """Bytes from an int or a size string (``"2GB"``, ``"1.5 GiB"``, ``"512M"``).

    Raises
    ------
    ValueError
        For a string that is not a size, a size ≤ 0, or one no machine has (≥ 2**62 bytes, inf).
    """
    if isinstance(size, str):
        from dask.utils import parse_bytes

        try:
            if not size.strip()[:1].isdigit() and size.strip()[:1] not in ("-", "+", "."):
                raise ValueError("no number")  # parse_bytes reads "" as 1 B and "GB" as 1 GB
            value = parse_bytes(size.strip())
        except (ValueError, KeyError, OverflowError) as error:  # 1e400GB: inf
            raise ValueError(
                f"{size!r} is not a memory size: use e.g. 2GB, 1.5GiB or 512MB"
            ) from error
    else:
        value = size
    if not 0 < value < MAX_MEMORY_BYTES:  # "1e400GB" parses as inf
        raise ValueError(f"a memory size must be > 0 and a size a machine can have, got {size!r}")
    return int(value)


def _levels(params: CorrelationParams, volume_shape, use_initial: bool) -> int:
    if use_initial:
        return 0
    return pyramid_levels(params.effective_search_radius, params.subvolume, volume_shape)


def halo(params: CorrelationParams, levels: int) -> tuple[int, int]:
    """Voxels needed around the POI centres in ``G`` and around their displaced centres in ``F``.

    Covers every pyramid level up to ``levels`` (a level's needs, in its binned voxels, times its
    factor, plus two factors for the rounding of binned centres). The level's subvolume and
    search radius are the engine's (:func:`..engine.correlation.pyramid.level_reach`).
    """
    reach_g, reach_f = 0, 0
    for lev in range(levels + 1):
        f, half_l, radius_l = level_reach(params, lev)
        rounding = 0 if lev == 0 else 2 * f
        margin = PREFILTER_MARGIN if lev == 0 else COARSE_PREFILTER_MARGIN
        reach_g = max(reach_g, f * (half_l + 1 + margin) + rounding)
        deformed_half = math.ceil(half_l * (1 + STRAIN_ALLOWANCE))
        reach_f = max(
            reach_f,
            f * (deformed_half + radius_l + 1 + SPLINE_SUPPORT + margin) + rounding,
        )
    return reach_g, reach_f


def _region(low_center, high_center, low_shift, high_shift, reaches, align, shape):
    """Region ``[lo, hi)`` (voxels) for POI centres in ``[low_center, high_center]``.

    ``lo`` falls on a multiple of ``align`` (so binned regions line up with the binned volume).
    """
    reach_g, reach_f = reaches
    low_center = np.asarray(low_center, np.int64)
    high_center = np.asarray(high_center, np.int64)
    low_shift = np.floor(np.asarray(low_shift, np.float64)).astype(np.int64)
    high_shift = np.ceil(np.asarray(high_shift, np.float64)).astype(np.int64)
    lo = np.minimum(low_center - reach_g, low_center + low_shift - reach_f)
    hi = np.maximum(high_center + reach_g, high_center + high_shift + reach_f) + 1
    shape = np.asarray(shape, np.int64)
    lo = np.clip((lo // align) * align, 0, shape - 1)
    hi = np.clip(hi, lo + 1, shape)
    return lo, hi


def _batch_bytes(region_voxels: float, points: int, itemsize: int, masked: bool, levels: int):
    per_voxel = BYTES_PER_REGION_VOXEL + itemsize + (2 if masked else 0)
    coarse = sum(per_voxel / 8**lev for lev in range(1, levels + 1))
    return (
        region_voxels * (per_voxel + coarse) + points * BYTES_PER_BATCH_POINT + _fft_search_bytes()
    )


def estimate_peak_memory(
    volume_shape,
    dtype,
    params: CorrelationParams | None,
    batch_shape,
    *,
    workers: int = 1,
    margin: int = 0,
    masked: bool = False,
    shift=(0, 0, 0),
    grid: tuple | None = None,
) -> int:
    """Estimated peak memory (bytes) of :func:`correlate_tiled`.

    Parameters
    ----------
    volume_shape : tuple of 3 ints
        ``(nz, ny, nx)`` of the volumes.
    dtype : numpy dtype
        Stored dtype (regions are read in it, then converted to float32).
    params : CorrelationParams
        DVC parameters (subvolume, step, search radius).
    batch_shape : tuple of 3 ints
        POIs per batch along ``(z, y, x)``.
    workers : int
        Batches held in memory at once (threads of the local scheduler; for a cluster, the
        threads of one worker give that worker's peak). 0 gives the fixed part alone.
    margin : int
        Layers of neighbouring POIs matched with each batch.
    masked : bool
        Whether a mask volume is read too.
    shift : tuple of 3 floats
        Expected rigid shift (voxels); widens the regions.
    grid : (origin, step, shape), optional
        POI grid (default :func:`grid_for_volume`).

    Returns
    -------
    int
        Bytes: ``workers`` batches (their regions at every pyramid level, the integer search's
        FFTs, their POIs) plus the assembled field, the matched POIs held between a batch's two
        tasks, the seed pass's hand-out and the blocks of the rigid-shift pass. The seed pass's tasks read a box's seeds' region, no larger than
        its batch's, and bin it to the coarsest level: they fit in a batch's estimate.
    """
    params = CorrelationParams() if params is None else params
    volume_shape = tuple(int(n) for n in volume_shape)
    if grid is None:
        grid = grid_for_volume(volume_shape, params.subvolume, params.step)
    _, step, grid_shape = grid
    grid_shape = np.asarray(grid_shape, np.int64)
    batch_shape = np.minimum(np.asarray(batch_shape, np.int64), grid_shape)
    levels = _levels(params, volume_shape, False)
    reach_g, reach_f = halo(params, levels)
    ext = np.minimum(batch_shape + 2 * margin, grid_shape)
    span = (ext - 1) * np.asarray(step, np.float64)
    reach = np.maximum(2 * reach_g, 2 * reach_f + np.abs(np.asarray(shift, np.float64)))
    extent = np.minimum(span + reach + 2**levels + 1, volume_shape)
    itemsize = np.dtype(dtype).itemsize
    batch = _batch_bytes(float(np.prod(extent)), int(np.prod(ext)), itemsize, masked, levels)
    held = BYTES_PER_HELD_POINT * float(np.prod(ext)) / float(np.prod(batch_shape))
    fixed = int(np.prod(grid_shape)) * (
        BYTES_PER_FIELD_POINT + BYTES_PER_SEED_POINT + held
    ) + SHIFT_BLOCK_VOXELS * (2 * (4 + itemsize) + 8)
    return int(max(int(workers), 0) * batch + fixed)


def choose_batch_shape(
    volume_shape, dtype, params, budget: int, *, workers=1, margin=0, masked=False, grid=None
) -> tuple[int, int, int]:
    """Largest cubic batch (clipped to the grid) whose :func:`estimate_peak_memory` fits ``budget``.

    Raises
    ------
    MemoryBudgetError
        If even a batch of one POI does not fit.
    """
    params = CorrelationParams() if params is None else params
    if grid is None:
        grid = grid_for_volume(volume_shape, params.subvolume, params.step)
    grid_shape = [int(n) for n in grid[2]]
    need = None
    for k in range(max(grid_shape), 0, -1):
        shape = tuple(min(k, n) for n in grid_shape)
        need = estimate_peak_memory(
            volume_shape,
            dtype,
            params,
            shape,
            workers=workers,
            margin=margin,
            masked=masked,
            grid=grid,
        )
        if need <= budget:
            return shape
    raise MemoryBudgetError(
        f"even one POI per batch needs an estimated {format_bytes(need)} with {workers} "
        f"concurrent batch(es), more than the {format_bytes(budget)} allowed: use fewer workers, "
        "a smaller subvolume or search radius, or allow more memory (--max-memory)"
    )


def _refuse_if_over(estimate, budget, max_memory, batch_shape, workers, where):
    if estimate <= budget:
        return
    if max_memory is not None and budget == max_memory:
        what = f"the limit of {format_bytes(max_memory)} (--max-memory)"
    else:
        what = f"the {format_bytes(budget)} available on {where}"
    raise MemoryBudgetError(
        f"this run needs an estimated {format_bytes(estimate)} at its peak ({workers} concurrent "
        f"batch(es) of {batch_shape[0]}x{batch_shape[1]}x{batch_shape[2]} POIs), more than "
        f"{what}: use smaller batches or fewer workers, let --max-memory choose the batch size, "
        "or run on a machine (or cluster workers) with more memory"
    )


def memory_budget(client, workers: int, max_memory: int | None) -> tuple[int, int, str]:
    """``(budget, concurrency, where)`` of block-by-block work.

    ``budget``: the bytes a run may use (the smallest worker memory limit of a
    ``distributed.Client``'s cluster, else this machine's :func:`available_memory`; at most
    ``max_memory``); ``concurrency``: the tasks one of them holds at once (the most threads of one
    worker, or ``workers`` locally); ``where``: the place, for messages.
    """
    from . import scheduling

    if client is not None:
        _, concurrency, limit = scheduling.cluster_resources(client)
        budget, where = (limit or available_memory()), "each worker of the cluster"
    else:
        concurrency, budget, where = int(workers), available_memory(), "this machine"
    if max_memory is not None:
        budget = min(budget, int(max_memory))
    return int(budget), int(concurrency), where


def refuse_blocks_over(need, budget, max_memory, concurrency, where, what: str) -> None:
    """Raise :class:`MemoryBudgetError` when ``need`` bytes of ``what`` (e.g. "the correction's
    warp and residual blocks"), ``concurrency`` at once, exceed ``budget``."""
    if need <= budget:
        return
    limit = (
        f"the limit of {format_bytes(max_memory)} (--max-memory)"
        if max_memory is not None and budget == max_memory
        else f"the {format_bytes(budget)} available on {where}"
    )
    raise MemoryBudgetError(
        f"{what} need an estimated {format_bytes(need)} ({concurrency} at once), more than "
        f"{limit}: use fewer workers or smaller blocks, or allow more memory (--max-memory)"
    )
