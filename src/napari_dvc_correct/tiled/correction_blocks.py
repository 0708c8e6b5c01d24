"""The block tasks of the out-of-core self-correction, run on workers: the statistics of the
scans, the gray-level sums, the warp with its residual, and the warp of a mask."""

from __future__ import annotations

import shutil
from collections.abc import Generator
from pathlib import Path

import numpy as np

from ..engine.evaluation.gray_levels import (
    block_sums,
)
from ..engine.evaluation.phases import lattice_sample
from ..engine.fields.field import DisplacementField
from ..engine.fields.field_spline import FieldSpline
from ..engine.fields.warp import (
    INVERT_MAX_ITERATIONS,
    INVERT_TOLERANCE,
    pull_back_block,
    warp_forward_block,
)
from ..engine.progress import Progress
from .volumes import LazySampler, _forward_values, write_iter


# --- block tasks (run on workers) ----------------------------------------------------------------
class NonZero:
    """A lazy volume read as 0/1 (``!= 0``): the material mask as the engine sees it."""

    def __init__(self, volume):
        self.volume = volume
        self.shape = tuple(volume.shape)
        self.dtype = np.dtype(np.float32)

    def read_region(self, slices):
        return (self.volume.read_region(slices) != 0).astype(np.float32)


def statistics_block(volume, stride, region):
    """The voxels of ``region`` on the lattice multi-Otsu samples, the sum and count of its
    finite values and how many are not finite."""
    block = volume.read_region(region)
    finite = np.isfinite(block)
    total = float(np.sum(block[finite], dtype=np.float64))
    return lattice_sample(block, region, stride), total, int(finite.sum()), int((~finite).sum())


def gray_sums_block(reference, deformed, spline, gray_cell, previous, block):
    """The gray-level map's cell sums of one block (:func:`..engine.evaluation.gray_levels.block_sums`)."""
    moved = pull_back_block(LazySampler(deformed), spline, block)
    g = reference.read_region(block)
    return block_sums(g, moved, block, reference.shape, gray_cell, previous)


def warp_residual_block(out, reference, deformed, spline, block, frame, fill, hull, gray):
    """The moved volume of one block (written) and the sum and count of its gray residual
    (with the gray-level map ``gray``: ``|map(F) - G'|`` or ``|map(F~) - G|``)."""
    if frame == "loaded":
        values, in_hull = warp_forward_block(
            LazySampler(reference),
            spline,
            block,
            INVERT_MAX_ITERATIONS,
            INVERT_TOLERANCE,
        )
        defined = np.isfinite(values)
        own = gray.apply(deformed.read_region(block), block)
        difference = np.abs(own - values)[defined & in_hull]
    else:
        values = pull_back_block(LazySampler(deformed), spline, block)
        inner = tuple(
            slice(max(b.start, h.start), min(b.stop, h.stop)) for b, h in zip(block, hull)
        )
        difference = np.zeros(0, np.float32)
        if all(s.stop > s.start for s in inner):
            local = tuple(slice(i.start - b.start, i.stop - b.start) for i, b in zip(inner, block))
            difference = np.abs(gray.apply(values[local], inner) - reference.read_region(inner))
            difference = difference[np.isfinite(difference)]
        defined = np.isfinite(values)
    values[~defined] = fill
    out.write(block, values)
    return float(np.sum(difference, dtype=np.float64)), int(difference.size)


def warp_mask_block(out, mask, spline, block):
    values = _forward_values(
        mask, spline, block, "extrapolate", INVERT_MAX_ITERATIONS, INVERT_TOLERANCE
    )
    inside = np.isfinite(values) & (values > 0.5)
    out.write(block, inside.astype(np.float32))
    return float(inside.sum()), int(inside.size)


def warp_mask_iter(mask, field: DisplacementField, path, *, run) -> Generator[Progress, None, Path]:
    """A material mask moved by ``field`` to the loaded state, block by block into ``path``.

    Inside (1) where the forward warp of the 0/1 mask (non-zero = material) exceeds 0.5, as
    ``warp.warp_forward(mask != 0, field, cval=0) > 0.5`` in memory; a float32 Zarr array.

    Parameters
    ----------
    mask : LazyVolume, shape (nz, ny, nx)
        The mask in the reference state's voxels.
    field : DisplacementField
        Lagrangian displacement (voxels) with finite nodes (cleaned).
    path : str or PathLike
        Where the ``.zarr`` array goes.
    run : (block_shape, scheduler, workers)
        As :func:`.volumes.write_iter`.

    Returns
    -------
    Path or None
        The written array's path; None (and nothing left at ``path``) when no voxel is inside.
    """
    summary = yield from write_iter(
        path,
        tuple(int(n) for n in mask.shape),
        1,
        warp_mask_block,
        [NonZero(mask), FieldSpline.from_field(field)],
        [],
        run=run,
        metadata={"quantity": "the mask warped to the loaded state"},
        stage="warp mask",
    )
    if not summary["mean"] > 0:
        shutil.rmtree(summary["path"], ignore_errors=True)
        return None
    return Path(summary["path"])
