"""The self-correction of volumes larger than memory: the engine's loop on a block-by-block back-end.

:func:`correct_tiled_iter` runs the one correction loop of the engine
(:func:`..engine.correction.self_correction.correct_volumes_iter`: clean, judge node by node against the noise,
warp, correlate, compose, stop) with :class:`TiledVolumes` doing every volume operation on lazily
read volumes (:mod:`..io.lazy`: TIFF, Zarr, .npy...), as Dask tasks on local threads or a
``dask.distributed`` cluster (:mod:`.scheduling`). The fields (node arrays) stay in memory.

* **Warp** (step d): the forward warp ``G'`` (or the pull-back ``F~`` in the reference frame) is
  written block by block to a temporary Zarr array (:func:`.volumes.write_iter`), its mean gray
  residual summed on the way; the warped mask likewise. Temporary arrays are removed when no
  longer needed, and all of them at the end, on error and on cancel.
* **Correcting DVC** (step e): :func:`.correlate.correlate_tiled_iter` on ``(G', F)`` with the
  pass's parameters, the field's grid and a zero initial field (no search, so no seeds).
* **Local acceptance**: the per-node means of the reference-frame residual
  ``|F(X + D(X)) - G(X)|`` over the nodes' cells and subvolumes are computed node block by node
  block, each block reading only the region its nodes' boxes need (plus the spline support and
  the prefilter margin in ``F``); eq. 1's background residual is summed over a partition of the
  voxels; the local gray gradients likewise (with the Gaussian's reach). The phase thresholds
  (multi-Otsu) are those of the in-memory run exactly: the lattice sample it uses
  (:func:`..engine.evaluation.phases.lattice_sample`) is gathered block by block.

Equal to :func:`..engine.correction.self_correction.correct_iter` up to float32 rounding of the regions'
prefilters and box means, and to what batching changes in the correcting DVC (the
reliability-guided repair works per batch; the noise-aware thresholds are the whole run's,
:func:`.correlate.correlate_tiled_iter`); see ``docs/scaling.md``.
"""

from __future__ import annotations

import itertools
import os
import shutil
from collections.abc import Generator
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from ..engine.correction.options import CorrectionOptions
from ..engine.correction.self_correction import check_options, correct_volumes_iter, params_of
from ..engine.correction.volumes import CorrectionVolumes
from ..engine.correlation.params import CorrelationParams
from ..engine.evaluation.gray_levels import (
    DEFAULT_CELL,
    CellSums,
    GrayLevelMap,
    cells_shape,
    fit_from_passes,
    start_map,
)
from ..engine.evaluation.gray_noise import pair_noise, scan_noises
from ..engine.evaluation.phases import otsu_stride, otsu_thresholds
from ..engine.fields.absurd_nodes import flag_absurd_nodes
from ..engine.fields.field import DisplacementField
from ..engine.fields.field_spline import FieldSpline
from ..engine.pair_checks import check_field_on_volume
from ..engine.progress import Progress, run_to_completion
from ..engine.run_options import RunOptions
from ..io.atomic import scratch_dir
from ..io.lazy import as_lazy, iter_blocks, open_volume
from . import scheduling
from .correction_blocks import (
    gray_sums_block,
    statistics_block,
    warp_mask_iter,
    warp_residual_block,
)
from .correlate import correlate_tiled_iter
from .memory import (
    PREFILTER_MARGIN,
    SPLINE_SUPPORT,
    _refuse_if_over,
    choose_batch_shape,
    estimate_peak_memory,
    format_bytes,
    memory_budget,
    parse_memory,
    refuse_blocks_over,
)
from .node_residuals import TiledResiduals, node_bytes
from .volumes import write_iter
from .whole_volume import whole_volume_iter

#: Voxels per block of the warps (z, y, x); also the temporary Zarr arrays' chunks.
CORRECTION_BLOCK = (32, 128, 128)

#: Grid nodes per block (along each axis) of the local residuals and gradients.
NODE_BLOCK = 8

