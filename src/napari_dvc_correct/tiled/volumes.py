"""Dense field, warps, gray residual and strain of large volumes, chunk by chunk to Zarr or TIFF.

The voxel-wise operations of :mod:`.warp` for volumes that do not fit in memory: every output
block is a ``dask.delayed`` task (dask's local threaded scheduler by default, or a
``dask.distributed`` cluster, see :mod:`.scheduling`) that

1. evaluates the field's cubic spline on the block's voxel lattice (:meth:`..engine.fields.field_spline.FieldSpline.lattice`),
   or inverts it there (:meth:`..engine.fields.field_spline.FieldSpline.invert`) for the forward warp;
2. reads only the region of the input volume those positions reach, plus
   :data:`.memory.SPLINE_SUPPORT` + :data:`.memory.PREFILTER_MARGIN` voxels, from a lazy volume
   (:mod:`..io.lazy`), prefilters it and samples it (:func:`.interpolation.sample`) — equal to
   sampling the prefiltered whole volume to float32 rounding; a pull-back reads the region its
   box reaches (the field's displacement bounded on a coarse lattice) and samples it while the
   field is evaluated (:class:`LazySampler`);
3. writes the block into the output (:mod:`..io.lazy_outputs`), which is renamed onto its path only
   when every block is written.

The results equal :func:`..engine.fields.field_spline.densify`, :func:`..engine.fields.warp.pull_back`, :func:`..engine.fields.warp.warp_forward` and
:func:`..engine.evaluation.residual.gray_residual` on the whole arrays.
"""

from __future__ import annotations

from collections.abc import Generator

import numpy as np

from ..engine.correlation.interpolation import prefilter, sample
from ..engine.evaluation.strain import equivalent_strain_field
from ..engine.fields.field import DisplacementField
from ..engine.fields.field_spline import FieldSpline, as_field_spline
from ..engine.fields.inverse_per_voxel import region_bounds
from ..engine.fields.pull_back_fill import pull_back_box
from ..engine.fields.warp import (
    INVERT_MAX_ITERATIONS,
    INVERT_TOLERANCE,
    box_axes,
    pull_back_block,
    warp_forward_block,
)
from ..engine.progress import Progress
from ..io.lazy import as_lazy
from ..io.lazy_outputs import create_output, output_chunks
from . import scheduling
from .memory import PREFILTER_MARGIN, SPLINE_SUPPORT

#: Default voxels per output block (z, y, x).
DEFAULT_BLOCK = (32, 256, 256)


def _block_slices(shape, block):
    for z0 in range(0, shape[0], block[0]):
        for y0 in range(0, shape[1], block[1]):
            for x0 in range(0, shape[2], block[2]):
                yield (
                    slice(z0, min(shape[0], z0 + block[0])),
                    slice(y0, min(shape[1], y0 + block[1])),
                    slice(x0, min(shape[2], x0 + block[2])),
                )


def sample_lazy(volume, points: np.ndarray) -> np.ndarray:
    """Tricubic B-spline samples of a lazy volume at ``points`` (N, 3), reading one region.

    Equals ``interpolation.sample(prefilter(whole), points)`` to float32 rounding: the region
    spans the finite points plus the spline support and the prefilter margin. NaN for points
    outside the volume or not finite.
    """
    out = np.full(len(points), np.nan, np.float32)
    finite = np.all(np.isfinite(points), axis=1)
    if not finite.any():
        return out
    reach = SPLINE_SUPPORT + PREFILTER_MARGIN
    shape = np.asarray(volume.shape)
    low = np.floor(points[finite].min(axis=0)).astype(np.int64) - reach
    high = np.ceil(points[finite].max(axis=0)).astype(np.int64) + reach + 1
    low = np.clip(low, 0, shape)
    high = np.clip(high, 0, shape)
    if np.any(high <= low):
        return out  # every point is outside the volume
    region = volume.read_region(tuple(slice(int(a), int(b)) for a, b in zip(low, high)))
    inside = finite & np.all((points >= 0) & (points <= shape - 1), axis=1)
    out[inside] = sample(prefilter(region), points[inside] - low, cval=np.nan)
    return out


#: Lattice stride (voxels) of the coarse evaluation that bounds a field's displacement over a box.
REACH_STRIDE = 4


