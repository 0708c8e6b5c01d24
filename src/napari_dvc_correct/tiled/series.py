"""Scan series of volumes larger than memory: the engine's series loop on a batch-by-batch back-end.

:func:`series_tiled_iter` runs the one series loop of the engine
(:func:`..engine.series.strategies.series_volumes_iter`: the total or incremental strategy, the
self-correction of increments and/or totals, the cleaning and composition of the increments,
the provenance and the summary) with :class:`TiledSeries` doing every volume operation on lazily
read volumes (:mod:`..io.lazy`: TIFF, Zarr, OME-Zarr, .npy, folders of slices), as Dask tasks on
local threads or a ``dask.distributed`` cluster (:mod:`.scheduling`). The fields stay in memory;
no state is ever read whole.

* **Correlate a pair**: :func:`.correlate.correlate_tiled_iter` on the series' grid (its own
  whole-volume pass, seed pass and batches, as for ``correlate --tiled``).
* **Correct a field**: :func:`.correction.correct_tiled_iter` (warps to temporary Zarr arrays
  under ``temp_dir``, removed at its end).
* **The mask of an increment** (incremental strategy with a mask): the first state's mask moved by
  the cleaned total ``U_0→k−1`` (:func:`.correction.warp_mask_iter`) into a temporary Zarr array,
  removed once the increment is measured (and corrected).
* **The summary's mean gray residual** ``|V_k(X + U(X)) − V_0(X)|`` over the grid's hull:
  :func:`.volumes.mean_gray_residual_iter`, block by block, nothing written.

Memory: before any work the plan of every kind of run the series makes is drawn up and checked
— the correlation of each pair of stored dtypes (with the first state's mask, which bounds a
carried one), the correction (on the series' grid, from a zero field) and the residual blocks —
by the very code that plans those runs (each run's generator is started up to its first report,
the plan, and closed): a series over the machine's memory or ``max_memory`` is refused with
:class:`.memory.MemoryBudgetError` before anything is read. Each run checks its plan again when it
starts (the correction and the residual blocks then with the field's real reach).

Equal to :func:`..engine.series.strategies.series_iter` as the tiled correlation and correction are to theirs
(``docs/scaling.md``): the same statuses, displacements within the IC-GN tolerance's trace, mean
gray residuals to float32 rounding of the regions' prefilters.
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Generator, Sequence
from pathlib import Path

import numpy as np

from ..engine.correlation.params import CorrelationParams
from ..engine.fields.field import DisplacementField, grid_for_volume
from ..engine.progress import Progress, run_to_completion
from ..engine.series.strategies import STRATEGIES, SeriesResult, series_volumes_iter
from ..engine.series.volumes import SeriesVolumes
from ..io.atomic import scratch_dir
from ..io.lazy import as_lazy, open_volume
from . import scheduling
from .correction import CORRECTION_BLOCK, NODE_BLOCK, _warp_bytes, correct_tiled_iter
from .correction_blocks import warp_mask_iter
from .correlate import correlate_tiled_iter
from .memory import format_bytes, memory_budget, parse_memory, refuse_blocks_over
from .volumes import mean_gray_residual_iter


def _first_report(generator) -> Progress:
    """The first report of a tiled run (its plan: checks and memory estimate, no work); the
    generator is closed after it, so nothing is read."""
    try:
        return next(generator)
    finally:
        generator.close()


def _reach(field: DisplacementField | None) -> float:
    if field is None or not np.isfinite(field.u).any():
        return 0.0
    return float(np.nanmax(np.abs(field.u)))


class TiledSeries(SeriesVolumes):
    """The series' volume operations batch by batch on lazy volumes (see the module).

    Parameters
    ----------
    volumes : sequence of LazyVolume, path or array, each shape (nz, ny, nx)
        ``V0, V1, ...`` in loading order (:func:`..io.lazy.as_lazy`), the same shape.
    params : CorrelationParams
        DVC parameters of every correlation and correction.
    grid : (origin, step, shape)
        The POI grid in the first state's voxels, on whole voxels.
    mask : LazyVolume, path or array, optional
        The first state's material mask (non-zero = inside).
    correction_options : dict, optional
        Keyword arguments of :func:`.correction.correct_tiled_iter` (frame, update, max_passes,
        min_improvement, clean_options...).
    batch_shape, max_memory, workers, scheduler, device
        As :func:`.correlate.correlate_tiled_iter`, for every DVC run; ``workers`` and
        ``scheduler`` also for the blocks of the warps and residuals.
    block_shape : tuple of 3 ints
        Voxels per block of the warps (mask, correction) and of the residuals.
    node_block : int
        Grid nodes per block of the correction's local residuals.
    temp_dir : str or PathLike, optional
        Where the temporary Zarr arrays go (default: the system's temporary folder; on a cluster
        of several machines, a folder every worker sees at the same path).
    """

    def __init__(
        self,
        volumes: Sequence,
        params: CorrelationParams,
        grid: tuple,
        mask=None,
        correction_options: dict | None = None,
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
        self.volumes = [as_lazy(v) for v in volumes]
        if len(self.volumes) < 2:
            raise ValueError(f"a series needs at least 2 volumes, got {len(self.volumes)}")
        shapes = {tuple(int(n) for n in v.shape) for v in self.volumes}
        if len(shapes) != 1:
            raise ValueError(
                f"all volumes of a series must have the same shape, got {sorted(shapes)}"
            )
        self.shape = next(iter(shapes))
        if len(self.shape) != 3:
            raise ValueError(f"volumes must be 3-D (z, y, x), got shape {self.shape}")
        self.n_states = len(self.volumes)
        self.mask = None if mask is None else as_lazy(mask)
        if self.mask is not None and tuple(self.mask.shape) != self.shape:
            raise ValueError(
                f"mask shape {tuple(self.mask.shape)} differs from the volume {self.shape}"
            )
        self.params = params
        self.grid = grid
        self.options = dict(correction_options or {})
        self.batch_shape = batch_shape
        self.max_memory = None if max_memory is None else parse_memory(max_memory)
        self.device = device
        self.workers_option = workers
        self.workers = min(4, os.cpu_count() or 1) if workers is None else int(workers)
        if self.workers < 1:
            raise ValueError(f"workers must be >= 1, got {workers}")
        self.block_shape = tuple(int(b) for b in np.broadcast_to(block_shape, (3,)))
        self.node_block = int(node_block)
        self.scheduler = scheduler
        self.client, self._owns_client = None, False
        if not scheduling.is_local(scheduler):
            self.client, self._owns_client = scheduling.connect(scheduler)
        self._temp_root = temp_dir
        self._temp_dir = None  # made when the first mask is carried
        self._temps: dict[int, Path] = {}
        self._count = 0

    # -- helpers
    @property
    def _where(self):
        return self.client if self.client is not None else self.scheduler

    def _run(self) -> dict:
        return dict(
            batch_shape=self.batch_shape,
            max_memory=self.max_memory,
            workers=self.workers_option,
            scheduler=self._where,
            device=self.device,
        )

    def _correction_run(self) -> dict:
        return dict(
            block_shape=self.block_shape,
            node_block=self.node_block,
            temp_dir=self._temp_root,
            **self._run(),
            **self.options,
        )

    def _residual_blocks(self, reach: float) -> int:
        """Bytes of the residual blocks held at once (``reach``: the field's largest |u|, voxels),
        as the correction's warp blocks; refused over the memory."""
        budget, concurrency, where = memory_budget(self.client, self.workers, self.max_memory)
        block = [min(b, n) for b, n in zip(self.block_shape, self.shape)]
        need = concurrency * _warp_bytes(block, reach)
        what = "the series' gray residual blocks"
        refuse_blocks_over(need, budget, self.max_memory, concurrency, where, what)
        return need

    # -- the plan
    def plan(self, strategy: str, correct_increments: bool, correct_total: bool) -> str:
        """Check every kind of run the series makes against the memory, before any work.

        Returns the plan as a sentence (the correlation's, the correction's and the residual
        blocks' estimates); raises :class:`.memory.MemoryBudgetError` (or ``ValueError`` for an
        input the runs refuse) instead.
        """
        pairs, corrected = [], []  # (i, j) of the DVC runs and of the corrections, in order
        for k in range(1, self.n_states):
            if strategy == "total" or k == 1:
                pairs.append((0, k))
                if correct_increments or correct_total:
                    corrected.append((0, k))
            else:
                pairs.append((k - 1, k))
                if correct_increments:
                    corrected.append((k - 1, k))
                if correct_total:
                    corrected.append((0, k))

        def kinds(pairs):
            seen = {}
            for i, j in pairs:
                seen.setdefault((str(self.volumes[i].dtype), str(self.volumes[j].dtype)), (i, j))
            return list(seen.values())

        parts = []
        for i, j in kinds(pairs):
            report = _first_report(
                correlate_tiled_iter(
                    self.volumes[i],
                    self.volumes[j],
                    self.params,
                    mask=self.mask,
                    grid=self.grid,
                    **self._run(),
                )
            )
            parts.append(f"correlation: {report.message}")
        if corrected:
            zero = DisplacementField.zeros(*self.grid)
            for i, j in kinds(corrected):
                report = _first_report(
                    correct_tiled_iter(
                        self.volumes[i],
                        self.volumes[j],
                        zero,
                        self.params,
                        mask=self.mask,
                        **self._correction_run(),
                    )
                )
                parts.append(f"correction: {report.message}")
        blocks = int(np.prod([-(-n // b) for n, b in zip(self.shape, self.block_shape)]))
        need = self._residual_blocks(0.0)
        parts.append(f"gray residuals: {blocks} blocks, estimated {format_bytes(need)}")
        return "; ".join(dict.fromkeys(parts))  # once each

    # -- the interface
    def correlate(self, i, j, mask):
        return correlate_tiled_iter(
            self.volumes[i], self.volumes[j], self.params, mask=mask, grid=self.grid, **self._run()
        )

    def correct(self, i, j, field, mask):
        return correct_tiled_iter(
            self.volumes[i], self.volumes[j], field, self.params, mask=mask,
            **self._correction_run(),
        )  # fmt: skip

    def carry_mask(self, total):
        if self._temp_dir is None:
            if self._temp_root is not None:
                Path(self._temp_root).mkdir(parents=True, exist_ok=True)  # named by the user
            self._temp_dir = scratch_dir("dvc-series", self._temp_root)  # a dead run's: removed
        self._count += 1
        path = yield from warp_mask_iter(
            self.mask,
            total,
            self._temp_dir / f"mask-{self._count}.zarr",
            run=(self.block_shape, self._where, self.workers),
        )
        if path is None:
            return None
        mask = open_volume(path)
        self._temps[id(mask)] = path
        return mask

    def mean_residual(self, k, total):
        self._residual_blocks(_reach(total))
        return (
            yield from mean_gray_residual_iter(
                self.volumes[0],
                self.volumes[k],
                total,
                block_shape=self.block_shape,
                scheduler=self._where,
                workers=self.workers,
            )
        )

    def release(self, mask) -> None:
        path = self._temps.pop(id(mask), None)
        if path is not None:
            shutil.rmtree(path, ignore_errors=True)

    def close(self) -> None:
        self._temps.clear()
        if self._temp_dir is not None:
            shutil.rmtree(self._temp_dir, ignore_errors=True)
            self._temp_dir = None
        if self._owns_client:
            self.client.close()
            self._owns_client = False


def series_tiled_iter(
    volumes: Sequence,
    params: CorrelationParams | None = None,
    *,
    strategy: str = "incremental",
    correct_increments: bool = False,
    correct_total: bool = False,
    correction_options: dict | None = None,
    mask=None,
    grid: tuple | None = None,
    batch_shape=None,
    max_memory: int | str | None = None,
    workers: int | None = None,
    scheduler=None,
    device="cpu",
    block_shape=CORRECTION_BLOCK,
    node_block: int = NODE_BLOCK,
    temp_dir=None,
) -> Generator[Progress, None, SeriesResult]:
    """Displacement fields of a scan series of lazily read volumes, batch by batch; yields progress.

    Parameters
    ----------
    volumes : sequence of LazyVolume, path or array, each shape (nz, ny, nx)
        States ``V0, V1, ...`` in loading order (:func:`..io.lazy.as_lazy`: TIFF, Zarr,
        OME-Zarr, .npy, folders of slices...), the same shape.
    params : CorrelationParams, optional
        DVC parameters for every correlation and every correction pass.
    strategy, correct_increments, correct_total, correction_options
        As :func:`..engine.series.strategies.series_iter` (``correction_options`` are keyword arguments of
        :func:`.correction.correct_tiled_iter`).
    mask : LazyVolume, path or array, shape (nz, ny, nx), optional
        Material mask in the first state's voxels (non-zero = inside); for increments it is
        carried to state ``k-1`` by the merged field.
    grid : (origin, step, shape), optional
        POI grid in the first state's voxels, on whole voxels (default
        :func:`..engine.fields.field.grid_for_volume`). A series at points runs in memory only.
    batch_shape, max_memory, workers, scheduler, device
        As :func:`.correlate.correlate_tiled_iter`, for every DVC run; ``workers`` and
        ``scheduler`` also for the blocks of the warps and residuals.
    block_shape, node_block, temp_dir
        See :class:`TiledSeries`.

    Yields
    ------
    Progress
        ``"plan"`` first (the estimated peak memory of each kind of run), then as
        :func:`..engine.series.strategies.series_iter`, stages prefixed by ``"state k of n"``, with the
        batches and blocks of every run.

    Returns
    -------
    SeriesResult
        As :func:`..engine.series.strategies.series_iter`; every field's ``metadata["tiled"]`` records its
        correlation's batches (and ``metadata["correction"]["tiled"]`` its correction's blocks).

    Raises
    ------
    MemoryBudgetError
        Before any work, when a run's estimated peak memory exceeds the machine or
        ``max_memory``.
    """
    if strategy not in STRATEGIES:
        raise ValueError(f"strategy must be one of {STRATEGIES}, got {strategy!r}")
    params = CorrelationParams() if params is None else params
    series = TiledSeries(
        volumes,
        params,
        grid,
        mask,
        correction_options,
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
        if series.grid is None:
            series.grid = grid_for_volume(series.shape, params.subvolume, params.step)
        message = series.plan(strategy, correct_increments, correct_total)
        yield Progress("plan", 1, 1, message)
    except BaseException:
        series.close()
        raise
    return (
        yield from series_volumes_iter(
            series,
            strategy=strategy,
            correct_increments=correct_increments,
            correct_total=correct_total,
        )
    )


def series_tiled(volumes: Sequence, params: CorrelationParams | None = None, **options):
    """Blocking form of :func:`series_tiled_iter` (same parameters, no progress)."""
    return run_to_completion(series_tiled_iter(volumes, params, **options))
