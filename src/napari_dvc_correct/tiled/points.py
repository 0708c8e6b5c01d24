"""Points of interest in scans larger than memory: :func:`..engine.correlation.correlate_points.correlate_points`
region by region.

1. The guide field on a grid a step beyond the points' bounding box, out of core
   (:func:`.correlate.correlate_tiled_iter`): every point's starting warp, as in memory.
2. The points in spatial groups (cubes of ``group_voxels`` voxels); each group's region — its
   points' subvolumes, where the guide sends them in ``F`` and the room IC-GN's updates and the
   B-spline prefilter need (:func:`.memory.halo` with an initial guess) — is read once,
   prefiltered and matched as in memory, with the whole reference's gray standard deviation for
   the texture test.
3. All points judged together (:func:`..engine.correlation.correlate_points.points_field`): the noise is
   the median over every point, as in memory.

The result equals the in-memory one within the IC-GN tolerance (the guide is the tiled field,
equal to the in-memory guide to ~1e-7 voxel). Groups run as Dask tasks, on local threads or a
``dask.distributed`` cluster; the peak memory is estimated, and the run refused, before any
point is matched.
"""

from __future__ import annotations

import os
import time
from collections.abc import Generator
from dataclasses import dataclass

import numpy as np

from ..engine.backend import select_device
from ..engine.correlation.correlate import validate_pair
from ..engine.correlation.correlate_points import (
    PointMatches,
    check_points,
    guide_grid,
    matched_variance,
    points_field,
    starting_warps,
)
from ..engine.correlation.params import CorrelationParams
from ..engine.correlation.pyramid import PyramidLevel
from ..engine.correlation.shape_function import params_to_displacement
from ..engine.fields.field import Status
from ..engine.fields.scattered import ScatteredField
from ..engine.progress import Progress, run_to_completion
from . import scheduling
from .batches import read_regions
from .correlate import correlate_tiled_iter, lazy_pair
from .memory import (
    BYTES_PER_BATCH_POINT,
    BYTES_PER_REGION_VOXEL,
    MemoryBudgetError,
    _region,
    available_memory,
    format_bytes,
    halo,
    parse_memory,
)

#: Edge (voxels) of the cubes the points are grouped in by default: a group's region is this
#: plus the halo on each side (about 200³ voxels, 0.4 GB, for 31³ subvolumes).
DEFAULT_GROUP_VOXELS = 128

#: Smallest group edge :func:`correlate_points_tiled_iter` shrinks to under ``max_memory``.
MIN_GROUP_VOXELS = 8

#: Layers of neighbouring POIs matched around each batch of the guide field
#: (:func:`.correlate.correlate_tiled_iter`'s ``margin``). The margin makes a tiled field equal
#: the in-memory one at the batches' faces, to the IC-GN tolerance's trace; a guide only starts
#: the points' own IC-GN, so none is needed (4.4× less guide work with 3³-POI batches).
GUIDE_MARGIN = 0


@dataclass
class PointGroup:
    """What one group's task needs: its points (indices into the matched points), their
    centres (voxels of the whole volume), starting warps and the region ``[low, high)``."""

    index: np.ndarray
    centers: np.ndarray
    trial: np.ndarray
    region_low: np.ndarray
    region_high: np.ndarray
    params: CorrelationParams
    std: float
    use_mask: bool
    device: str
    threads: int | None

    @property
    def region_voxels(self) -> int:
        return int(np.prod(self.region_high - self.region_low))


def match_group(group: PointGroup, reference, deformed, mask=None) -> PointMatches:
    """One task: read the group's region, match its points as in memory (their
    :class:`..engine.correlation.correlate_points.PointMatches`, in the order of ``group.index``)."""
    g, f, m = read_regions(group, reference, deformed, mask)
    n = len(group.index)
    trial = group.trial.copy()
    if m is not None and not m.any():  # no material here: every point is masked, as in memory
        status = np.full(n, int(Status.MASKED), np.int64)
        return PointMatches(
            trial, np.full(n, np.nan), status, np.zeros(n, np.int64), np.full(n, np.nan)
        )
    params = group.params
    g, f, m = validate_pair(g, f, params, m)
    level = PyramidLevel.build(
        1, g, f, m, params.half, params.min_texture, select_device(group.device).kind, std=group.std,
        weights=params.subvolume_weights(),
    )  # fmt: skip
    centers = group.centers - group.region_low
    zncc, status, iterations = level.match(centers, trial, params.order, params)
    variance = matched_variance(level, centers, trial, zncc, status, params.order)
    return PointMatches(trial, zncc, status, iterations, variance)