def displacement_reach(spline, box) -> np.ndarray:
    """Per axis, a bound (voxels, rounded up, plus one) on ``|u|`` over ``box`` from the field
    evaluated every :data:`REACH_STRIDE` voxels and at the box's last voxels."""
    axes = []
    for s in box:
        axis = np.arange(s.start, s.stop, REACH_STRIDE, dtype=np.float64)
        axes.append(np.unique(np.append(axis, s.stop - 1)))
    values = spline.lattice(*axes).reshape(-1, 3)
    values = values[np.all(np.isfinite(values), axis=1)]
    largest = np.abs(values).max(axis=0) if len(values) else np.zeros(3)
    return np.ceil(largest).astype(np.int64) + 1


class LazySampler:
    """Tricubic B-spline sampler of a lazy volume (:func:`sample_lazy` when called on points).

    :meth:`pull_back` gives ``F(X + u(X))`` over a box from one region read around it (the box
    widened by the field's reach, the spline's support and the prefilter margin), prefiltered
    and sampled in one pass (:func:`..engine.fields.pull_back_fill.pull_back_box`): no positions array.
    Voxels whose position leaves that region (the coarse reach missed an overshoot) are sampled
    by :func:`sample_lazy`, so the values are those of ``sample_lazy`` at every voxel, to float32
    rounding.
    """

    def __init__(self, volume) -> None:
        self.volume = volume

    def __call__(self, points: np.ndarray) -> np.ndarray:
        return sample_lazy(self.volume, points)

    def _region(self, spline, box):
        """The coefficients of the region a box's positions reach, its first voxel and the
        volume's shape."""
        shape = np.asarray(self.volume.shape, np.int64)
        start = np.array([s.start for s in box], np.int64)
        stop = np.array([s.stop for s in box], np.int64)
        margin = SPLINE_SUPPORT + PREFILTER_MARGIN
        reach = displacement_reach(spline, box)
        low = np.clip(start - reach - margin, 0, shape - 1)
        high = np.clip(stop + reach + margin, low + 1, shape)
        region = self.volume.read_region(tuple(slice(int(a), int(b)) for a, b in zip(low, high)))
        return prefilter(region), low, shape

    def pull_back(self, spline, box, outside: str = "extrapolate") -> np.ndarray:
        coefficients, low, shape = self._region(spline, box)
        margin = SPLINE_SUPPORT + PREFILTER_MARGIN
        values = pull_back_box(
            coefficients, spline, box, outside, region_start=low, whole_shape=shape, margin=margin
        )
        missed = np.isposinf(values)
        if missed.any():
            voxels = np.argwhere(missed) + np.array([s.start for s in box])
            points = voxels + spline(voxels.astype(np.float64))
            values[missed] = sample_lazy(self.volume, points)
        return values

    def warp_forward(self, inverter) -> tuple[np.ndarray, np.ndarray]:
        """``G(X)`` with ``X + u(X) = x`` over ``inverter``'s box (an
        :class:`..engine.fields.inverse_lattice.LatticeInverter`): one region read, sampled as the
        positions are made (its ``warp``); the same positions as its ``solve``."""
        coefficients, low, shape = self._region(inverter.spline, inverter.box)
        margin = SPLINE_SUPPORT + PREFILTER_MARGIN
        bounds = region_bounds(coefficients.shape, low, shape, margin)
        values, in_hull = inverter.warp(coefficients, region=bounds)
        missed = np.isposinf(values)
        if missed.any():
            positions = inverter.solve().positions
            values[missed] = sample_lazy(self.volume, positions[missed.reshape(-1)])
        return values, in_hull


def _finite_sum(values) -> tuple[float, int]:
    finite = np.isfinite(values)
    return float(np.sum(values[finite], dtype=np.float64)), int(finite.sum())


# --- block tasks (run on workers) ----------------------------------------------------------------
def _dense_block(out, spline, block, outside):
    values = spline.lattice(*box_axes(block), outside=outside)
    if values.shape[-1] == 1:
        values = values[..., 0]
    out.write(block, values)
    return _finite_sum(values)


def _pull_back_values(deformed, spline, block, outside):
    return pull_back_block(LazySampler(deformed), spline, block, outside)


def _forward_values(reference, spline, block, outside, max_iterations, tolerance):
    values, in_hull = warp_forward_block(
        LazySampler(reference), spline, block, max_iterations, tolerance
    )
    if outside == "nan":
        values[~in_hull] = np.nan
    return values


def _pull_back_block(out, deformed, spline, block, outside, cval):
    values = _pull_back_values(deformed, spline, block, outside)
    summary = _finite_sum(values)
    values[~np.isfinite(values)] = cval
    out.write(block, values)
    return summary