#: Voxels read at a time by the statistics pass (phase thresholds, mean gray value).
STATISTICS_BLOCK_VOXELS = 1 << 23

#: Working bytes per voxel of a warp block (positions, inverse map iterates, Jacobians, values).
BYTES_PER_WARP_VOXEL = 240


# --- the back-end --------------------------------------------------------------------------------
class TiledVolumes(CorrectionVolumes):
    """The correction's volume operations block by block on lazy volumes (see the module).

    Parameters
    ----------
    reference, deformed : LazyVolume, path or array, shape (nz, ny, nx)
        ``G`` and ``F`` (:func:`..io.lazy.as_lazy`).
    frame : {"loaded", "reference"}
    mask : LazyVolume, path or array, optional
        Reference-space material mask (non-zero = inside).
    batch_shape, max_memory, workers, scheduler, device
        As :func:`.correlate.correlate_tiled_iter`, for every DVC run; ``workers`` and
        ``scheduler`` also for the blocks of the warps and residuals.
    block_shape : tuple of 3 ints
        Voxels per warp block.
    node_block : int
        Grid nodes per block (each axis) of the local residuals.
    temp_dir : str or PathLike, optional
        Where the temporary Zarr arrays go (default: the system's temporary folder). On a
        cluster of several machines it must be a folder every worker sees at the same path.
    """

    def __init__(
        self,
        reference,
        deformed,
        frame: str = "loaded",
        mask=None,
        *,
        batch_shape=None,
        max_memory=None,
        workers: int | None = None,
        scheduler=None,
        device="cpu",
        block_shape=CORRECTION_BLOCK,
        node_block: int = NODE_BLOCK,
        temp_dir=None,
    ):
        self.reference = as_lazy(reference)
        self.deformed = as_lazy(deformed)
        self.mask = None if mask is None else as_lazy(mask)
        self.shape = tuple(int(n) for n in self.reference.shape)
        if tuple(self.deformed.shape) != self.shape:
            raise ValueError(
                f"reference {self.shape} and deformed {tuple(self.deformed.shape)} volumes must "
                "have the same shape"
            )
        if self.mask is not None and tuple(self.mask.shape) != self.shape:
            raise ValueError(
                f"mask shape {tuple(self.mask.shape)} differs from the volume {self.shape}"
            )
        self.frame = frame
        self.block_shape = tuple(int(b) for b in np.broadcast_to(block_shape, (3,)))
        self.node_block = max(1, int(node_block))
        self.max_memory = None if max_memory is None else parse_memory(max_memory)
        self.batch_shape = batch_shape
        self.device = device
        self.workers = min(4, os.cpu_count() or 1) if workers is None else int(workers)
        if self.workers < 1:
            raise ValueError(f"workers must be >= 1, got {workers}")
        self.scheduler = scheduler
        self.client, self._owns_client = None, False
        if not scheduling.is_local(scheduler):
            self.client, self._owns_client = scheduling.connect(scheduler)
        if temp_dir is not None:
            Path(temp_dir).mkdir(parents=True, exist_ok=True)  # a folder named by the user
        self._temp_dir = scratch_dir("dvc-correct", temp_dir)  # a dead run's: removed
        self._temps: dict[int, Path] = {}
        self._count = 0
        self._statistics = None

    # -- running blocks
    @property
    def _where(self):
        return self.client if self.client is not None else self.scheduler

    def _tasks(self, function, shared, items, stage) -> Generator[Progress, None, list]:
        import dask

        shared = [dask.delayed(item) for item in shared]
        task = dask.delayed(function, pure=False)
        tasks = [task(*shared, item) for item in items]
        results = [None] * len(tasks)
        with scheduling.running(tasks, self.scheduler, self.workers, self.client) as finished:
            for done, (index, result) in enumerate(finished, start=1):
                results[index] = result
                yield Progress(stage, done, len(tasks), f"block {done} of {len(tasks)}")
        return results

    def _temporary(self, name: str) -> Path:
        self._count += 1
        return self._temp_dir / f"{name}-{self._count}.zarr"

    def _keep(self, path: Path):
        volume = open_volume(path)
        self._temps[id(volume)] = path
        return volume

    def release(self, moved) -> None:
        path = self._temps.pop(id(moved), None)
        if path is not None:
            shutil.rmtree(path, ignore_errors=True)

    def close(self) -> None:
        self._temps.clear()
        shutil.rmtree(self._temp_dir, ignore_errors=True)
        if self._owns_client:
            self.client.close()
            self._owns_client = False

    # -- the whole-volume statistics: phase thresholds and the fill value
    def statistics(self) -> Generator[Progress, None, SimpleNamespace]:
        """One read of both volumes: their multi-Otsu thresholds (as in memory) and mean gray."""
        if self._statistics is not None:
            return self._statistics
        stride = otsu_stride(self.shape)
        regions = [
            (z, y, slice(0, self.shape[2]))
            for z, y in iter_blocks(self.shape, STATISTICS_BLOCK_VOXELS)
        ]
        found = {}
        for name, volume in (("reference", self.reference), ("deformed", self.deformed)):
            parts = yield from self._tasks(
                statistics_block, [volume, stride], regions, f"statistics ({name})"
            )
            bad = sum(part[3] for part in parts)
            if bad:
                raise ValueError(
                    f"the {name} volume contains {bad} NaN or infinite values: fix or mask them"
                )
            count = sum(part[2] for part in parts)
            # the whole volume's lattice sample in another order, which a histogram ignores
            sample = np.concatenate([part[0] for part in parts])
            found[name] = (sample, sum(part[1] for part in parts) / max(count, 1))
        try:
            thresholds = (
                otsu_thresholds(found["reference"][0], 2),
                otsu_thresholds(found["deformed"][0], 2),
            )
        except ValueError:  # a volume with a single gray value: no phases, no eq. 1
            thresholds = None
        self._statistics = SimpleNamespace(
            samples=(found["reference"][0], found["deformed"][0]),
            thresholds=thresholds,
            mean_reference=found["reference"][1],
            mean_deformed=found["deformed"][1],
        )
        return self._statistics

    # -- the interface
    def run_options(self) -> dict:
        """The keywords of every tiled DVC run of this back-end (:func:`.correlate.correlate_tiled_iter`)."""
        return dict(
            batch_shape=self.batch_shape,
            max_memory=self.max_memory,
            workers=self.workers,
            scheduler=self._where,
            device=self.device,
        )

    def correlate(self, params, pair=None, *, grid=None, initial=None, active=None):
        run = self.run_options()
        if pair is None:
            return correlate_tiled_iter(
                self.reference, self.deformed, params, mask=self.mask, **run
            )
        g, f, mask = pair
        return correlate_tiled_iter(
            g, f, params, mask=mask, grid=grid, initial=initial, active=active, **run
        )

    def original_matcher(self):
        return OriginalPairMatcher(self)

    def align(self, field):
        stats = yield from self.statistics()
        spline = FieldSpline.from_field(field)
        loaded = self.frame == "loaded"
        fill = stats.mean_reference if loaded else stats.mean_deformed
        hull = spline.hull_slices(self.shape)
        path = self._temporary("warped" if loaded else "pulled-back")
        summary = yield from write_iter(
            path,
            self.shape,
            1,
            warp_residual_block,
            [self.reference, self.deformed, spline],
            [self.frame, float(fill), hull, self._gray()],
            run=(self.block_shape, self._where, self.workers),
            metadata={"quantity": f"correction: the pair aligned by the field ({self.frame})"},
            stage="warp",
        )
        return self._keep(Path(summary["path"])), float(summary["mean"])

    def matching_pair(self, moved, field):
        if self.frame == "reference":
            return self.reference, moved, self.mask
        mask = None
        if self.mask is not None:
            path = yield from warp_mask_iter(
                self.mask,
                field,
                self._temporary("mask"),
                run=(self.block_shape, self._where, self.workers),
            )
            mask = None if path is None else self._keep(path)
        return moved, self.deformed, mask

    def _gray(self) -> GrayLevelMap:
        return self.gray_levels if self.gray_levels is not None else GrayLevelMap.identity()

    def fit_gray_levels(self, field):
        stats = yield from self.statistics()
        spline = FieldSpline.from_field(field)
        blocks = [
            tuple(slice(a, min(a + b, n)) for a, b, n in zip(start, self.block_shape, self.shape))
            for start in itertools.product(
                *(range(0, n, b) for n, b in zip(self.shape, self.block_shape))
            )
        ]

        def sums_with(previous):
            parts = yield from self._tasks(
                gray_sums_block,
                [self.reference, self.deformed, spline, DEFAULT_CELL, previous],
                blocks,
                "gray levels",
            )
            sums = CellSums.zeros(cells_shape(self.shape, DEFAULT_CELL))
            for part in parts:
                sums.add(part)
            return sums

        # the robust start from the scans' lattice samples (the statistics pass's), as in memory
        start = start_map(*stats.samples)
        # each scan's noise on its central block, as in memory
        noises = scan_noises(self.reference, self.deformed, read=lambda v, box: v.read_region(box))
        noise = pair_noise(*noises, field.displacement)
        self.gray_levels = yield from fit_from_passes(
            sums_with, start, self.shape, DEFAULT_CELL, noise=noise
        )
        return self.gray_levels

    def residuals(self):
        stats = yield from self.statistics()
        return TiledResiduals(self, stats.thresholds, self._gray())


