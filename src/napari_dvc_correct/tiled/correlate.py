"""Correlation beyond one machine's memory and cores: spatial batches of POIs on Dask.

:func:`correlate_tiled` gives the same :class:`DisplacementField` as
:func:`.correlate.correlate` while holding only a few regions of the volumes in memory:

1. **Whole-volume pass** (one read of both volumes, block by block, as Dask tasks): both volumes
   are binned while they are read, exactly as :func:`.initial_guess.global_shift` bins the whole
   volumes, for the rigid shift; the gray standard deviation of ``G`` (inside the mask) binned by
   every pyramid factor is accumulated for the low-texture test. The pass also checks that every
   value is finite.
2. **Seed pass**: the POI grid is split into boxes of ``batch_shape`` POIs. The seeds of the
   initial guess (every ``round(subvolume / step)`` POIs of the whole grid,
   :func:`..engine.correlation.guided_repair.seed_axes`) are matched first, one ``dask.delayed`` task per box
   that holds seeds, each reading only the region of its seeds (:func:`match_seeds`,
   :func:`.correlate.correlate_seeds`: FFT search and IC-GN at the coarsest pyramid level).
   The seeds are then judged on the whole seed grid (ZNCC, status, median test) and every POI
   is given its nearest good seed of the whole grid, exactly as
   :func:`..engine.correlation.guided_repair.seed_guesses` does in memory (``seeds=`` of
   :func:`.correlate.correlate_iter`); each batch receives the seeds its POIs need.
3. **Batches**, in two tasks each (``dask.delayed``), each reading its region of ``G`` and ``F``
   plus a halo. The first (:func:`.batches.match_batch`) runs the first half of
   :func:`.correlate.correlate_iter` (:func:`.correlate.match_iter`: the same pyramid and IC-GN
   as in memory) with the whole volume's rigid shift, gray statistics and seeds
   (``rigid_shift``, ``texture_std``, ``seeds``), on its POIs plus ``margin`` layers of
   neighbouring POIs (default 1). It returns the matched POIs and the noise estimates
   ``s² (1 − ZNCC)`` of the batch's own POIs. The noise of the scans is then the median over all
   batches' POIs, exactly the in-memory run's (:func:`..engine.correlation.noise.noise_aware_thresholds`).
   The second task (:func:`.batches.judge_batch`) judges the batch at that noise
   (:func:`..engine.correlation.match_judgement.judge_iter`: thresholds, ``LOW_TEXTURE``, the reliability-guided
   repair, ``LOW_ZNCC``, the uncertainties), reading the region again only if it repairs a POI
   or measures an uncertainty again, so that every POI gets the in-memory threshold. The margin lets the repair and the median test see, at the batch's
   border, the neighbours they see in memory (only the batch's own POIs are kept). Every POI
   starts from its in-memory guess whatever the margin; what differs without a margin is the
   repair at the full resolution, which re-matches a failed POI from its best neighbour, and
   that neighbour may lie in the next batch (measured on a rotation with failing seeds at one
   face, 4x4x10-POI batches: margin 0 left 16 of 1000 POIs up to 3.6e-4 voxel away; margin 1
   gave the in-memory field to 4e-8 voxel, the coarse prefilter at the regions' edges). A
   repair chain that runs more than ``margin`` POIs across a face still differs there.
4. The batches' results are assembled into one field, and the uncertainty bound (a median over
   the whole run's POIs too, :func:`..engine.correlation.noise.uncertainty_bound`) is applied to it.

The halo around a batch's POIs (per side, in voxels) covers the subvolume half-size widened by
:data:`.memory.STRAIN_ALLOWANCE` for the shape function, the search radius around the rigid shift, the
B-spline support (:data:`.memory.SPLINE_SUPPORT`) and :data:`.memory.PREFILTER_MARGIN` voxels, so that the region's
B-spline prefilter equals the whole volume's to float32 rounding (measured: the difference decays
as 0.27 per voxel and is below 6e-8 of the gray range after 12 voxels); coarse pyramid levels,
which only give starting guesses, keep :data:`.memory.COARSE_PREFILTER_MARGIN` binned voxels.

Scheduling (:mod:`.scheduling`): dask's local threaded scheduler by default (nothing to start);
``scheduler="ADDRESS"`` (or a ``distributed.Client``) sends the tasks to a ``dask.distributed``
cluster. Memory: the peak is estimated before anything runs (:func:`estimate_peak_memory`); a run
that would exceed the machine (or ``max_memory``) is refused with :class:`MemoryBudgetError`, and
``max_memory`` picks the batch size.
"""