def _forward_block(out, reference, spline, block, outside, cval, max_iterations, tolerance):
    values = _forward_values(reference, spline, block, outside, max_iterations, tolerance)
    summary = _finite_sum(values)
    values[~np.isfinite(values)] = cval
    out.write(block, values)
    return summary


def _residual_values(reference, deformed, spline, block, mode, outside):
    if mode == "reference":
        moved = _pull_back_values(deformed, spline, block, outside)
        return np.abs(moved - reference.read_region(block))
    warped = _forward_values(
        reference, spline, block, outside, INVERT_MAX_ITERATIONS, INVERT_TOLERANCE
    )
    return np.abs(deformed.read_region(block) - warped)


def _residual_block(out, reference, deformed, spline, block, mode, outside):
    residual = _residual_values(reference, deformed, spline, block, mode, outside)
    out.write(block, residual)
    return _finite_sum(residual)


def _residual_sum_block(reference, deformed, spline, block, mode, outside):
    return _finite_sum(_residual_values(reference, deformed, spline, block, mode, outside))


# --- the driver ----------------------------------------------------------------------------------
def _write(path, shape, components, function, shared, extra, *, run, metadata, stage, progress):
    """:func:`write_iter` run to its end, ``progress`` (a callable or None) called on the way.

    The public writers below are each one call of this driver: their calls look alike (the
    duplicate finder pairs them) because they name the same slots, filled differently.
    """
    writing = write_iter(
        path, shape, components, function, shared, extra, run=run, metadata=metadata, stage=stage
    )
    while True:
        try:
            report = next(writing)
        except StopIteration as stop:
            return stop.value
        if progress is not None:
            progress(report)


def _summed_blocks(function, leading, shared, blocks, extra, scheduler, workers, stage):
    """Run ``function(*leading, *shared, block, *extra)`` on every block as ``dask.delayed``
    tasks (``shared`` handed over once, ``leading`` as it is); yield a :class:`Progress` per
    block, return the total ``(sum, count)`` of their results. Closing it early stops the blocks
    not yet started (:func:`.scheduling.running`)."""
    import dask

    client, owned = (None, False)
    if not scheduling.is_local(scheduler):
        client, owned = scheduling.connect(scheduler)
    try:
        delayed_shared = [dask.delayed(item) for item in shared]
        task = dask.delayed(function, pure=False)
        tasks = [task(*leading, *delayed_shared, block, *extra) for block in blocks]
        total, count = 0.0, 0
        with scheduling.running(tasks, scheduler, workers, client) as finished:
            for done, (_, (block_sum, block_count)) in enumerate(finished, start=1):
                total += block_sum
                count += block_count
                yield Progress(stage, done, len(tasks), f"block {done} of {len(tasks)}")
    finally:
        if owned:
            client.close()
    return total, count


def _residual_inputs(reference, deformed, mode, region):
    """``(reference, deformed, shape, outside)`` of a gray residual: the lazy volumes, the shape
    of the residual's frame and how the field goes beyond the grid's hull."""
    if mode not in ("reference", "loaded"):
        raise ValueError(f"mode must be 'reference' or 'loaded', got {mode!r}")
    if region not in ("hull", "volume"):
        raise ValueError(f"region must be 'hull' or 'volume', got {region!r}")
    reference = as_lazy(reference)
    deformed = as_lazy(deformed)
    shape = _check(reference.shape if mode == "reference" else deformed.shape, "shape")
    return reference, deformed, shape, "nan" if region == "hull" else "extrapolate"


def write_iter(
    path, shape, components, function, shared, extra, *, run, metadata, stage
) -> Generator[Progress, None, dict]:
    """Run ``function(out, *shared, block, *extra)`` on every block and commit the output.

    A generator: yields a :class:`Progress` after every block and returns the summary dict of
    the public writers. Closing it early (a cancelled caller) stops the blocks not yet started
    and removes the unfinished output. ``function`` returns ``(sum, count)`` of what it wrote
    (the summary's ``mean``). ``run`` is ``(block_shape, scheduler, workers)``.
    """

    block_shape, scheduler, workers = run

    shape = tuple(int(n) for n in shape)
    out_shape = shape if components == 1 else (*shape, components)
    block_shape = tuple(min(int(b), n) for b, n in zip(block_shape, shape))
    chunks = block_shape if components == 1 else (*block_shape, components)
    out = create_output(path, out_shape, np.float32, chunks=chunks, metadata=metadata)
    try:
        blocks = list(_block_slices(shape, output_chunks(out, block_shape)))
        total, count = yield from _summed_blocks(
            function, (out,), shared, blocks, extra, scheduler, workers, stage
        )
    except BaseException:
        out.discard()
        raise
    final = out.commit()
    return {
        "path": str(final),
        "shape": list(out_shape),
        "blocks": len(blocks),
        "mean": total / count if count else float("nan"),
        "defined_voxels": count,
    }