#: Layers of neighbouring nodes matched with each batch of the oriented step's runs (and then
#: dropped; the correcting passes use the tiled DVC's default, 1). An oriented direction's nodes
#: are few and scattered, and its noisy matches get repaired: a node is re-matched from the
#: best neighbour that passes the median test, and that test reads the neighbour's own
#: neighbours, two layers out. With 1 layer, 2 of 125 nodes of tests/tiled/test_correction.py's
#: case came out 1e-3 voxel off the in-memory run; with 2, equal to the bit. A chain of repairs
#: (a repaired node seeding the next) that crosses a batch face still differs, as in any tiled
#: run (4 of 3125 nodes, <= 1.6e-3 voxel, on docs/method.md's longer case; more layers did not
#: remove them). Only the active nodes of the margins are matched: the cost is a few nodes and
#: a larger region read.
ORIENTED_MARGIN = 2


class OriginalPairMatcher:
    """The tiled back-end's matcher of the original pair for the oriented step
    (:func:`..engine.correction.oriented.oriented_rematch`): each direction's run is a tiled DVC
    (:func:`.correlate.correlate_tiled_iter`) of the lazy ``(G, F, mask)`` from the given field,
    only the batches with nodes to match, every region read with the margins of that run's box
    (its halo follows the run's subvolume) and :data:`ORIENTED_MARGIN` layers of neighbouring
    nodes; the whole-volume pass (the gray statistics of the low-texture test) is read once for
    every direction's run."""

    def __init__(self, volumes: TiledVolumes):
        self.shape = volumes.shape
        self._volumes = volumes
        self._whole = None

    def __call__(self, params, initial, active, weights):
        volumes = self._volumes
        if self._whole is None:
            run = (volumes.scheduler, volumes.workers, volumes.client)
            self._whole = yield from whole_volume_iter(
                volumes.reference, volumes.deformed, volumes.mask, 0, run
            )
        return (
            yield from correlate_tiled_iter(
                volumes.reference, volumes.deformed, params, mask=volumes.mask,
                grid=(initial.origin, initial.step, initial.shape), initial=initial,
                active=active, weights=weights, whole=self._whole, margin=ORIENTED_MARGIN,
                **volumes.run_options(),
            )
        )  # fmt: skip


