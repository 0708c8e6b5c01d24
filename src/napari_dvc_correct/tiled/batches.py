"""One batch of :mod:`.correlate`'s tiled correlation: what its tasks receive and return.

Each batch runs as two tasks: :func:`match_batch` (the first half of
:func:`..engine.correlation.correlate.correlate_iter`: pyramid and IC-GN in the batch's region) and, once
every batch is matched and the whole run's noise is known, :func:`judge_batch` (the thresholds,
the reliability-guided repair and the uncertainties at that noise, :func:`..engine.correlation.match_judgement.judge_iter`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from ..engine.backend import select_device
from ..engine.correlation.correlate import match_iter, validate_pair
from ..engine.correlation.guided_repair import GivenSeeds
from ..engine.correlation.match_judgement import MatchedGrid, judge_iter, measure_plain_sigma
from ..engine.correlation.params import CorrelationParams
from ..engine.correlation.pyramid import PyramidLevel
from ..engine.fields.field import DisplacementField, Provenance, Status
from ..engine.progress import run_to_completion


# --- one batch ---------------------------------------------------------------------------------
@dataclass
class BatchJob:
    """What one batch task needs (small; the volumes travel separately)."""

    params: CorrelationParams
    origin: np.ndarray  # (3,) voxels: first POI of the extended sub-grid
    step: np.ndarray  # (3,) voxels
    sub_shape: tuple  # extended sub-grid shape (batch + margin, clipped to the grid)
    core: tuple  # slices of the batch's own POIs inside the extended sub-grid
    core_index: np.ndarray  # (m,) flat indices of those POIs in the whole grid
    region_low: np.ndarray  # (3,) region [low, high) in voxels
    region_high: np.ndarray
    shift: np.ndarray | None  # whole-volume rigid shift (None with an initial field)
    texture_std: dict | None  # whole-volume gray std per binning factor
    initial_u: np.ndarray | None = None  # (*sub_shape, 3)
    initial_gradient: np.ndarray | None = None  # (*sub_shape, 3, 3)
    threads: int | None = None
    use_mask: bool = False
    device: str = "cpu"
    grid_anchor: tuple | None = None  # (whole-grid index of the sub-grid's first POI, grid shape)
    seeds: GivenSeeds | None = None  # the seed pass's seeds for this sub-grid
    active: np.ndarray | None = None  # (*sub_shape,) bool: the POIs to match (None: all)
    weights: np.ndarray | None = None  # (subvolume,)*3 voxel weights (None: the params' window)

    def subvolume_weights(self):
        """The weights every match of the batch uses (``weights``, else the params' window)."""
        return self.params.subvolume_weights() if self.weights is None else self.weights

    @property
    def region_voxels(self) -> int:
        return int(np.prod(self.region_high - self.region_low))


@dataclass
class BatchResult:
    """The batch's own POIs, flat in C order of its box."""

    core_index: np.ndarray
    u: np.ndarray
    gradient: np.ndarray
    zncc: np.ndarray
    status: np.ndarray
    iterations: np.ndarray
    timings: dict = field(default_factory=dict)
    uncertainty: np.ndarray | None = None  # (n, 3) voxels, before the uncertainty bound
    thresholds: np.ndarray | None = None  # (n,) ZNCC thresholds at the whole run's noise


@dataclass
class BatchMatch:
    """A batch after its IC-GN (:func:`match_batch`): its POIs matched, not yet judged."""

    matched: MatchedGrid | None  # the extended sub-grid; None: no material in the region
    estimates: np.ndarray  # noise estimates s² (1 - ZNCC) of the batch's own POIs
    timings: dict = field(default_factory=dict)


def read_regions(job, reference, deformed, mask):
    """``(G, F, mask)`` over ``job``'s region (``region_low``/``region_high``; the mask only
    with ``use_mask``), with the task's numba threads set from ``job.threads``."""
    if job.threads:
        import numba

        numba.set_num_threads(max(1, min(int(job.threads), numba.config.NUMBA_NUM_THREADS)))
    region = tuple(slice(int(a), int(b)) for a, b in zip(job.region_low, job.region_high))
    g = reference.read_region(region)
    f = deformed.read_region(region)
    m = mask.read_region(region) != 0 if job.use_mask and mask is not None else None
    return g, f, m


def _local_grid(job: BatchJob):
    local_origin = tuple(float(v) for v in job.origin - job.region_low)
    return local_origin, tuple(float(v) for v in job.step), job.sub_shape


def match_batch(job: BatchJob, reference, deformed, mask=None) -> BatchMatch:
    """First task of a batch: :func:`.correlate.match_iter` in its region (IC-GN, not judged).

    ``reference``, ``deformed`` and ``mask`` are lazy volumes (:mod:`..io.lazy`). Returns the
    matched sub-grid and the noise estimates of the batch's own POIs, whose median over all
    batches is the whole run's noise (:func:`judge_batch`).
    """
    started = time.perf_counter()
    g, f, m = read_regions(job, reference, deformed, mask)
    read_s = time.perf_counter() - started
    if m is not None and not m.any():  # nothing of the material here: every POI is masked
        return BatchMatch(None, np.empty(0), {"read_s": read_s})
    local_origin, step, _ = grid = _local_grid(job)
    initial = None
    if job.initial_u is not None:
        initial = DisplacementField(
            local_origin, step, job.initial_u, gradient=job.initial_gradient
        )
    matched, fine = run_to_completion(
        match_iter(
            g,
            f,
            job.params,
            mask=m,
            grid=grid,
            initial=initial,
            rigid_shift=job.shift,
            texture_std=job.texture_std,
            device=job.device,
            grid_anchor=job.grid_anchor,
            seeds=job.seeds,
            active=job.active,
            weights=job.subvolume_weights(),
            noise_hint=0.0,  # measure_plain_sigma below keeps the noise-free estimate only
        )
    )
    # the noise-free uncertainty while the volumes are here: a clean batch's judge reads nothing
    measure_plain_sigma(fine, matched, job.params.order)
    del fine
    core = np.arange(int(np.prod(job.sub_shape))).reshape(job.sub_shape)[job.core].ravel()
    timings = {"read_s": read_s, "match_task_s": time.perf_counter() - started}
    return BatchMatch(matched, matched.noise_estimates(core), timings)


class _RegionLevel:
    """The batch's full-resolution :class:`.correlate.PyramidLevel`, read and prefiltered again
    only when the judge needs it: to repair a POI, or to measure an uncertainty again (noisy
    scans, repaired POIs). A clean batch with nothing to repair reads nothing."""

    def __init__(self, job, reference, deformed, mask, timings):
        self._args = (job, reference, deformed, mask)
        self._level = None
        self._timings = timings

    def _built(self):
        if self._level is None:
            started = time.perf_counter()
            job = self._args[0]
            g, f, m = read_regions(*self._args)
            g, f, m = validate_pair(g, f, job.params, m)
            self._level = PyramidLevel.build(
                1,
                g,
                f,
                m,
                job.params.half,
                job.params.min_texture,
                select_device(job.device).kind,
                std=None if job.texture_std is None else job.texture_std[1],
                weights=job.subvolume_weights(),
            )
            self._timings["judge_prefilter_s"] = time.perf_counter() - started
        return self._level

    @property
    def reference(self):
        return self._built().reference

    @property
    def half(self):
        return self._args[0].params.half

    def match(self, centers, warps, order, params):
        return self._built().match(centers, warps, order, params)

    def statistics(self, centers, warps, zncc, order, sensitivity, out, index):
        if len(centers):
            self._built().statistics(centers, warps, zncc, order, sensitivity, out, index)


def judge_batch(
    job: BatchJob, batch: BatchMatch, noise_variance, reference, deformed, mask=None
) -> BatchResult:
    """Second task of a batch: its POIs judged at the whole run's ``noise_variance``.

    Runs :func:`.judge.judge_iter` (thresholds, repair, uncertainties) as in memory, reading the
    region again where it needs the volumes (:class:`_RegionLevel`: the prefilter is rebuilt,
    not held between the tasks); the uncertainty bound, another median over the whole run, is
    left to the driver.
    """
    started = time.perf_counter()
    timings = dict(batch.timings)
    if batch.matched is None:
        shape = job.sub_shape
        result = DisplacementField(
            _local_grid(job)[0],
            tuple(float(v) for v in job.step),
            np.full((*shape, 3), np.nan),
            status=np.full(shape, int(Status.MASKED), np.uint8),
            provenance=np.full(shape, int(Provenance.MASKED), np.uint8),
            gradient=np.full((*shape, 3, 3), np.nan),
        )
        thresholds = np.full(int(np.prod(shape)), float(job.params.min_zncc))
    else:
        fine = _RegionLevel(job, reference, deformed, mask, timings)
        result, thresholds = run_to_completion(
            judge_iter(batch.matched, fine, job.params, noise_variance=noise_variance, bound=False)
        )
        del fine
    core = job.core
    gradient = (
        result.gradient if result.gradient is not None else np.full((*job.sub_shape, 3, 3), np.nan)
    )
    timings.update(
        {k: v for k, v in result.metadata.get("timings", {}).items() if isinstance(v, (int, float))}
    )
    iterations = result.iterations[core].reshape(-1)
    timings.update(
        task_s=timings.get("match_task_s", 0.0) + time.perf_counter() - started,
        voxel_iterations=int(iterations.sum()) * job.params.subvolume**3,
        points=int(len(job.core_index)),
        computed_points=int(np.prod(job.sub_shape)),
        region_voxels=job.region_voxels,
    )
    timings.pop("match_task_s", None)
    timings["total_s"] = timings["task_s"]  # not since the first task began (the wait between)
    return BatchResult(
        core_index=job.core_index,
        u=result.u[core].reshape(-1, 3),
        gradient=gradient[core].reshape(-1, 3, 3),
        zncc=result.zncc[core].reshape(-1),
        status=result.status[core].reshape(-1),
        iterations=iterations,
        timings=timings,
        uncertainty=None if result.uncertainty is None else result.uncertainty[core].reshape(-1, 3),
        thresholds=thresholds.reshape(job.sub_shape)[core].reshape(-1),
    )