def _check(volume_shape, name):
    shape = tuple(int(n) for n in volume_shape)
    if len(shape) != 3 or min(shape) < 1:
        raise ValueError(f"{name} must be 3 positive ints (nz, ny, nx), got {shape}")
    return shape


def _outside(outside):
    if outside not in ("extrapolate", "nan"):
        raise ValueError(f"outside must be 'extrapolate' or 'nan', got {outside!r}")
    return outside


def write_dense_field(
    field: DisplacementField | FieldSpline,
    shape,
    path,
    *,
    outside: str = "extrapolate",
    block_shape=DEFAULT_BLOCK,
    scheduler=None,
    workers: int = 2,
    progress=None,
) -> dict:
    """Cubic-spline dense displacement field (paper step c) written to ``path``.

    Parameters
    ----------
    field : DisplacementField or FieldSpline
        Grid field with finite nodes (clean it first).
    shape : tuple of 3 ints
        Volume shape ``(nz, ny, nx)``.
    path : str or PathLike
        ``.zarr`` or ``.tif``: a float32 array of shape ``(nz, ny, nx, 3)``, components
        ``(uz, uy, ux)`` in voxels.
    outside : {"extrapolate", "nan"}
        As :func:`..engine.fields.field_spline.densify`.
    block_shape : tuple of 3 ints
        Voxels per task (and per Zarr chunk).
    scheduler, workers
        See :mod:`.scheduling`.
    progress : callable, optional
        Called with a :class:`Progress` after every block.

    Returns
    -------
    dict
        ``path``, ``shape``, ``blocks``, ``mean`` (of all components), ``defined_voxels``.
    """
    shape = _check(shape, "shape")
    return _write(
        path,
        shape,
        3,
        _dense_block,
        [as_field_spline(field)],
        [_outside(outside)],
        run=(block_shape, scheduler, workers),
        metadata={"quantity": "displacement (uz, uy, ux), voxels"},
        stage="densify",
        progress=progress,
    )


def write_pull_back(
    deformed,
    field: DisplacementField | FieldSpline,
    path,
    *,
    shape=None,
    cval: float = np.nan,
    outside: str = "extrapolate",
    block_shape=DEFAULT_BLOCK,
    scheduler=None,
    workers: int = 2,
    progress=None,
) -> dict:
    """``F~(X) = F(X + u(X))`` written to ``path`` (see :func:`..engine.fields.warp.pull_back`).

    ``deformed`` is a lazy volume, a path or an array (:func:`..io.lazy.as_lazy`).
    """

    deformed = as_lazy(deformed)
    shape = _check(deformed.shape if shape is None else shape, "shape")
    return _write(
        path,
        shape,
        1,
        _pull_back_block,
        [deformed, as_field_spline(field)],
        [_outside(outside), float(cval)],
        run=(block_shape, scheduler, workers),
        metadata={"quantity": "deformed volume pulled back to the reference frame"},
        stage="pull back",
        progress=progress,
    )


def write_warp_forward(
    reference,
    field: DisplacementField | FieldSpline,
    path,
    *,
    shape=None,
    cval: float = np.nan,
    outside: str = "extrapolate",
    max_iterations: int = 50,
    tolerance: float = 1e-4,
    block_shape=DEFAULT_BLOCK,
    scheduler=None,
    workers: int = 2,
    progress=None,
) -> dict:
    """``G'(X + u(X)) = G(X)`` (paper step d) written to ``path`` (see :func:`..engine.fields.warp.warp_forward`)."""

    reference = as_lazy(reference)
    shape = _check(reference.shape if shape is None else shape, "shape")
    return _write(
        path,
        shape,
        1,
        _forward_block,
        [reference, as_field_spline(field)],
        [_outside(outside), float(cval), int(max_iterations), float(tolerance)],
        run=(block_shape, scheduler, workers),
        metadata={"quantity": "reference volume warped to the loaded state"},
        stage="warp",
        progress=progress,
    )