from __future__ import annotations

import dataclasses
import os
import time
from collections.abc import Generator

import numpy as np

from ..engine.correlation.icgn_weighted import check_weights
from ..engine.correlation.noise import noise_metadata, uncertainty_bound, zncc_floor
from ..engine.correlation.params import CorrelationParams
from ..engine.fields.field import (
    GOOD_STATUSES,
    DisplacementField,
    Provenance,
    Status,
    grid_for_volume,
)
from ..engine.progress import Progress, run_to_completion
from ..io.lazy import as_lazy
from . import scheduling
from .batches import BatchJob, judge_batch, match_batch
from .memory import (
    _batch_bytes,
    _levels,
    _refuse_if_over,
    _region,
    available_memory,
    choose_batch_shape,
    estimate_peak_memory,
    format_bytes,
    halo,
    parse_memory,
)
from .seeds import give_seeds, match_seeds, seed_jobs
from .whole_volume import WholeVolume, whole_volume_iter

#: Default memory per concurrent batch when neither ``batch_shape`` nor ``max_memory`` is given.
DEFAULT_BATCH_BYTES = 1 << 30


# --- the driver --------------------------------------------------------------------------------
def lazy_pair(reference, deformed, mask, params: CorrelationParams):
    """The volumes (and mask) as lazy volumes, checked: one shape, room for a subvolume."""
    reference = as_lazy(reference)
    deformed = as_lazy(deformed)
    mask = None if mask is None else as_lazy(mask)
    shape = tuple(int(n) for n in reference.shape)
    if tuple(deformed.shape) != shape:
        raise ValueError(
            f"reference {shape} and deformed {tuple(deformed.shape)} volumes must have the "
            "same shape"
        )
    if mask is not None and tuple(mask.shape) != shape:
        raise ValueError(f"mask shape {tuple(mask.shape)} differs from the volume {shape}")
    if params.subvolume > min(shape):
        from ..engine.pair_checks import largest_subvolume_advice

        raise ValueError(
            f"subvolume {params.subvolume} is larger than the volume {shape}: "
            + largest_subvolume_advice(shape)
        )
    return reference, deformed, mask


def _check_grid(grid):
    origin, step, grid_shape = grid
    origin = np.asarray(origin, np.float64).reshape(3)
    step = np.asarray(step, np.float64).reshape(3)
    grid_shape = tuple(int(n) for n in grid_shape)
    if min(grid_shape) < 1:
        raise ValueError(f"the POI grid is empty (shape {grid_shape})")
    whole = np.abs(np.r_[origin, step] - np.rint(np.r_[origin, step])) <= 1e-6
    if not np.all(whole) or np.any(step < 1):
        raise ValueError("POI positions (origin + i * step) must be whole voxels")
    return np.rint(origin).astype(np.int64), np.rint(step).astype(np.int64), grid_shape


def _batch_ranges(grid_shape, batch_shape):
    axes = [
        [(start, min(n, start + b)) for start in range(0, n, b)]
        for n, b in zip(grid_shape, batch_shape)
    ]
    return [(rz, ry, rx) for rz in axes[0] for ry in axes[1] for rx in axes[2]]


def _make_jobs(batches, params, shape, grid, levels, whole, margin, initial, options):
    origin, step, grid_shape = grid
    reaches = halo(params, levels)
    flat_index = np.arange(int(np.prod(grid_shape))).reshape(grid_shape)
    jobs = []
    for core_ranges in batches:
        ext = [
            (max(0, a - margin), min(n, b + margin)) for (a, b), n in zip(core_ranges, grid_shape)
        ]
        first = origin + step * np.array([a for a, _ in ext])
        last = origin + step * np.array([b - 1 for _, b in ext])
        window = tuple(slice(a, b) for a, b in ext)
        initial_u = initial_gradient = None
        if initial is not None:
            initial_u = np.ascontiguousarray(initial.u[window])
            if initial.gradient is not None:
                initial_gradient = np.ascontiguousarray(initial.gradient[window])
            finite = initial_u.reshape(-1, 3)
            finite = finite[np.all(np.isfinite(finite), axis=1)]
            low_shift = finite.min(axis=0) if len(finite) else np.zeros(3)
            high_shift = finite.max(axis=0) if len(finite) else np.zeros(3)
        else:
            low_shift = high_shift = whole.shift
        lo, hi = _region(first, last, low_shift, high_shift, reaches, 2**levels, shape)
        jobs.append(
            BatchJob(
                params=params,
                origin=first,
                step=step,
                sub_shape=tuple(b - a for a, b in ext),
                core=tuple(slice(c0 - e0, c1 - e0) for (c0, c1), (e0, _) in zip(core_ranges, ext)),
                core_index=flat_index[tuple(slice(a, b) for a, b in core_ranges)].ravel(),
                region_low=lo,
                region_high=hi,
                shift=None if initial is not None else whole.shift,
                texture_std=whole.texture_std,
                initial_u=initial_u,
                initial_gradient=initial_gradient,
                grid_anchor=(tuple(a for a, _ in ext), tuple(grid_shape)),
                **options,
            )
        )
    return jobs


