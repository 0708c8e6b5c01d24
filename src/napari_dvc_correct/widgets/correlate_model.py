"""The Correlate panel without Qt: checking the choices, previews, estimates and POI read-outs.

Everything here takes plain arrays (or napari layers only through :func:`layer_volume`) and is
tested without a viewer.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field

import numpy as np

from ..engine.correlation.params import CorrelationParams
from ..engine.fields.field import (
    GOOD_STATUSES,
    DisplacementField,
    Provenance,
    Status,
    grid_for_volume,
)
from ..engine.run_options import RunOptions
from ..tiled.memory import format_bytes
from .regions_model import whole

#: Cost of one IC-GN iteration per subvolume voxel (seconds, one core; see :func:`estimate_run`).
#: Measured on the sample data (96³, subvolume 31, 2 cores: ~18 s); :func:`record_timing` replaces
#: it with what the runs of this session measure.
SECONDS_PER_VOXEL_ITERATION = 1.0e-7
_calibration = {"seconds_per_voxel_iteration": SECONDS_PER_VOXEL_ITERATION}
#: Typical IC-GN iterations per POI (first order, speckle-poor soil).
TYPICAL_ITERATIONS = 8


#: Devices offered by the Correlate panel (key: engine name, value: label).
DEVICES = {
    "auto": "auto (GPU if available)",
    "cpu": "CPU (numba, all cores)",
    "cuda": "CUDA GPU (falls back to the CPU)",
}


@dataclass
class CorrelationJob:
    """A checked request: what the Correlate panel hands to the engine.

    Attributes
    ----------
    volumes : list of ndarray (nz, ny, nx)
        Two volumes (reference, deformed) for a pair; more for a scan series, in order.
    params : CorrelationParams
    mask : ndarray of bool (nz, ny, nx), regions_model.Region or None
        The region; a :class:`.regions_model.Region` is a lazy mask (read block by block by an
        out-of-core run, whole by an in-memory one).
    strategy : {"pair", "total", "incremental"}
    correct_states : bool
        For a series: self-correct every state's total displacement (engine/series/strategies.py).
    voxel_size, offset : tuple of 3 floats
        ``scale`` and ``translate`` (z, y, x) of the reference layer, for display.
    names : list of str
        Names of the layers (or states) the volumes come from.
    unit : str or None
        Length unit of ``voxel_size`` (``"µm"``...), None for plain voxels.
    kept : regions_model.Kept or None
        How many POIs the region keeps (None for the whole volume, and for a lazy threshold or
        Labels region, which the run itself reads).
    points : ndarray (N, 3) or None
        Points of interest in reference voxel indices (z, y, x), fractional allowed
        (:func:`points_in_voxels`); None for the regular grid. A pair only.
    points_layer : str
        Name of the Points layer they come from.
    tiled : bool
        Out of core (:mod:`..tiled`: a pair on the grid or at points, a series on the grid): the
        scans are read block by block, never whole (for lazily backed layers, or scans larger
        than memory).
    max_memory : str or None
        Peak memory of a tiled run (``"4GB"``...); None = about 1 GiB per concurrent batch.
    device : {"auto", "cpu", "cuda"}
        Where IC-GN runs for a pair (:func:`..engine.backend.select_device`); scan series run on
        the CPU.
    """

    volumes: list
    params: CorrelationParams
    mask: np.ndarray | None = None
    strategy: str = "pair"
    correct_states: bool = False
    voxel_size: tuple = (1.0, 1.0, 1.0)
    offset: tuple = (0.0, 0.0, 0.0)
    names: list = field(default_factory=list)
    device: str = RunOptions.device
    unit: str | None = None
    kept: object = None
    points: np.ndarray | None = None
    points_layer: str = ""
    tiled: bool = False
    max_memory: str | None = None

    @property
    def shape(self) -> tuple:
        return tuple(int(n) for n in self.volumes[0].shape)

    def run_options(self) -> RunOptions:
        """How the job runs: out of core (``tiled``) within ``max_memory``, IC-GN on ``device``."""
        from ..tiled.memory import parse_memory

        limit = parse_memory(self.max_memory) if self.max_memory else None
        return RunOptions(tiled=bool(self.tiled), device=self.device, max_memory=limit)


@dataclass
class CorrelationResult:
    """What a run returns to the panel: one ``(source, field)`` per field.

    Attributes
    ----------
    fields : list of (str, DisplacementField or ScatteredField)
    voxel_size, offset : tuple of 3 floats
        ``scale`` and ``translate`` (z, y, x) of the reference layer.
    series : list of DisplacementField or None
        A series' fields as its 4-D layers show them, state 0 (no displacement) first
        (:func:`..layers.series_fields`), made in the worker so the quantity on view is
        computed there for every state, state 0 included; None for a pair.
    """

    fields: list
    voxel_size: tuple = (1.0, 1.0, 1.0)
    offset: tuple = (0.0, 0.0, 0.0)
    series: list | None = None


def done_message(result: CorrelationResult, region_given: bool) -> str:
    """The panel's line after a run on the grid: the node counts of each field (by state for
    a series) and, where many nodes found no texture and the run had no region, the hint to
    give one (:meth:`..engine.fields.field.NodeCounts.region_hint`)."""
    lines = []
    for source, state_field in result.fields:
        counts = state_field.node_counts().text()
        lines.append(f"{source}: {counts}" if len(result.fields) > 1 else counts)
    hint = result.fields[0][1].node_counts().region_hint(region_given)
    return "Done: " + "; ".join(lines) + "." + (f" {hint} (Region)." if hint else "")


def _finish(field: DisplacementField, job: CorrelationJob, names) -> DisplacementField:
    """Record where the field belongs (for display, export, and the other panels)."""
    field.metadata.update(
        voxel_size=list(job.voxel_size),
        offset=list(job.offset),
        reference_layer=names[0],
        deformed_layer=names[1],
    )
    if job.unit:
        field.metadata["unit"] = job.unit
    return field


def run_job(job: CorrelationJob):
    """Generator run by the panel's worker: the grid run (:func:`run_grid_job`) or, when the
    job has points, :func:`run_points_job`."""
    if job.points is not None:
        return (yield from run_points_job(job))
    return (yield from run_grid_job(job))


def run_grid_job(job: CorrelationJob):
    """Generator run by the panel's worker: yields Progress, returns a :class:`CorrelationResult`.

    A pair gives one field, source ``"uncorrected"``; a series gives one field per state after
    the first, source ``"state k (total)"`` (or ``incremental``, ``+ corrected`` when each state
    was self-corrected), each the total displacement from state 0, and the result's ``series``
    (state 0 first, as the 4-D layers show it).
    """
    from ..jobs.correlate import correlate_job
    from ..layers import series_fields

    results = []
    if job.strategy == "pair":
        run = job.run_options()
        mask = job.mask if run.out_of_core else whole(job.mask)  # in memory: one array
        field = yield from correlate_job(
            job.volumes[0], job.volumes[1], job.params, mask=mask, run=run
        )
        field = _finish(field, job, job.names)
        results.append(("uncorrected", field))
    else:
        fields = yield from run_series(job)
        suffix = ", corrected" if job.correct_states else ""
        for k, field in enumerate(fields, start=1):
            field = _finish(field, job, [job.names[0], job.names[k]])
            source = f"state {k} ({job.strategy}{suffix})"
            results.append((source, field))
        series = series_fields([item[1] for item in results])
        return CorrelationResult(results, job.voxel_size, job.offset, series=series)
    return CorrelationResult(results, job.voxel_size, job.offset)


def run_points_job(job: CorrelationJob):
    """DVC at the job's points (:func:`..engine.correlation.correlate_points.correlate_points`).

    The guide field (the initial guess of every point) is correlated first on a grid of the
    job's step over the points' bounding box, with progress and cancel; then IC-GN runs at each
    point. Out of core (``job.tiled``) the guide runs in batches and the points in groups, each
    reading only its region (:func:`..tiled.points.correlate_points_tiled_iter`). Returns a
    :class:`CorrelationResult` with one ``("points", ScatteredField)``; the field's metadata
    says where it belongs (voxel size, offset, layers).
    """
    from ..jobs.correlate import points_job
    from .points_model import check_points

    params, points = job.params, np.asarray(job.points, dtype=np.float64)
    reference, deformed = job.volumes[0], job.volumes[1]
    check_points(points, job.shape, params.subvolume, job.points_layer)
    run = job.run_options()
    mask = job.mask if run.out_of_core else whole(job.mask)  # in memory: one array
    result = yield from points_job(reference, deformed, points, params, mask=mask, run=run)
    result.metadata.update(
        voxel_size=list(job.voxel_size),
        offset=list(job.offset),
        reference_layer=job.names[0],
        deformed_layer=job.names[1],
        points_layer=job.points_layer,
    )
    if job.unit:
        result.metadata["unit"] = job.unit
    return CorrelationResult([("points", result)], job.voxel_size, job.offset)


def is_lazy(volume) -> bool:
    """True for a volume napari shows lazily (a Dask or Zarr array, a memory map): one that the
    in-memory run would read whole."""
    return not isinstance(volume, np.ndarray) or isinstance(volume, np.memmap)


def suggest_tiled(volumes, memory: int | None = None) -> bool:
    """Whether a run should be out of core: a Dask or Zarr scan, or in-memory working copies
    (:func:`estimate_run`'s 6 float32 per voxel) above half the available ``memory``.

    A memory-mapped TIFF is judged by its size only: the in-memory run reads a small one whole
    in no time (a 4 MB scan is not a reason to go out of core)."""
    from ..tiled.memory import available_memory

    if any(is_lazy(v) and not isinstance(v, np.memmap) for v in volumes):
        return True
    voxels = float(np.prod(volumes[0].shape)) if volumes else 0.0
    memory = available_memory() if memory is None else memory
    return voxels * 4 * 6 > 0.5 * memory


def check_tiled(job_strategy: str, points, max_memory: str | None) -> str | None:
    """Refuse what a tiled run does not do; the memory limit checked (None = automatic).

    A pair runs out of core on a grid or at points of interest, a series on a grid."""
    if job_strategy != "pair" and points is not None:
        raise ValueError(
            "a series at points of interest runs in memory: untick 'out of core' or use the grid"
        )
    text = (max_memory or "").strip()
    if text in ("", "auto"):
        return None
    from ..tiled.memory import parse_memory

    parse_memory(text)  # raises ValueError with the accepted forms
    return text


def run_series(job: CorrelationJob):
    """Total displacements ``U_0→k`` of a scan series (:func:`..engine.series.strategies.series_iter`;
    out of core, :func:`..tiled.series.series_tiled_iter`: every state read batch by batch)."""
    from ..jobs.series import series_job

    run = job.run_options()
    result = yield from series_job(
        job.volumes,
        job.params,
        strategy=job.strategy,
        correct_total=job.correct_states,
        mask=job.mask if run.out_of_core else whole(job.mask),  # in memory: one array
        run=run,
    )
    return result.totals


def layer_volume(layer, index: int | None = None) -> np.ndarray:
    """The array of an Image layer (level 0 if multiscale); ``index`` picks a 4-D state."""
    data = layer.data[0] if getattr(layer, "multiscale", False) else layer.data
    if index is not None:
        data = data[index]
    return data


def named_volume(layers, name: str) -> np.ndarray:
    """The volume a field's metadata names: a layer, or ``"layer[k]"``, state k of a 4-D layer.

    ``layers`` is the viewer's layer list (indexable by name). Raises ValueError when the
    volume is not open any more.
    """
    import re

    match = re.fullmatch(r"(.*)\[(\d+)\]", str(name))
    if match and match.group(1) in layers:
        return layer_volume(layers[match.group(1)], int(match.group(2)))
    if name in layers:
        return layer_volume(layers[name])
    raise ValueError(f"the volume '{name}' this field was measured on is not open any more")


def layer_placement(layer) -> tuple[tuple, tuple]:
    """``(voxel_size, offset)``: the last three entries of ``scale`` and ``translate``."""
    return (
        tuple(float(v) for v in np.asarray(layer.scale)[-3:]),
        tuple(float(v) for v in np.asarray(layer.translate)[-3:]),
    )


#: Length units offered for the voxel size ("" = plain voxels, no physical size).
UNITS = ("", "nm", "µm", "mm")


def voxel_scale(scale, voxel_size: float) -> tuple:
    """``scale`` of a scan layer with an isotropic ``voxel_size`` on its last three axes."""
    scale = [float(v) for v in scale]
    if not voxel_size > 0:
        raise ValueError(f"the voxel size must be > 0, got {voxel_size}")
    return tuple(scale[:-3] + [float(voxel_size)] * 3)


def check_volume(shape, name: str) -> None:
    """Refuse anything that is not a 3-D volume, with a message that says what to do."""
    if len(shape) != 3:
        hint = (
            " (a 2-D image: DVC needs 3-D volumes)"
            if len(shape) == 2
            else " (for a scan series pick the 4-D mode)"
            if len(shape) == 4
            else ""
        )
        raise ValueError(f"'{name}' has shape {tuple(shape)}, not a 3-D volume (z, y, x){hint}")
    if min(shape) < 5:
        raise ValueError(f"'{name}' is too thin for DVC: shape {tuple(shape)}")


def check_pair(reference_name, reference_shape, deformed_name, deformed_shape) -> None:
    """Check a reference/deformed choice: two different 3-D layers of the same shape."""
    if reference_name is None or deformed_name is None:
        raise ValueError("choose a reference and a deformed Image layer")
    if reference_name == deformed_name:
        raise ValueError(
            f"the reference and deformed volumes are the same layer ('{reference_name}'): "
            "choose two different scans"
        )
    check_volume(reference_shape, reference_name)
    check_volume(deformed_shape, deformed_name)
    if tuple(reference_shape) != tuple(deformed_shape):
        raise ValueError(
            f"'{reference_name}' {tuple(reference_shape)} and '{deformed_name}' "
            f"{tuple(deformed_shape)} differ in shape: DVC needs two scans of the same size"
        )


def check_mask(mask, volume_shape, name: str = "mask") -> np.ndarray:
    """A boolean mask of the volume's shape that selects something."""
    mask = np.asarray(mask)
    if mask.shape != tuple(volume_shape):
        raise ValueError(
            f"the mask '{name}' has shape {mask.shape} but the volumes are {tuple(volume_shape)}"
        )
    mask = mask != 0
    if not mask.any():
        raise ValueError(f"the mask '{name}' is empty: paint the material region first")
    return mask


def mask_from_layer(layer, volume_shape) -> np.ndarray:
    """Boolean mask from a Labels layer (non-zero) or a Shapes layer, extruded through z.

    A shape drawn on one slice (of a 2-D or a 3-D Shapes layer) stands for its outline through
    every slice (:func:`.regions_model.layer_mask`).
    """
    from .regions_model import layer_mask

    return check_mask(layer_mask(layer, volume_shape), volume_shape, layer.name)


def make_params(
    subvolume: int, step: int, order: int, search_radius: int | None
) -> CorrelationParams:
    """:class:`CorrelationParams` from the panel's fields (``search_radius`` 0 or None = auto)."""
    return CorrelationParams(
        subvolume=int(subvolume),
        step=int(step),
        order=int(order),
        search_radius=None if not search_radius else int(search_radius),
    )


# -- preview ----------------------------------------------------------------------------------
def grid_preview(
    volume_shape, params: CorrelationParams, max_points: int = 20000, max_slices: int = 64
):
    """Points of the POI grid and the outline of the central POI's subvolume, in voxels.

    Returns
    -------
    points : ndarray (N, 3)
        POI positions (z, y, x), subsampled along each axis so at most ``max_points`` are shown.
    box : list of ndarray (4, 3)
        Rectangles (corners z, y, x) that outline the central POI's subvolume in every slice it
        crosses, along each of the three axes, so the box shows in any 2-D view and as a cage in
        3-D (at most ``max_slices`` rectangles per axis).
    n_points : int
        Number of POIs of the full grid.
    """
    origin, step, shape = grid_for_volume(volume_shape, params.subvolume, params.step)
    stride = 1
    while int(np.prod([-(-n // stride) for n in shape])) > max_points:
        stride += 1
    axes = [origin[a] + step[a] * np.arange(0, shape[a], stride) for a in range(3)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    centre = np.array([origin[a] + step[a] * (shape[a] // 2) for a in range(3)])
    low, high = centre - params.half, centre + params.half
    box = []
    for axis in range(3):
        u, v = [a for a in range(3) if a != axis]
        n = min(params.subvolume, max_slices)
        for value in np.unique(np.round(np.linspace(low[axis], high[axis], n))):
            corners = np.empty((4, 3))
            corners[:, axis] = value
            corners[:, u] = [low[u], low[u], high[u], high[u]]
            corners[:, v] = [low[v], high[v], high[v], low[v]]
            box.append(corners)
    return grid, box, int(np.prod(shape))


# -- estimates --------------------------------------------------------------------------------
@dataclass(frozen=True)
class RunEstimate:
    """Rough size of a run, shown before it starts."""

    n_points: int
    memory_bytes: int
    seconds: float

    def text(self) -> str:
        return (
            f"{self.n_points:,} POIs · ~{format_bytes(self.memory_bytes)} memory · "
            f"~{format_seconds(self.seconds)}"
        )


def format_seconds(seconds: float) -> str:
    if seconds < 1:
        return "under a second"
    if seconds < 120:
        return f"{seconds:.0f} s"
    if seconds < 7200:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.1f} h"


def estimate_run(
    volume_shape, params: CorrelationParams, n_pairs: int = 1, threads: int | None = None
) -> RunEstimate:
    """Memory and time of correlating ``n_pairs`` pairs of volumes of ``volume_shape``.

    Memory: the two float32 working copies, the B-spline coefficients of the deformed volume and
    the gradient of the reference (3 float32 per voxel), plus the field arrays. Time: POIs ×
    subvolume voxels × :data:`TYPICAL_ITERATIONS` × :data:`SECONDS_PER_VOXEL_ITERATION`, spread over
    the CPU cores, plus a second per 10⁸ voxels for prefiltering and the initial search.
    """
    voxels = float(np.prod(volume_shape))
    _, _, shape = grid_for_volume(volume_shape, params.subvolume, params.step)
    n_points = int(np.prod(shape))
    per_point_bytes = 8 * 3 + 4 + 1 + 4 + 1 + 8 * 9  # u, zncc, status, iterations, prov., gradient
    memory = voxels * 4 * (2 + 1 + 3) + n_points * per_point_bytes * n_pairs
    threads = threads or os.cpu_count() or 1
    work = _work_units(n_points, params) / threads
    seconds = (work * _calibration["seconds_per_voxel_iteration"] + voxels / 1e8) * n_pairs
    return RunEstimate(n_points * n_pairs, int(memory), float(seconds))


def _work_units(n_points: int, params: CorrelationParams) -> float:
    """POIs × subvolume voxels × typical iterations (× 3 for the 30-parameter shape function)."""
    order_factor = 1.0 if params.order == 1 else 3.0
    return float(n_points) * params.subvolume**3 * TYPICAL_ITERATIONS * order_factor


def record_timing(
    seconds: float,
    volume_shape,
    params: CorrelationParams,
    n_pairs: int = 1,
    threads: int | None = None,
) -> None:
    """Update the time estimate from a finished run (a running mean in log space)."""
    _, _, shape = grid_for_volume(volume_shape, params.subvolume, params.step)
    threads = threads or os.cpu_count() or 1
    work = _work_units(int(np.prod(shape)), params) / threads * n_pairs
    measured = (seconds - n_pairs * float(np.prod(volume_shape)) / 1e8) / max(work, 1.0)
    if measured > 0 and np.isfinite(measured):
        old = _calibration["seconds_per_voxel_iteration"]
        _calibration["seconds_per_voxel_iteration"] = float(np.sqrt(old * measured))


# -- POI read-out -----------------------------------------------------------------------------
def nearest_node(field: DisplacementField, position) -> tuple[int, int, int] | None:
    """Grid index of the node nearest to ``position`` (z, y, x voxels), or None if outside.

    A position counts as on the grid when it lies within half a step of a node.
    """
    position = np.asarray(position, dtype=np.float64)[-3:]
    index = np.rint((position - np.asarray(field.origin)) / np.asarray(field.step)).astype(int)
    if np.any(index < 0) or np.any(index >= np.asarray(field.shape)):
        return None
    return tuple(int(i) for i in index)


def describe_poi(field: DisplacementField, index) -> dict:
    """Values at one node, for the dock: position, u, |u|, ZNCC, status, provenance, iterations."""
    i, j, k = index
    u = field.u[i, j, k]
    position = np.asarray(field.origin) + np.asarray(index) * np.asarray(field.step)
    status, provenance = int(field.status[i, j, k]), int(field.provenance[i, j, k])
    status_text = Status(status).label if status in Status._value2member_map_ else str(status)
    if provenance == Provenance.CORRECTED and status not in [int(s) for s in GOOD_STATUSES]:
        # the status is the first match's; the self-correction measured the node since
        status_text = f"{status_text} in the first match, corrected since"
    return {
        "index": (int(i), int(j), int(k)),
        "position": tuple(float(p) for p in position),
        "u": tuple(float(v) for v in u),
        "magnitude": float(np.linalg.norm(u)),
        "zncc": float(field.zncc[i, j, k]),
        "status": status_text,
        "provenance": Provenance(provenance).label
        if provenance in Provenance._value2member_map_
        else str(provenance),
        "iterations": int(field.iterations[i, j, k]),
    }


def poi_text(values: dict, source: str = "") -> str:
    """The read-out of :func:`describe_poi` as a few lines of text."""
    uz, uy, ux = values["u"]
    z, y, x = values["position"]
    head = f"POI {values['index']} at (z, y, x) = ({z:.0f}, {y:.0f}, {x:.0f})"
    if source:
        head += f" — {source}"
    return "\n".join(
        [
            head,
            f"u = ({uz:+.3f}, {uy:+.3f}, {ux:+.3f}) vx, |u| = {values['magnitude']:.3f} vx",
            f"ZNCC {values['zncc']:.4f} · status: {values['status']} · "
            f"provenance: {values['provenance']} · iterations: {values['iterations']}",
        ]
    )
