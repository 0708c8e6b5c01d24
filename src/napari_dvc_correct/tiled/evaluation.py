"""The accuracy evaluation of large volumes, block by block on Dask.

:func:`evaluate_tiled_iter` computes the same :class:`..engine.evaluation.results.Evaluation` as
:func:`..engine.evaluation.accuracy.evaluate_iter` — mean residuals, background residual (eq. 1), phases and
their Table 1 statistics, accuracy index (eq. 2), local accuracy and the curves against strain —
from lazily read volumes (TIFF, Zarr, ...), holding only a few blocks at a time. Both run the
engine's block code (:mod:`..engine.evaluation.accuracy_blocks`): the in-memory path on z-slabs of arrays,
this one on 3-D blocks that read their region of the other volume (the positions the field
reaches, plus :data:`.memory.SPLINE_SUPPORT` + :data:`.memory.PREFILTER_MARGIN` voxels) and
prefilter it there (:func:`.volumes.sample_lazy`).

Two passes over the volumes, each a list of ``dask.delayed`` block tasks (local threads or a
``dask.distributed`` cluster, :mod:`.scheduling`):

1. **scan**: finite values, the gray range of each state and, for ``phases="auto"``, the lattice
   subsample multi-Otsu uses (:func:`..engine.evaluation.phases.lattice_sample`: the very voxels the
   in-memory run samples, so the thresholds are equal);
2. **blocks**: the phases of both states (Table 1 sums and counts) and, for every field, the
   residual, the mapped phases and their sums (:func:`..engine.evaluation.accuracy_blocks.field_block`);
   with ``outputs`` the residual and label volumes are written block by block (Zarr or TIFF,
   committed only when every block is written).

What differs from the in-memory run: each block prefilters its own region of the other volume,
whose coefficients equal the whole volume's to float32 rounding (about 1e-7 of the gray range,
docs/scaling.md), so residuals agree to that and sums to the order of the float64 rounding of
their addition order; a voxel whose moved gray lies within that rounding of a threshold may take
the other phase.
"""

from __future__ import annotations

import os
from collections.abc import Iterator

import numpy as np

from ..engine.evaluation.accuracy import (
    assemble_evaluation,
    check_same_phase_count,
    phase_contrast,
    plan_evaluation,
)
from ..engine.evaluation.accuracy_blocks import (
    FieldAccumulator,
    field_block,
    field_partial,
    halo_gradient,
)
from ..engine.evaluation.accuracy_pair import (
    pair_start_map,
)
from ..engine.evaluation.binning import node_voxels
from ..engine.evaluation.error_estimate import error_region_half
from ..engine.evaluation.error_scales import window_ladder
from ..engine.evaluation.gray_noise import scan_noises
from ..engine.evaluation.local_accuracy import region_half
from ..engine.evaluation.options import EvaluationOptions
from ..engine.evaluation.phases import (
    NO_PHASE,
    OTSU_SAMPLES,
    PhaseTotals,
    label_phases,
    lattice_sample,
    otsu_stride,
    otsu_thresholds,
    validate_thresholds,
)
from ..engine.fields.field_spline import FieldSpline
from ..engine.pair_checks import check_field_on_volume
from ..engine.progress import Progress, run_to_completion
from ..engine.run_options import RunOptions
from ..io.lazy import as_lazy, open_volume
from ..io.lazy_outputs import create_output
from . import scheduling
from .evaluation_pair import measure_pair, region_block
from .memory import (
    PREFILTER_MARGIN,
    SPLINE_SUPPORT,
    MemoryBudgetError,
    available_memory,
    format_bytes,
)
from .volumes import LazySampler, _block_slices

#: Default voxels per block (z, y, x).
DEFAULT_EVALUATION_BLOCK = (128, 128, 128)

#: Bytes per voxel of a block while :func:`..engine.evaluation.accuracy_blocks.field_block` runs on it
#: (dense field, voxel lattice and displaced positions as float64, moved, residual and the two
#: states as float32, labels, integral images of sum and count, cell indices).
BYTES_PER_BLOCK_VOXEL = 128

#: Bytes per voxel of the other volume's region a block reads (float32 region, its float32
#: coefficients, scipy's line buffers). With the constant above: 169 B per block voxel for a 64³
#: block and its 96³ region, against a tracemalloc peak of 137 (reference mode) and 140 (loaded)
#: measured for one block task.
BYTES_PER_REGION_VOXEL = 12

#: Bytes per grid node of each field held by the driver (field, spline coefficients, strain,
#: cell and node sums and counts, local maps).
BYTES_PER_NODE = 400