def write_gray_residual(
    reference,
    deformed,
    field: DisplacementField | FieldSpline,
    path,
    *,
    mode: str = "reference",
    region: str = "hull",
    block_shape=DEFAULT_BLOCK,
    scheduler=None,
    workers: int = 2,
    progress=None,
) -> dict:
    """Gray residual volume written to ``path`` (see :func:`..engine.evaluation.residual.gray_residual`).

    Returns
    -------
    dict
        With ``mean``: the mean residual over the voxels where it is defined (as
        :func:`..engine.evaluation.residual.mean_gray_residual`).
    """

    reference, deformed, shape, outside = _residual_inputs(reference, deformed, mode, region)
    return _write(
        path,
        shape,
        1,
        _residual_block,
        [reference, deformed, as_field_spline(field)],
        [mode, outside],
        run=(block_shape, scheduler, workers),
        metadata={"quantity": f"gray residual ({mode} frame, {region})"},
        stage="residual",
        progress=progress,
    )


def mean_gray_residual_iter(
    reference,
    deformed,
    field: DisplacementField | FieldSpline,
    *,
    mode: str = "reference",
    region: str = "hull",
    block_shape=DEFAULT_BLOCK,
    scheduler=None,
    workers: int = 2,
) -> Generator[Progress, None, float]:
    """Mean of the gray residual block by block, nothing written; yields progress per block.

    The mean of :func:`..engine.evaluation.residual.mean_gray_residual` (same ``mode`` and ``region``) from
    lazily read volumes: every block (a ``dask.delayed`` task) reads its part of one volume and
    the region of the other its positions reach, and returns the sum and count of its defined
    residuals. Equal to the in-memory mean to float32 rounding of the regions' prefilters.

    Parameters
    ----------
    reference, deformed : LazyVolume, path or array, shape (nz, ny, nx)
        ``G`` and ``F`` (:func:`..io.lazy.as_lazy`).
    field : DisplacementField or FieldSpline
        Lagrangian displacement ``u(X)`` in voxels on a grid, nodes finite (clean it first).
    mode : {"reference", "loaded"}
        ``|F(X + u(X)) - G(X)|`` at the reference voxels, or ``|F(x) - G'(x)|`` at the loaded ones.
    region : {"hull", "volume"}
        Over the grid's hull only (default), or everywhere with the field extrapolated.
    block_shape : tuple of 3 ints
        Voxels per task.
    scheduler, workers
        See :mod:`.scheduling` (a ``distributed.Client`` is used as it is).

    Returns
    -------
    float
        The mean residual (gray levels); NaN where it is defined nowhere.
    """
    reference, deformed, shape, outside = _residual_inputs(reference, deformed, mode, region)
    block_shape = tuple(min(int(b), n) for b, n in zip(block_shape, shape))
    total, count = yield from _summed_blocks(
        _residual_sum_block,
        (),
        [reference, deformed, as_field_spline(field)],
        list(_block_slices(shape, block_shape)),
        [mode, outside],
        scheduler,
        workers,
        "residual",
    )
    return total / count if count else float("nan")


def write_equivalent_strain(
    field: DisplacementField,
    shape,
    path,
    *,
    measure: str = "small",
    method: str = "central",
    window: int = 5,
    outside: str = "extrapolate",
    block_shape=DEFAULT_BLOCK,
    scheduler=None,
    workers: int = 2,
    progress=None,
) -> dict:
    """Equivalent strain (eq. 3) at every voxel: the grid's strain densified by cubic splines.

    The strain is computed on the grid (:func:`.strain.equivalent_strain_field`, see there for
    ``measure``, ``method`` and ``window``), then interpolated like the displacement.

    Raises
    ------
    ValueError
        If some nodes have no strain (invalid displacement): clean the field first.
    """

    shape = _check(shape, "shape")
    values = equivalent_strain_field(field, measure=measure, method=method, window=window)
    if not np.all(np.isfinite(values)):
        raise ValueError(
            f"{int(np.sum(~np.isfinite(values)))} grid nodes have no strain: clean the field "
            "first (napari_dvc_correct.engine.correction.cleaning.clean)"
        )
    spline = FieldSpline(field.origin, field.step, values[..., None])
    return _write(
        path,
        shape,
        1,
        _dense_block,
        [spline],
        [_outside(outside)],
        run=(block_shape, scheduler, workers),
        metadata={"quantity": f"equivalent strain ({measure})"},
        stage="strain",
        progress=progress,
    )