def _groups(centers, trial, shifts, params, shape, edge, std, options) -> list[PointGroup]:
    """The points in cubes of ``edge`` voxels, each with the region its matches read."""
    reaches = halo(params, 0)
    cells = centers // int(edge)
    order = np.lexsort(cells.T[::-1])
    _, starts = np.unique(cells[order], axis=0, return_index=True)
    groups = []
    for k, start in enumerate(starts):
        stop = starts[k + 1] if k + 1 < len(starts) else len(order)
        index = np.sort(order[start:stop])
        c = centers[index]
        lo, hi = _region(
            c.min(axis=0), c.max(axis=0), shifts[index].min(axis=0), shifts[index].max(axis=0),
            reaches, 1, shape,
        )  # fmt: skip
        groups.append(PointGroup(index, c, trial[index], lo, hi, params, std, **options))
    return groups


def _group_bytes(group: PointGroup, itemsize: int, masked: bool) -> float:
    per_voxel = BYTES_PER_REGION_VOXEL + itemsize + (2 if masked else 0)
    return group.region_voxels * per_voxel + len(group.index) * BYTES_PER_BATCH_POINT


def correlate_points_tiled_iter(
    reference,
    deformed,
    points,
    params: CorrelationParams | None = None,
    *,
    mask=None,
    group_voxels: int | None = None,
    max_memory: int | str | None = None,
    workers: int | None = None,
    scheduler=None,
    device="cpu",
    **guide_options,
) -> Generator[Progress, None, ScatteredField]:
    """Correlate at the given points, reading only the regions they need; yields progress.

    Parameters
    ----------
    reference, deformed : LazyVolume, path or array, shape (nz, ny, nx)
        The volumes, read region by region (:func:`..io.lazy.as_lazy`).
    points : array-like, shape (N, 3)
        Positions ``(z, y, x)`` in reference voxels, as for
        :func:`..engine.correlation.correlate_points.correlate_points`.
    params : CorrelationParams, optional
        Subvolume, shape function... (``step`` is the guide grid's).
    mask : LazyVolume, path or array, optional
        Reference-space mask of the material (non-zero = inside).
    group_voxels : int, optional
        Edge of the cubes the points are grouped in (default :data:`DEFAULT_GROUP_VOXELS`,
        smaller when ``max_memory`` asks).
    max_memory : int or str, optional
        Peak memory the run may use (``"2GB"``...); the guide's run obeys it too.
    workers : int, optional
        Groups matched at once on this machine (default ``min(4, cores)``).
    scheduler : None, "threads", "sync", str or distributed.Client
        As for :func:`.correlate.correlate_tiled_iter`.
    device : {"cpu", "cuda", "auto"}
        Where IC-GN runs.
    **guide_options
        Further keyword arguments of the guide's :func:`.correlate.correlate_tiled_iter`
        (``batch_shape``, ``margin``...).

    Returns
    -------
    ScatteredField
        As :func:`..engine.correlation.correlate_points.correlate_points`; ``metadata["tiled"]`` records the
        groups, the largest region and the memory estimate.

    Raises
    ------
    ValueError
        For bad points or volumes (as in memory); :class:`.memory.MemoryBudgetError` when even
        the smallest groups would exceed the memory allowed.
    """
    started = time.perf_counter()
    params = CorrelationParams() if params is None else params
    reference, deformed, mask = lazy_pair(reference, deformed, mask, params)
    shape = tuple(int(n) for n in reference.shape)
    points, centers, inside = check_points(points, shape, params)
    max_memory = None if max_memory is None else parse_memory(max_memory)
    budget = available_memory() if max_memory is None else min(available_memory(), max_memory)
    cores = os.cpu_count() or 1
    local = scheduling.is_local(scheduler)
    workers = min(4, cores) if workers is None else int(workers)
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    # the plan before any work: the smallest groups must fit (a point's own region)
    itemsize = np.dtype(np.result_type(reference.dtype, deformed.dtype)).itemsize
    smallest = (2 * sum(halo(params, 0)) + 1) ** 3 * (BYTES_PER_REGION_VOXEL + itemsize + 2)
    if smallest * (workers if local else 1) > budget:
        raise MemoryBudgetError(
            f"matching one point needs an estimated {format_bytes(smallest)} per task, more "
            f"than the {format_bytes(budget)} allowed for {workers} concurrent task(s): use "
            "fewer workers or a smaller subvolume"
        )

    # the guide only starts the points' IC-GN, which converges to the same match from any
    # start near it: its batches need no margin of neighbouring POIs (GUIDE_MARGIN)
    guide_options = {"margin": GUIDE_MARGIN, **guide_options}
    guide = yield from correlate_tiled_iter(
        reference,
        deformed,
        params,
        mask=mask,
        grid=guide_grid(shape, points[inside], params),
        max_memory=max_memory,
        workers=workers,
        scheduler=scheduler,
        device=device,
        **guide_options,
    )
    guide_seconds = time.perf_counter() - started
    std = float(guide.metadata["tiled"]["reference_gray_std"])
    order = params.order
    matched_centers = centers[inside]
    trial = starting_warps(guide, matched_centers, order)
    shifts, _ = params_to_displacement(trial, order)  # where the guide sends each centre
    options = dict(
        use_mask=mask is not None,
        device=device,
        threads=max(1, cores // workers) if local else 1,
    )
    edge = int(group_voxels or DEFAULT_GROUP_VOXELS)
    while True:  # the largest cubes whose regions fit the memory allowed
        groups = _groups(matched_centers, trial, shifts, params, shape, edge, std, options)
        largest = max(groups, key=lambda group: group.region_voxels)
        estimate = (workers if local else 1) * _group_bytes(largest, itemsize, mask is not None)
        if estimate <= budget or edge <= MIN_GROUP_VOXELS:
            break
        edge = max(MIN_GROUP_VOXELS, edge // 2)
    if estimate > budget:
        raise MemoryBudgetError(
            f"the points' regions need an estimated {format_bytes(estimate)}, more than the "
            f"{format_bytes(budget)} allowed: use fewer workers or a larger --max-memory"
        )
    yield Progress(
        "plan",
        1,
        1,
        f"{len(groups)} groups of points, largest region {largest.region_voxels:,} voxels, "
        f"estimated peak {format_bytes(estimate)} (allowed {format_bytes(budget)})",
    )

    import dask

    n = len(matched_centers)
    matches = PointMatches(
        trial,
        np.full(n, np.nan),
        np.full(n, int(Status.NOT_COMPUTED), np.int64),
        np.zeros(n, np.int64),
        np.full(n, np.nan),
    )
    volumes = [None if v is None else dask.delayed(v) for v in (reference, deformed, mask)]
    task = dask.delayed(match_group, pure=False)
    client, owns_client = (None, False)
    if not local:
        client, owns_client = scheduling.connect(scheduler)
    t0 = time.perf_counter()
    try:
        tasks = [task(group, *volumes) for group in groups]
        with scheduling.running(tasks, scheduler, workers, client) as finished:
            for done, (i, group_matches) in enumerate(finished, start=1):
                index = groups[i].index
                for name in ("trial", "zncc", "status", "iterations", "variance"):
                    getattr(matches, name)[index] = getattr(group_matches, name)
                yield Progress("IC-GN", done, len(groups), f"group {done} of {len(groups)}")
    finally:
        if owns_client:
            client.close()
    result = points_field(points, centers, inside, matches, params, guide)
    result.metadata.update(
        volume_shape=list(shape),
        device=select_device(device).description,
        timings={
            "total_s": time.perf_counter() - started,
            "guide_s": guide_seconds,
            "points_s": time.perf_counter() - t0,
        },
        tiled={
            "groups": len(groups),
            "group_voxels": edge,
            "largest_region_voxels": largest.region_voxels,
            "estimated_peak_bytes": int(estimate),
            "workers": workers,
            "scheduler": "local threads" if local else str(scheduler),
            "guide": guide.metadata.get("tiled", {}),
        },
    )
    good = int(np.count_nonzero(result.valid))
    yield Progress("done", 1, 1, f"{good} of {len(points)} points matched")
    return result


def correlate_points_tiled(reference, deformed, points, params=None, **kwargs) -> ScatteredField:
    """Blocking form of :func:`correlate_points_tiled_iter` (same parameters, no progress)."""
    return run_to_completion(
        correlate_points_tiled_iter(reference, deformed, points, params, **kwargs)
    )
