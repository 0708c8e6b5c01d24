"""The scan pair's gray-level map and ``r0`` block by block (:mod:`.evaluation`'s first passes).

:func:`..engine.evaluation.accuracy_pair.measure_pair` on lazily read volumes: for every candidate
field, two passes over the blocks fit its map and one more measures its ``r0``; the best candidate
gives the pair's (:func:`..engine.evaluation.accuracy_pair.choose_best`). Blocks are slices
``(z, y, x)`` of the volumes.
"""

from __future__ import annotations

import numpy as np

from ..engine.evaluation.accuracy_pair import (
    background_from_sums,
    choose_best,
    residual_box,
    same_phase_block,
    with_noise_correlation,
)
from ..engine.evaluation.gray_levels import (
    DEFAULT_CELL,
    CellSums,
    GrayLevelMap,
    block_sums,
    cells_shape,
    fit_from_passes,
)
from ..engine.evaluation.gray_noise import noise_box, pair_noise
from ..engine.evaluation.phases import label_phases
from ..engine.fields.field_spline import FieldSpline
from ..engine.fields.warp import pull_back_block
from .volumes import LazySampler


def region_block(region, block):
    """The specimen region at ``block`` (bool), or None for the whole volume."""
    if region is None:
        return None
    if hasattr(region, "read_region"):
        return np.asarray(region.read_region(block)) != 0
    return np.asarray(region[block]) != 0


def _pair_moved(reference, deformed, spline, block, region):
    g = reference.read_region(block)
    moved = pull_back_block(LazySampler(deformed), spline, block, "nan")
    inside = region_block(region, block)
    if inside is not None:
        moved[~inside] = np.nan
    return g, moved


def _pair_sums_block(reference, deformed, spline, block, shape, cell, previous, region=None):
    """The gray-level map's cell sums of one block (:func:`..engine.evaluation.gray_levels.block_sums`)."""
    g, moved = _pair_moved(reference, deformed, spline, block, region)
    return block_sums(g, moved, block, shape, cell, previous)


def _pair_background_block(reference, deformed, spline, block, thresholds, gray, region=None):
    """Eq. 1's same-phase sums of one block with the map ``gray`` (``thresholds``: the
    reference's, then the moved scan's)."""
    g, moved = _pair_moved(reference, deformed, spline, block, region)
    labels = label_phases(g, thresholds[0])
    return same_phase_block(g, moved, labels, thresholds[1], gray, block)


def measure_pair(
    volumes, candidates, blocks, shape, thresholds, fit, start, run, region=None, noises=None,
    sources=None,
):  # fmt: skip
    """:func:`..engine.evaluation.accuracy_pair.measure_pair` block by block (generator): for every
    candidate two passes fit its map, one more measures its ``r0``. ``noises``: the scans' noise
    variances (:func:`..engine.evaluation.gray_noise.scan_noises`) for the map's fit;
    ``sources``: the reference, the deformed volume and the region themselves, to read the
    residual on the central block the noise correlation is measured on (None: not measured)."""
    import dask

    measured, residuals = {}, {}
    central = noise_box(shape)
    for name, field in candidates.items():
        spline = dask.delayed(FieldSpline.from_field(field))

        def sums_with(previous, spline=spline, name=name):
            task = dask.delayed(_pair_sums_block, pure=False)
            tasks = [
                task(*volumes, spline, block, shape, DEFAULT_CELL, previous, region)
                for block in blocks
            ]
            parts = yield from run(tasks, f"gray levels ({name})")
            total = CellSums.zeros(cells_shape(shape, DEFAULT_CELL))
            for part in parts:
                total.add(part)
            return total

        if isinstance(fit, GrayLevelMap):
            gray = fit
        elif fit:
            noise = None if noises is None else pair_noise(*noises, field.displacement)
            gray = yield from fit_from_passes(sums_with, start, shape, DEFAULT_CELL, noise=noise)
        else:
            gray = GrayLevelMap.identity(shape)
        task = dask.delayed(_pair_background_block, pure=False)
        tasks = [task(*volumes, spline, block, thresholds, gray, region) for block in blocks]
        parts = yield from run(tasks, f"background ({name})")
        same_sums = sum(p[0] for p in parts)
        same_counts = sum(p[1] for p in parts)
        largest = max(p[2] for p in parts)
        measured[str(name)] = (gray, background_from_sums(same_sums, same_counts, largest))
        if sources is not None:
            here = FieldSpline.from_field(field)
            g, moved = _pair_moved(*sources[:2], here, central, sources[2])
            residuals[str(name)] = residual_box(g, moved, gray, central)
    if sources is None:
        return choose_best(measured)
    fields = {str(k): v for k, v in candidates.items()}
    return with_noise_correlation(choose_best(measured), residuals, g, fields)