# --- memory and the driver -----------------------------------------------------------------------
def _warp_bytes(block_shape, reach: float) -> float:
    block = np.asarray(block_shape, np.float64)
    region = np.prod(block + 2 * (reach + SPLINE_SUPPORT + PREFILTER_MARGIN))
    return float(np.prod(block)) * BYTES_PER_WARP_VOXEL + region * 12.0


def plan_memory(volumes: TiledVolumes, params: CorrelationParams, field=None) -> tuple[int, int]:
    """``(estimate, budget)`` bytes of a tiled correction; raises :class:`MemoryBudgetError`.

    The estimate is the largest of: the DVC runs (:func:`.memory.estimate_peak_memory` for the
    first run's parameters, for second-order correcting matches on the smaller subvolume
    :func:`..engine.correction.pass_method.correction_params` may choose and, from a first-order
    run, for the oriented step's larger box, :func:`..engine.correction.oriented.oriented_params`),
    the warp blocks and the node blocks of the local residuals, each times the blocks held at once.
    """
    from ..engine.correction.oriented import oriented_params
    from ..engine.correction.pass_method import MIN_PASS_SUBVOLUME, PASS_SUBVOLUME_FRACTION

    shape = volumes.shape
    dtype = np.result_type(volumes.reference.dtype, volumes.deformed.dtype)
    masked = volumes.mask is not None
    budget, concurrency, where = memory_budget(volumes.client, volumes.workers, volumes.max_memory)
    grid = None if field is None else (field.origin, field.step, field.shape)
    subvolume = 2 * int(round(PASS_SUBVOLUME_FRACTION * params.half)) + 1
    subvolume = min(params.subvolume, max(MIN_PASS_SUBVOLUME, subvolume))
    candidates = [(params, 0), (params.replace(order=2, subvolume=subvolume), 0)]
    if params.order == 1:  # the oriented step's larger box, never beyond the volume
        box = min(oriented_params(params)[0].subvolume, 2 * ((min(shape) - 1) // 2) + 1)
        candidates.append((params.replace(subvolume=max(box, params.subvolume)), ORIENTED_MARGIN))
    estimates = []
    for candidate, margin in candidates:
        sizes = dict(workers=concurrency, masked=masked, grid=grid, margin=margin)
        batch = volumes.batch_shape
        if batch is None:
            batch = choose_batch_shape(shape, dtype, candidate, budget, **sizes)
        batch = tuple(int(b) for b in np.broadcast_to(np.asarray(batch), (3,)))
        estimate = estimate_peak_memory(shape, dtype, candidate, batch, **sizes)
        _refuse_if_over(estimate, budget, volumes.max_memory, batch, concurrency, where)
        estimates.append(estimate)
    reach = 0.0
    if field is not None and np.isfinite(field.u).any():
        reach = float(np.nanmax(np.abs(field.u)))
    step = params.step if field is None else max(field.step)
    blocks = concurrency * max(
        _warp_bytes(volumes.block_shape, reach),
        node_bytes(np.broadcast_to(step, (3,)), volumes.node_block, params.half, reach),
    )
    estimate = int(max(max(estimates), blocks))
    what = "the correction's warp and residual blocks"
    refuse_blocks_over(blocks, budget, volumes.max_memory, concurrency, where, what)
    return estimate, int(budget)


def correct_tiled_iter(
    reference,
    deformed,
    field: DisplacementField | None = None,
    params: CorrelationParams | None = None,
    *,
    frame: str = CorrectionOptions.frame,
    update: str = CorrectionOptions.update,
    max_passes: int = CorrectionOptions.max_passes,
    min_improvement: float = CorrectionOptions.min_improvement,
    mask=None,
    clean_options: dict | None = None,
    batch_shape=RunOptions.batch_shape,
    max_memory: int | str | None = RunOptions.max_memory,
    workers: int | None = RunOptions.workers,
    scheduler=RunOptions.scheduler,
    device="cpu",
    block_shape=CORRECTION_BLOCK,
    node_block: int = NODE_BLOCK,
    temp_dir=None,
    selective: bool = True,
    noise_fit: bool = CorrectionOptions.noise_fit,
) -> Generator[Progress, None, DisplacementField]:
    """Self-correct a field of two lazily read volumes, batch by batch; yields progress.

    Parameters
    ----------
    reference, deformed : LazyVolume, path or array, shape (nz, ny, nx)
        ``G`` and ``F`` (:func:`..io.lazy.as_lazy`: TIFF, Zarr, OME-Zarr, .npy, slices...).
    field, params, frame, update, max_passes, min_improvement, clean_options, selective, noise_fit
        As :func:`..engine.correction.self_correction.correct_iter` (``field`` None: a tiled DVC runs first).
    mask : LazyVolume, path or array, optional
        Reference-space material mask (non-zero = inside).
    batch_shape, max_memory, workers, scheduler, device
        As :func:`.correlate.correlate_tiled_iter`, for every DVC run and (``workers``,
        ``scheduler``) the blocks of the warps and residuals.
    block_shape, node_block, temp_dir
        See :class:`TiledVolumes`.

    Yields
    ------
    Progress
        ``"plan"`` first (the estimated peak memory), then as :func:`correct_iter` with the
        blocks of the warps and the DVC batches.

    Returns
    -------
    DisplacementField
        As :func:`..engine.correction.self_correction.correct_iter`; ``metadata["correction"]["tiled"]``
        records the estimate and the blocks.

    Raises
    ------
    MemoryBudgetError
        Before any work, when the estimated peak memory exceeds the machine or ``max_memory``.
    """
    check_options(frame, update, max_passes, min_improvement)
    volumes = TiledVolumes(
        reference,
        deformed,
        frame,
        mask,
        batch_shape=batch_shape,
        max_memory=max_memory,
        workers=workers,
        scheduler=scheduler,
        device=device,
        block_shape=block_shape,
        node_block=node_block,
        temp_dir=temp_dir,
    )
    try:
        if field is not None:
            check_field_on_volume(field, volumes.shape)
            field, _ = flag_absurd_nodes(field, volumes.shape)  # a few: failed matches
            nodes = np.concatenate([np.asarray(field.origin), np.asarray(field.step)])
            if np.max(np.abs(nodes - np.rint(nodes))) > 1e-6:
                raise ValueError(
                    f"the field's grid (origin {field.origin}, step {field.step}) is not on "
                    "whole voxels: regrid it (correct --grid-step N) or correct it in memory"
                )
        params = params_of(field, params)
        estimate, budget = plan_memory(volumes, params, field)
        blocks = int(np.prod([-(-n // b) for n, b in zip(volumes.shape, volumes.block_shape)]))
        largest = "x".join(str(min(b, n)) for b, n in zip(volumes.block_shape, volumes.shape))
        at_once = volumes.workers if volumes.client is None else "cluster"
        yield Progress(
            "plan",
            1,
            1,
            f"estimated peak memory {format_bytes(estimate)} (allowed {format_bytes(budget)}); "
            f"warps in {blocks} blocks of up to {largest} voxels ({at_once} at a time)",
        )
        result = yield from correct_volumes_iter(
            volumes,
            field,
            params,
            update=update,
            max_passes=max_passes,
            min_improvement=min_improvement,
            clean_options=clean_options,
            selective=selective,
            noise_fit=noise_fit,
        )
    finally:
        volumes.close()  # the temporary arrays, also on error or cancel (idempotent)
    result.metadata["correction"]["tiled"] = {
        "estimated_peak_bytes": int(estimate),
        "block_shape": list(volumes.block_shape),
        "node_block": int(volumes.node_block),
        "scheduler": "local threads" if volumes.client is None else str(scheduler),
    }
    return result


def correct_tiled(reference, deformed, field=None, params=None, **kwargs) -> DisplacementField:
    """Blocking form of :func:`correct_tiled_iter` (same parameters, no progress)."""
    return run_to_completion(correct_tiled_iter(reference, deformed, field, params, **kwargs))