def _reach(field) -> int:
    """Voxels a block's region of the other volume reaches beyond the block (displacement + taps)."""
    u = np.asarray(field.u)
    largest = float(np.nanmax(np.abs(u))) if np.isfinite(u).any() else 0.0
    return int(np.ceil(largest)) + SPLINE_SUPPORT + PREFILTER_MARGIN + 1


def estimate_evaluation_memory(volume_shape, block_shape, fields, *, workers: int = 1) -> int:
    """Estimated peak memory (bytes) of :func:`evaluate_tiled_iter`.

    Parameters
    ----------
    volume_shape : tuple of 3 ints
        ``(nz, ny, nx)``.
    block_shape : tuple of 3 ints
        Voxels per block.
    fields : list of DisplacementField
        The fields evaluated (their grids, and their largest displacement widens the regions).
    workers : int
        Blocks in memory at once.

    Returns
    -------
    int
        ``workers`` blocks (the block's arrays and its region of the other volume) plus the
        fields' grids and the multi-Otsu samples of both states.
    """
    shape = np.asarray([int(n) for n in volume_shape], np.int64)
    block = np.minimum(np.asarray([int(b) for b in block_shape], np.int64), shape)
    reach = max((_reach(f) for f in fields), default=SPLINE_SUPPORT + PREFILTER_MARGIN)
    region = np.minimum(block + 2 * reach, shape)
    per_block = float(np.prod(block)) * BYTES_PER_BLOCK_VOXEL + float(np.prod(region)) * (
        BYTES_PER_REGION_VOXEL
    )
    stride = otsu_stride(tuple(shape))
    samples = min(OTSU_SAMPLES, int(np.prod(-(-shape // stride))))
    fixed = sum(int(np.prod(f.shape)) for f in fields) * BYTES_PER_NODE + 2 * samples * 20
    return int(max(int(workers), 0) * per_block + fixed)


def choose_block_shape(volume_shape, fields, budget: int, *, workers: int = 1):
    """Largest cubic block (edge a multiple of 16, clipped to the volume) that fits ``budget``.

    Raises
    ------
    MemoryBudgetError
        If even a 16³ block does not fit.
    """
    shape = [int(n) for n in volume_shape]
    need = None
    for edge in range(16 * (-(-max(shape) // 16)), 0, -16):
        block = tuple(min(edge, n) for n in shape)
        need = estimate_evaluation_memory(shape, block, fields, workers=workers)
        if need <= budget:
            return block
    raise MemoryBudgetError(
        f"even blocks of 16³ voxels need an estimated {format_bytes(need)} with {workers} "
        f"block(s) at once, more than the {format_bytes(budget)} allowed: use fewer workers or "
        "allow more memory (--max-memory)"
    )


# --- block tasks (run on workers) ----------------------------------------------------------------
def _read_finite(volume, block, name):
    values = volume.read_region(block)
    if not np.all(np.isfinite(values)):
        z, y = block[0], block[1]
        raise ValueError(
            f"the {name} contains NaN or infinite values (in z {z.start}:{z.stop}, "
            f"y {y.start}:{y.stop})"
        )
    return values


def _scan_block(reference, deformed, block, stride, region=None):
    """Finite check, gray range and the multi-Otsu lattice sample of both states in one block
    (range and sample over the specimen region's voxels, with one)."""
    inside = region_block(region, block)
    out = []
    for volume, name in ((reference, "reference volume"), (deformed, "deformed volume")):
        values = _read_finite(volume, block, name)
        if inside is not None:
            values = np.where(inside, values.astype(np.float64), np.nan)
        sample = None if stride is None else lattice_sample(values, block, stride)
        finite = values[np.isfinite(values)] if inside is not None else values
        low = float(finite.min()) if finite.size else np.inf
        high = float(finite.max()) if finite.size else -np.inf
        out.append((low, high, sample))
    return out


def _evaluate_block(reference, deformed, splines, block, setup, outputs, region=None):
    """Phases of both states and every field's totals in one block; writes the volumes asked."""
    mode, thresholds, plan, centers, halves, mapping, mapped_levels = setup
    g = reference.read_region(block)
    f = deformed.read_region(block)
    inside = region_block(region, block)
    labels = [label_phases(g, thresholds[0]), label_phases(f, thresholds[1])]
    grays = (g, f)
    if inside is not None:  # outside the specimen: no phase, no gray range
        for lab in labels:
            lab[~inside] = NO_PHASE
        grays = tuple(np.where(inside, v.astype(np.float64), np.nan) for v in (g, f))
    phase_totals = [
        PhaseTotals(thresholds[k].size + 1).add(v, lab)
        for k, (v, lab) in enumerate(zip(grays, labels))
    ]
    for key, lab in zip(("labels_reference", "labels_deformed"), labels):
        if key in outputs:
            outputs[key].write(block, lab)
    if mode == "reference":
        own, other, own_labels = g, deformed, labels[0]
        other_thresholds = thresholds[0] if mapped_levels else thresholds[1]
    else:
        own, other, other_thresholds = f, reference, thresholds[0]
        own_labels = None if mapping is not None else labels[1]

    sampler = LazySampler(other)  # a callable, and a one-pass pull-back (reference mode)
    own_volume = reference if mode == "reference" else deformed
    gradient = halo_gradient(
        own_volume.read_region,
        block,
        own_volume.shape,
        None if mode == "reference" else mapping,
        instrument=True,
    )

    totals = []
    for index, ((name, _), spline) in enumerate(zip(plan.named, splines)):
        result, _, residual, mapped = field_block(
            own, sampler, spline, block, mode, other_thresholds, own_labels,
            plan.bin_fields[index], centers[index], halves[index], mapping,
            window_ladder(error_region_half(plan.named[index][1])), gradient, inside,
        )  # fmt: skip
        for key, values in ((("residual", name), residual), (("labels_mapped", name), mapped)):
            if key in outputs:
                outputs[key].write(block, values)
        totals.append(result)
    return phase_totals, totals


def _description(key) -> dict:
    """The metadata :func:`..report.write_volumes` gives the same volume."""
    if key in ("labels_reference", "labels_deformed"):
        return {"quantity": f"phases, {key.split('_')[1]}"}
    quantity = {"residual": "gray residual", "labels_mapped": "phases mapped by the field"}
    if not (isinstance(key, tuple) and len(key) == 2 and key[0] in quantity):
        raise ValueError(
            f"unknown output {key!r}: use 'labels_reference', 'labels_deformed', "
            "('residual', name) or ('labels_mapped', name)"
        )
    return {"quantity": quantity[key[0]], "field": key[1]}


# --- the driver ----------------------------------------------------------------------------------
def _run(tasks, scheduler, workers, client, stage, progress_every=1):
    """Run ``tasks``; yield a Progress per finished task, then return the results in order."""
    results = [None] * len(tasks)
    with scheduling.running(tasks, scheduler, workers, client) as finished:
        for done, (index, value) in enumerate(finished, start=1):
            results[index] = value
            if done % progress_every == 0 or done == len(tasks):
                yield Progress(stage, done, len(tasks), f"block {done} of {len(tasks)}")
    return results


def evaluate_tiled_iter(
    reference,
    deformed,
    fields,
    *,
    phases=EvaluationOptions.phases,
    phases_deformed=EvaluationOptions.phases_deformed,
    n_phases: int = EvaluationOptions.n_phases,
    phase_pair: tuple[int, int] | None = EvaluationOptions.phase_pair,
    mode: str = EvaluationOptions.mode,
    strain_measure: str = EvaluationOptions.strain_measure,
    strain_method: str = EvaluationOptions.strain_method,
    strain_window: int = EvaluationOptions.strain_window,
    n_bins: int = EvaluationOptions.n_bins,
    bin_edges=None,
    shared_background: bool = EvaluationOptions.shared_background,
    bin_by: str | None = EvaluationOptions.bin_by,
    outputs: dict | None = None,
    block_shape=RunOptions.block_shape,
    max_memory=RunOptions.max_memory,
    workers: int | None = RunOptions.workers,
    scheduler=RunOptions.scheduler,
    gray_levels=EvaluationOptions.gray_levels,
    background_fields=None,
    pair=None,
    region=None,
) -> Iterator[Progress]:
    """:func:`..engine.evaluation.accuracy.evaluate_iter` on lazily read volumes, block by block (generator).

    Yields :class:`Progress` (``"plan"`` with the memory estimate, ``"scan"``, ``"evaluate"``)
    and returns the :class:`..engine.evaluation.results.Evaluation`.

    Parameters
    ----------
    reference, deformed : lazy volume, path or array
        ``G`` and ``F`` (:func:`..io.lazy.as_lazy`), of one shape.
    fields, phases, phases_deformed, n_phases, phase_pair, mode, strain_measure, strain_method, \
strain_window, n_bins, bin_edges, shared_background, bin_by, gray_levels, background_fields, pair
        As :func:`..engine.evaluation.accuracy.evaluate_iter` (fields must be finite: clean them first).
        The pair's map and ``r0`` are measured block by block, three passes per candidate
        field (two fit the map, one measures ``r0``), as in memory.
    region : ndarray of bool or lazy region (``read_region``), optional
        The specimen region (reference space), as :func:`..engine.evaluation.accuracy.evaluate_iter`'s:
        read block by block.
    outputs : dict, optional
        Volumes to write, key -> path (``.zarr``, ``.tif``): ``"labels_reference"``,
        ``"labels_deformed"`` (uint8 phases), ``("residual", name)`` (float32, NaN where
        undefined) and ``("labels_mapped", name)`` (uint8, 255 where undefined) for field
        ``name``. The result's ``residual``, ``labels_mapped`` and label volumes are then these
        files opened lazily (else None).
    block_shape : tuple of 3 ints, optional
        Voxels per block (default: the largest cube that fits the memory, at most
        :data:`DEFAULT_EVALUATION_BLOCK`).
    max_memory : int, optional
        Peak memory the run may use (bytes); with the machine's (or a cluster worker's)
        available memory, the budget the estimate must fit.
    workers : int, optional
        Blocks at once on this machine (default: up to 4); a cluster uses all its threads.
    scheduler : None, "threads", "sync", address or distributed.Client
        See :mod:`.scheduling`.

    Raises
    ------
    MemoryBudgetError
        If the estimated peak memory exceeds the budget (nothing is read or written then).
    ValueError
        As the in-memory evaluation: bad thresholds, an empty phase, a field that does not fit.
    """
    import dask

    reference, deformed = as_lazy(reference), as_lazy(deformed)
    shape = tuple(int(n) for n in reference.shape)
    if tuple(deformed.shape) != shape:
        raise ValueError(
            f"reference {shape} and deformed {tuple(deformed.shape)} volumes must have the "
            "same shape"
        )
    plan = plan_evaluation(
        fields, shape, mode=mode, strain_measure=strain_measure, strain_method=strain_method,
        strain_window=strain_window, n_bins=n_bins, bin_edges=bin_edges,
        shared_background=shared_background, bin_by=bin_by,
    )  # fmt: skip
    for name, item in plan.named:
        check_field_on_volume(item, shape, f"field {name!r}")
        if not np.all(np.isfinite(item.u)):
            raise ValueError(f"field {name!r} holds NaN displacements: clean it first")
    items = [item for _, item in plan.named]
    outputs = dict(outputs or {})
    names = [name for name, _ in plan.named]
    metadata = {key: _description(key) for key in outputs}
    for key in outputs:
        if isinstance(key, tuple) and key[1] not in names:
            raise ValueError(f"output {key!r} names no evaluated field (fields: {names})")

    client, owned = (None, False)
    if not scheduling.is_local(scheduler):
        client, owned = scheduling.connect(scheduler)
    created = {}
    try:
        if client is not None:
            total_threads, concurrency, worker_limit = scheduling.cluster_resources(client)
            workers = total_threads
            budget, where = worker_limit or available_memory(), f"each worker at {scheduler!r}"
        else:
            workers = min(4, os.cpu_count() or 1) if workers is None else int(workers)
            if workers < 1:
                raise ValueError(f"workers must be >= 1, got {workers}")
            concurrency, budget, where = workers, available_memory(), "this machine"
        if max_memory is not None:
            budget = min(budget, int(max_memory))
        if block_shape is None:
            block_shape = choose_block_shape(shape, items, budget, workers=concurrency)
            block_shape = tuple(min(b, d) for b, d in zip(block_shape, DEFAULT_EVALUATION_BLOCK))
        block_shape = tuple(min(int(b), n) for b, n in zip(block_shape, shape))
        estimate = estimate_evaluation_memory(shape, block_shape, items, workers=concurrency)
        if estimate > budget:
            limit = (
                f"the limit of {format_bytes(budget)} (--max-memory)"
                if max_memory is not None and budget == int(max_memory)
                else f"the {format_bytes(budget)} available on {where}"
            )
            raise MemoryBudgetError(
                f"this evaluation needs an estimated {format_bytes(estimate)} at its peak "
                f"({concurrency} block(s) of {'x'.join(map(str, block_shape))} voxels at once), "
                f"more than {limit}: use smaller blocks or fewer workers, let --max-memory choose "
                "the block size, or run where more memory is available"
            )
        blocks = list(_block_slices(shape, block_shape))
        yield Progress(
            "plan", 1, 1,
            f"estimated peak memory {format_bytes(estimate)} (allowed {format_bytes(budget)}); "
            f"{len(blocks)} blocks of up to {'x'.join(map(str, block_shape))} voxels "
            f"({concurrency} at a time)",
        )  # fmt: skip

        # pass 1: finite values, gray ranges, multi-Otsu samples
        choices = (phases, phases if phases_deformed is None else phases_deformed)
        auto = [p is None or (isinstance(p, str) and p == "auto") for p in choices]
        for choice, is_auto in zip(choices, auto):
            if isinstance(choice, str) and not is_auto:
                raise ValueError(f"phases must be 'auto' or a list of thresholds, got {choice!r}")
        stride = otsu_stride(shape)  # multi-Otsu's lattice, and the gray-level map's start
        volumes = [dask.delayed(reference), dask.delayed(deformed)]
        scan = dask.delayed(_scan_block, pure=False)
        region_task = dask.delayed(region)
        tasks = [scan(*volumes, block, stride, region_task) for block in blocks]
        scanned = yield from _run(tasks, scheduler, workers, client, "scan")
        thresholds = []
        for k, (choice, name) in enumerate(zip(choices, ("reference volume", "deformed volume"))):
            if auto[k]:
                sample = np.concatenate([item[k][2] for item in scanned])
                thresholds.append(otsu_thresholds(sample, n_phases))
            else:
                low = min(item[k][0] for item in scanned)
                high = max(item[k][1] for item in scanned)
                thresholds.append(validate_thresholds(choice, (low, high), name))
        check_same_phase_count(*thresholds)

        def run(tasks, stage):
            return (yield from _run(tasks, scheduler, workers, client, stage))

        mapped_levels = gray_levels is not False
        if pair is None:
            candidates = dict(background_fields) if background_fields else dict(plan.named)
            start = pair_start_map(
                np.concatenate([item[0][2] for item in scanned]),
                np.concatenate([item[1][2] for item in scanned]),
            )
            moved_thresholds = (thresholds[0], thresholds[0] if mapped_levels else thresholds[1])
            noises = scan_noises(reference, deformed, read=lambda v, box: v.read_region(box))
            pair = yield from measure_pair(
                volumes, candidates, blocks, shape, moved_thresholds, gray_levels, start, run,
                region_task, noises, (reference, deformed, region),
            )  # fmt: skip
        mapping = None if pair.gray_levels.is_identity else pair.gray_levels

        # pass 2: phases and every field's totals, block by block
        for key, path in outputs.items():
            dtype = np.float32 if metadata[key]["quantity"] == "gray residual" else np.uint8
            created[key] = create_output(
                path, shape, dtype, chunks=block_shape, metadata=metadata[key]
            )
        splines = [dask.delayed(FieldSpline.from_field(item)) for item in items]
        setup = (
            mode,
            thresholds,
            plan,
            [node_voxels(item, shape) for item in items],
            [region_half(item) for item in items],
            mapping,
            mapped_levels,
        )
        task = dask.delayed(_evaluate_block, pure=False)
        shared = [dask.delayed(setup), dask.delayed(created)]
        tasks = [task(*volumes, splines, block, *shared, region_task) for block in blocks]
        results = yield from _run(tasks, scheduler, workers, client, "evaluate")
    except BaseException:
        for output in created.values():
            output.discard()
        raise
    finally:
        if owned:
            client.close()

    phase_totals = [PhaseTotals(t.size + 1) for t in thresholds]
    accumulators = [
        FieldAccumulator(item, plan.bin_fields[k], window_ladder(error_region_half(item)))
        for k, item in enumerate(items)
    ]
    for block_phases, block_fields in results:
        for total, part in zip(phase_totals, block_phases):
            total.merge(part)
        for accumulator, part in zip(accumulators, block_fields):
            accumulator.add(part)
    try:
        for total, t, name in zip(
            phase_totals, thresholds, ("reference volume", "deformed volume")
        ):
            total.check_nonempty(t, name)
        tables = tuple(total.table(t) for total, t in zip(phase_totals, thresholds))
        phase_contrast(*tables, phase_pair)  # errors of the assembly, before any output is kept
        for accumulator in accumulators:
            accumulator.background()
        final = {key: open_volume(output.commit()) for key, output in created.items()}
    except BaseException:
        for output in created.values():
            output.discard()
        raise
    partial = [
        field_partial(
            plan,
            k,
            accumulators[k],
            final.get(("residual", name)),
            final.get(("labels_mapped", name)),
        )  # fmt: skip
        for k, (name, _) in enumerate(plan.named)
    ]
    labels = (final.get("labels_reference"), final.get("labels_deformed"))
    return assemble_evaluation(plan, tuple(thresholds), tables, phase_pair, partial, labels, pair)


def evaluate_tiled(reference, deformed, fields, **options):
    """Run :func:`evaluate_tiled_iter` to the end and return its ``Evaluation``."""
    return run_to_completion(evaluate_tiled_iter(reference, deformed, fields, **options))