def _active_jobs(jobs, active):
    """The jobs whose own POIs include some of ``active`` (grid-shaped bool), each with its
    sub-grid's part of ``active`` (the margins included, as in memory)."""
    kept = []
    for job in jobs:
        if not active.reshape(-1)[job.core_index].any():
            continue
        window = tuple(slice(a, a + n) for a, n in zip(job.grid_anchor[0], job.sub_shape))
        kept.append(dataclasses.replace(job, active=np.ascontiguousarray(active[window])))
    return kept


def correlate_tiled_iter(
    reference,
    deformed,
    params: CorrelationParams | None = None,
    *,
    mask=None,
    grid: tuple | None = None,
    initial: DisplacementField | None = None,
    batch_shape=None,
    max_memory: int | str | None = None,
    workers: int | None = None,
    threads_per_task: int | None = None,
    scheduler=None,
    margin: int = 1,
    device="cpu",
    seed_pass: bool = True,
    active=None,
    weights=None,
    whole: WholeVolume | None = None,
) -> Generator[Progress, None, DisplacementField]:
    """Correlate ``reference`` (G) with ``deformed`` (F) batch by batch; yields progress, returns the field.

    Parameters
    ----------
    reference, deformed : LazyVolume, path or array, shape (nz, ny, nx)
        The volumes (see :func:`..io.lazy.as_lazy`: a path is opened lazily, an array wrapped).
    params : CorrelationParams, optional
        As for :func:`.correlate.correlate`.
    mask : LazyVolume, path or array, shape (nz, ny, nx), optional
        Reference-space mask of the material (non-zero = inside).
    grid : (origin, step, shape), optional
        POI grid; whole-voxel positions. Default :func:`grid_for_volume`.
    initial : DisplacementField, optional
        Initial guess on the same grid (skips the searches); the regions follow its displacement.
    batch_shape : int or tuple of 3 ints, optional
        POIs per batch ``(z, y, x)``. Default: the largest cube whose estimate fits the memory.
    max_memory : int or str, optional
        Peak memory this run may use (bytes, or a size like ``"2GB"``); picks the batch size.
        Default: about 1 GiB per concurrent batch, within the available memory.
    workers : int, optional
        Concurrent batches on the local threaded scheduler (default ``min(4, cores)``).
    threads_per_task : int, optional
        numba threads per batch (default: cores / workers locally, 1 on a cluster).
    scheduler : None, "threads", "sync", str or distributed.Client
        ``None``/``"threads"``: dask's local threaded scheduler; ``"sync"``: one thread;
        any other string: the address of a ``dask.distributed`` scheduler (e.g.
        ``"tcp://10.0.0.5:8786"``); or a ``distributed.Client``.
    margin : int
        Layers of neighbouring POIs matched with each batch (and then dropped) so that the
        reliability-guided repair and the median test see, at the batch's border, the
        neighbours they see in memory (the seeds come from the seed pass); then the batch's POIs
        get the in-memory field. Costs ``((b + 2m) / b)³`` times the work for batches of ``b³``
        POIs (2.1 for 7³ batches and the default margin of 1, 1.3 for 20³); 0 matches every POI
        once, and POIs that the repair re-matches near a batch's face may then differ from
        memory by up to the IC-GN tolerance's trace (3.6e-4 voxel measured at tolerance 1e-5).
        Without the seed pass the margin must also reach each POI's nearest good seed.
    device : {"cpu", "cuda", "auto"}
        Where each batch's IC-GN runs (see :func:`.correlate.correlate_iter`); on a cluster, on
        the workers' devices.
    seed_pass : bool
        Match the initial guess's seeds on the whole grid before the batches (default; see the
        module's docstring). False: each batch searches the whole grid's seeds in its box
        (``grid_anchor``), which differs from memory at the batch faces unless ``margin``
        reaches each POI's nearest good seed.
    active : ndarray of bool, shape of the grid, optional
        Match only these POIs (as :func:`..engine.correlation.correlate.correlate_iter`'s ``active``); a
        batch with none of its own POIs active is not run. The others get
        ``Status.NOT_COMPUTED``.
    weights : ndarray, shape (subvolume,)*3, optional
        Weights of the subvolume's voxels for every match (as
        :func:`..engine.correlation.correlate.correlate_iter`'s ``weights``, e.g. the
        self-correction's oriented windows). Default: those of ``params.window``.
    whole : WholeVolume, optional
        The whole-volume pass of these volumes and mask (:func:`.whole_volume.whole_volume_iter`),
        from an earlier run with an initial field: several runs on one pair read it once. Only
        with ``initial`` (a search needs the pyramid's binned moments).

    Yields
    ------
    Progress
        The plan (with the estimated peak memory), the whole-volume pass (rigid shift, gray
        statistics), the seed pass (stage ``"seeds"``, one report per box of seeds), one report
        per batch matched (stage ``"IC-GN"``), then one per batch judged (stage ``"repair"``).

    Returns
    -------
    DisplacementField
        As :func:`.correlate.correlate`; ``metadata["tiled"]`` records the batches, the memory
        estimate and the throughput.

    Raises
    ------
    MemoryBudgetError
        When the estimated peak memory exceeds the available memory or ``max_memory``.
    """

    started = time.perf_counter()
    params = CorrelationParams() if params is None else params
    reference, deformed, mask = lazy_pair(reference, deformed, mask, params)
    shape = tuple(int(n) for n in reference.shape)
    if not isinstance(margin, (int, np.integer)) or margin < 0:
        raise ValueError(f"margin must be an integer >= 0, got {margin!r}")
    if whole is not None and initial is None:
        raise ValueError("a whole-volume pass can be reused only by a run from an initial field")
    if weights is not None:  # here, not in a batch's task after the whole-volume pass
        check_weights(weights, params.half)
        weights = np.asarray(weights, np.float64)
    if grid is None:
        grid = grid_for_volume(shape, params.subvolume, params.step)
    grid = _check_grid(grid)
    grid_shape = grid[2]
    if initial is not None and initial.shape != grid_shape:
        raise ValueError(
            f"initial field grid {initial.shape} differs from the POI grid {grid_shape}"
        )
    max_memory = None if max_memory is None else parse_memory(max_memory)
    levels = _levels(params, shape, initial is not None)
    dtype = np.result_type(reference.dtype, deformed.dtype)
    masked = mask is not None
    cores = os.cpu_count() or 1

    client, owns_client = (None, False)
    if not scheduling.is_local(scheduler):
        client, owns_client = scheduling.connect(scheduler)
    try:
        # where the work runs and how much memory it may use
        if client is not None:
            total_threads, concurrency, worker_limit = scheduling.cluster_resources(client)
            workers = total_threads
            threads_per_task = 1 if threads_per_task is None else threads_per_task
            budget = worker_limit or available_memory()
            where = f"each worker of the cluster at {scheduler!r}"
        else:
            workers = min(4, cores) if workers is None else int(workers)
            if workers < 1:
                raise ValueError(f"workers must be >= 1, got {workers}")
            concurrency = workers
            budget = available_memory()
            where = "this machine"
        if max_memory is not None:
            budget = min(budget, max_memory)
        sizes = dict(margin=margin, masked=masked, grid=grid)
        # the part that no batch holds: the field, the seeds and the matched POIs held between a
        # batch's two tasks (these count each batch's margin, so they depend on the batch shape;
        # the whole grid as one batch gives the least)
        fixed = estimate_peak_memory(shape, dtype, params, grid_shape, workers=0, **sizes)
        if batch_shape is None:
            target = budget if max_memory is not None else fixed + concurrency * DEFAULT_BATCH_BYTES
            batch_shape = choose_batch_shape(
                shape, dtype, params, min(target, budget), workers=concurrency, **sizes
            )
        batch_shape = tuple(int(b) for b in np.broadcast_to(np.asarray(batch_shape), (3,)))
        if min(batch_shape) < 1:
            raise ValueError(f"batch_shape must hold 3 ints >= 1, got {batch_shape}")
        estimate = estimate_peak_memory(
            shape, dtype, params, batch_shape, workers=concurrency, **sizes
        )
        _refuse_if_over(estimate, budget, max_memory, batch_shape, concurrency, where)
        fixed = estimate_peak_memory(shape, dtype, params, batch_shape, workers=0, **sizes)
        batches = _batch_ranges(grid_shape, batch_shape)
        if client is None:
            workers = concurrency = max(1, min(workers, len(batches)))
            if threads_per_task is None:
                threads_per_task = max(1, cores // workers)
        yield Progress(
            "plan",
            1,
            1,
            f"estimated peak memory {format_bytes(estimate)} (allowed {format_bytes(budget)}); "
            f"{len(batches)} batches of up to {batch_shape[0]}x{batch_shape[1]}x{batch_shape[2]} "
            f"POIs on {'this machine' if client is None else scheduler} ({workers} at a time)",
        )

        t0 = time.perf_counter()
        if whole is None:
            whole = yield from whole_volume_iter(
                reference, deformed, mask, levels, (scheduler, workers, client)
            )
        if masked and whole.mask_count == 0:
            raise ValueError("the mask is empty: no voxel is selected")
        shift = None if initial is not None else whole.shift
        shift_seconds = time.perf_counter() - t0

        jobs = _make_jobs(
            batches,
            params,
            shape,
            grid,
            levels,
            whole,
            margin,
            initial,
            dict(threads=threads_per_task, use_mask=masked, device=device, weights=weights),
        )
        if active is not None:  # only the batches with POIs to match, each told which
            jobs = _active_jobs(jobs, np.asarray(active, bool).reshape(grid_shape))
        largest = max(jobs, key=lambda job: job.region_voxels, default=None)
        itemsize = np.dtype(dtype).itemsize
        points = 0 if largest is None else int(np.prod(largest.sub_shape))
        actual = fixed + concurrency * _batch_bytes(
            0 if largest is None else largest.region_voxels, points, itemsize, masked, levels
        )
        _refuse_if_over(actual, budget, max_memory, batch_shape, concurrency, where)

        import dask

        volumes = [None if v is None else dask.delayed(v) for v in (reference, deformed, mask)]
        t0 = time.perf_counter()
        good_seeds = None
        if initial is None and seed_pass:
            seed_batch_jobs, seed_flat, seed_shape = seed_jobs(
                batches,
                params,
                shape,
                grid,
                levels,
                whole,
                dict(threads=threads_per_task, use_mask=masked, device=device),
            )
            seed_task = dask.delayed(match_seeds, pure=False)
            seed_results = []
            with scheduling.running(
                [seed_task(job, *volumes) for job in seed_batch_jobs], scheduler, workers, client
            ) as finished:
                for done, (_, result) in enumerate(finished, start=1):
                    seed_results.append(result)
                    yield Progress(
                        "seeds",
                        done,
                        len(seed_batch_jobs),
                        f"seeds of batch {done} of {len(seed_batch_jobs)} matched",
                    )
            good_seeds = give_seeds(
                jobs, seed_results, seed_flat, seed_shape, grid_shape, levels, params
            )
            del seed_results
        seed_seconds = time.perf_counter() - t0
        n_points = int(np.prod(grid_shape))
        t0 = time.perf_counter()
        task = dask.delayed(match_batch, pure=False)
        matches = [None] * len(jobs)
        with scheduling.running(
            [task(job, *volumes) for job in jobs], scheduler, workers, client
        ) as finished:
            for done, (i, result) in enumerate(finished, start=1):
                matches[i] = result
                yield Progress("IC-GN", done, len(jobs), f"batch {done} of {len(jobs)} matched")
        # the whole run's noise: the median over every batch's own POIs, as in memory
        estimates = np.concatenate([np.empty(0)] + [m.estimates for m in matches])
        noise_variance = float(np.median(estimates)) if estimates.size else 0.0
        del estimates
        u = np.full((n_points, 3), np.nan)
        gradient = np.full((n_points, 3, 3), np.nan)
        zncc = np.full(n_points, np.nan, np.float32)
        status = np.full(n_points, int(Status.NOT_COMPUTED), np.uint8)
        iterations = np.zeros(n_points, np.int32)
        uncertainty = np.full((n_points, 3), np.nan)
        thresholds = np.full(n_points, float(params.min_zncc))
        totals: dict = {}
        task = dask.delayed(judge_batch, pure=False)
        judge_tasks = [task(job, m, noise_variance, *volumes) for job, m in zip(jobs, matches)]
        del matches
        with scheduling.running(judge_tasks, scheduler, workers, client) as finished:
            for done, (_, result) in enumerate(finished, start=1):
                index = result.core_index
                u[index] = result.u
                gradient[index] = result.gradient
                zncc[index] = result.zncc
                status[index] = result.status
                iterations[index] = result.iterations
                thresholds[index] = result.thresholds
                if result.uncertainty is not None:
                    uncertainty[index] = result.uncertainty
                for key, value in result.timings.items():
                    totals[key] = totals.get(key, 0) + value
                yield Progress(
                    "repair",
                    done,
                    len(jobs),
                    f"batch {done} of {len(jobs)} judged ({totals.get('points', 0)} of "
                    f"{n_points} POIs)",
                )
        del judge_tasks
        batch_seconds = time.perf_counter() - t0
    finally:
        if owns_client:
            client.close()

    # the uncertainty bound over the whole run's POIs, as in memory
    bound, unsure = uncertainty_bound(uncertainty, status)
    status[unsure] = int(Status.LOW_ZNCC)
    noise = {
        **noise_metadata(noise_variance, thresholds, status, params.min_zncc),
        "zncc_threshold_floor": zncc_floor(params.order, params.subvolume),
        "uncertainty_bound": bound,
        "uncertain": int(unsure.sum()),
    }
    provenance = np.full(n_points, int(Provenance.MEASURED), np.uint8)
    provenance[status == int(Status.MASKED)] = int(Provenance.MASKED)
    matched = totals.get("points", 0)
    timings = {
        "whole_volume_s": shift_seconds,
        "seeds_s": seed_seconds,
        "batches_s": batch_seconds,
        "total_s": time.perf_counter() - started,
        "task_s": {k: v for k, v in totals.items() if k.endswith("_s")},
        "voxel_iterations": int(totals.get("voxel_iterations", 0)),
        "points_per_s": matched / batch_seconds if batch_seconds > 0 else float("nan"),
        # POIs matched including the margins (the work done), per POI kept
        "margin_overhead": totals.get("computed_points", 0) / max(matched, 1),
    }
    origin, step, _ = grid
    result_field = DisplacementField(
        origin=tuple(float(o) for o in origin),
        step=tuple(float(s) for s in step),
        u=u.reshape(*grid_shape, 3),
        zncc=zncc.reshape(grid_shape),
        status=status.reshape(grid_shape),
        iterations=iterations.reshape(grid_shape),
        provenance=provenance.reshape(grid_shape),
        gradient=gradient.reshape(*grid_shape, 3, 3),
        uncertainty=uncertainty.reshape(*grid_shape, 3),
        params=params.to_dict(),
        metadata={
            "volume_shape": list(shape),
            "global_shift": [0, 0, 0] if shift is None else [int(s) for s in shift],
            "pyramid_levels": int(levels),
            "timings": timings,
            "masked": masked,
            "noise": noise,
            "tiled": {
                "batch_shape": list(batch_shape),
                "batches": len(jobs),
                "margin": int(margin),
                "workers": int(workers),
                "threads_per_task": threads_per_task,
                "scheduler": "local threads" if client is None else str(scheduler),
                "estimated_peak_bytes": int(actual),
                "largest_region_voxels": 0 if largest is None else int(largest.region_voxels),
                "seed_pass": good_seeds is not None,
                "good_seeds": good_seeds,
                # the whole (masked) reference's gray std, for the texture test of later runs
                # on regions of these volumes (tiled.points)
                "reference_gray_std": float(whole.texture_std[1]),
            },
        },
    )
    good = int(np.isin(status, [int(s) for s in GOOD_STATUSES]).sum())
    yield Progress("done", 1, 1, f"{good} of {n_points} POIs matched")
    return result_field


def correlate_tiled(reference, deformed, params: CorrelationParams | None = None, **kwargs):
    """Blocking form of :func:`correlate_tiled_iter` (same parameters, no progress)."""
    return run_to_completion(correlate_tiled_iter(reference, deformed, params, **kwargs))
