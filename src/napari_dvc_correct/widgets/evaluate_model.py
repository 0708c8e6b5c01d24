"""The Evaluate panel without Qt: histogram, live phases, the evaluation run and its report."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..engine.evaluation.options import EvaluationOptions
from ..engine.fields.field import DisplacementField
from ..engine.run_options import RunOptions

#: Voxels sampled for the histogram and the automatic thresholds of a large volume.
HISTOGRAM_SAMPLES = 1 << 21


def sample_voxels(volume: np.ndarray, max_samples: int = HISTOGRAM_SAMPLES) -> np.ndarray:
    """A regular subsample of ``volume`` (every k-th voxel along each axis), flattened, float64."""
    volume = np.asanyarray(volume)
    stride = 1
    while np.prod([-(-n // stride) for n in volume.shape]) > max_samples:
        stride += 1
    sample = np.asarray(volume[tuple(slice(None, None, stride) for _ in volume.shape)])
    sample = sample.astype(np.float64).ravel()
    return sample[np.isfinite(sample)]


def gray_histogram(volume: np.ndarray, bins: int = 128) -> tuple[np.ndarray, np.ndarray]:
    """Histogram of the gray values (subsampled for large volumes): ``(counts, edges)``."""
    sample = sample_voxels(volume)
    if sample.size == 0:
        raise ValueError("the volume has no finite gray value")
    low, high = float(sample.min()), float(sample.max())
    if high <= low:
        high = low + 1.0
    return np.histogram(sample, bins=bins, range=(low, high))


def automatic_thresholds(volume: np.ndarray, n_phases: int) -> np.ndarray:
    """Multi-Otsu thresholds for ``n_phases`` phases (engine's :func:`auto_thresholds`).

    A lazy volume (Dask, Zarr) is read only on the engine's sampling lattice, never whole; the
    thresholds are the same.
    """
    from ..engine.evaluation.phases import auto_thresholds, otsu_stride

    if not isinstance(volume, np.ndarray):  # a lazy scan: read only the lattice Otsu samples
        stride = otsu_stride(volume.shape)
        volume = np.asarray(volume[::stride, ::stride, ::stride])
    return np.asarray(auto_thresholds(volume, int(n_phases)), dtype=np.float64)


@dataclass
class PhasePreview:
    """Live phase split of one volume: display labels and per-phase mean gray."""

    labels: np.ndarray  # uint8, 0 = unassigned (NaN), 1..N = phases dark to bright
    mean_gray: list  # per phase, gray levels (NaN for an empty phase)
    fractions: list  # per phase, share of the voxels

    def text(self) -> str:
        return " · ".join(
            f"phase {k + 1}: mean gray {g:.1f} ({100 * f:.0f} %)"
            for k, (g, f) in enumerate(zip(self.mean_gray, self.fractions))
        )


def check_thresholds(thresholds) -> np.ndarray:
    """The gray thresholds as float64, refused unless one or more and strictly increasing."""
    values = np.asarray(thresholds, dtype=np.float64)
    if values.ndim != 1 or values.size < 1 or np.any(np.diff(values) <= 0):
        raise ValueError(f"thresholds must be strictly increasing, got {list(values)}")
    return values


def phase_preview(volume: np.ndarray, thresholds) -> PhasePreview:
    """Split ``volume`` by increasing ``thresholds``; labels shifted by one for a Labels layer."""
    from ..engine.evaluation.phases import NO_PHASE, label_phases, phase_table

    values = check_thresholds(thresholds)
    labels = label_phases(volume, values)
    # unassigned (NaN) voxels go to label N, which phase_table leaves out of phases 0..N-1
    table = phase_table(volume, np.where(labels == NO_PHASE, values.size + 1, labels), values)
    display = np.where(labels == NO_PHASE, 0, labels + 1).astype(np.uint8)
    return PhasePreview(
        labels=display,
        mean_gray=[s.mean_gray for s in table],
        fractions=[s.fraction for s in table],
    )


def ready_for_evaluation(field: DisplacementField) -> DisplacementField:
    """The field as the evaluation needs it: every node finite, failed matches refilled.

    A freshly correlated field can hold failed or out-of-bounds nodes; they are replaced by
    :func:`~napari_dvc_correct.engine.correction.cleaning.clean` (paper step b) so the field can be
    densified. A field that is already usable everywhere is returned as is.
    """
    if field.valid.all():
        return field
    from ..engine.correction.cleaning import clean

    return clean(field, fill_masked=True)


def tiled_outputs(names, folder=None) -> dict:
    """Where an out-of-core evaluation writes each field's residual volume (Zarr), by name.

    In a new temporary folder (``dvc-evaluate-*``) unless ``folder`` is given; the residual
    layers read these files lazily, so they stay until the folder is removed.
    """
    import tempfile
    from pathlib import Path

    folder = Path(folder) if folder is not None else Path(tempfile.mkdtemp(prefix="dvc-evaluate-"))
    return {name: folder / f"residual_{k}.zarr" for k, name in enumerate(names)}


class TemporaryFolders:
    """The folders out-of-core evaluations write their residual volumes to (``dvc-evaluate-*``).

    The residual layers read those Zarr files lazily, so a folder must stay while a layer reads
    it and should go once none does: :meth:`new` makes one for a run (:func:`tiled_outputs`),
    :meth:`release` removes every folder that none of the given paths in use lies in (a replaced
    or removed layer, a failed or cancelled run), :meth:`remove_all` the rest (at exit).
    """

    def __init__(self) -> None:
        self.folders: list = []

    def new(self, names) -> dict:
        outputs = tiled_outputs(names)
        folder = next(iter(outputs.values())).parent if outputs else None
        if folder is not None:
            self.folders.append(folder)
        return outputs

    def release(self, in_use) -> None:
        from pathlib import Path

        used = {Path(p).resolve() for p in in_use if p}
        for folder in list(self.folders):
            if folder.resolve() not in used:
                self._remove(folder)

    def remove_all(self) -> None:
        for folder in list(self.folders):
            self._remove(folder)

    def _remove(self, folder) -> None:
        import shutil

        shutil.rmtree(folder, ignore_errors=True)
        if not folder.exists():
            self.folders.remove(folder)


def open_residual(path):
    """A residual volume an out-of-core evaluation wrote, as a lazy Zarr array (read only)."""
    import zarr

    return zarr.open_array(str(path), mode="r")


def run_evaluation(
    reference,
    deformed,
    fields: dict,
    thresholds,
    mode: str = EvaluationOptions.mode,
    outputs: dict | None = None,
    max_memory: str | None = None,
    tiled: bool | None = None,
    background_fields: dict | None = None,
    region=None,
):
    """Generator for the panel's worker: cleans the fields if needed, then evaluates them all.

    Parameters
    ----------
    reference, deformed : ndarray, shape (nz, ny, nx)
    fields : dict of name -> DisplacementField
        E.g. ``{"uncorrected": d, "corrected": d2}``, compared on the same bins.
    thresholds : sequence of float
        The ``N - 1`` gray thresholds (used for both states).
    mode : {"reference", "loaded"}
    outputs : dict of name -> path, optional
        Out of core (:func:`..tiled.evaluation.evaluate_tiled_iter`): the volumes read block
        by block and each field's residual written to its Zarr path (:func:`tiled_outputs`)
        instead of kept in memory; ``max_memory`` (``"4GB"``...) bounds the run.
    tiled : bool, optional
        Out of core even without ``outputs`` (then no residual volume is kept: the numbers
        only, as a series needs). Default: out of core when ``outputs`` are given.
    background_fields : dict of name -> DisplacementField, optional
        Every field known on this pair, ticked or not: the pair's gray-level map and ``r0``
        are measured with the best of them, so a field's p does not depend on which others are
        ticked (default: ``fields``).
    region : ndarray of bool or lazy region, optional
        The specimen (the Correlate panel's regions, reference space): phases, r0 and every
        residual statistic use only its voxels (out of core: read block by block).

    Returns
    -------
    Evaluation
    """
    if not fields:
        raise ValueError("no displacement field to evaluate: run Correlate first")
    ready = {name: ready_for_evaluation(field) for name, field in fields.items()}
    candidates = {
        name: ready[name] if name in ready else ready_for_evaluation(field)
        for name, field in (background_fields or fields).items()
    }
    from ..jobs.evaluate import evaluate_job
    from ..tiled.memory import parse_memory

    limit = parse_memory(max_memory) if max_memory else None
    run = RunOptions(tiled=outputs is not None or bool(tiled), max_memory=limit)
    if region is not None and not run.out_of_core:
        region = np.asarray(region) != 0  # read here, in the worker (out of core: by blocks)
    options = EvaluationOptions(phases=[float(t) for t in thresholds], mode=mode)
    outputs = {("residual", name): str(path) for name, path in (outputs or {}).items()}
    return (
        yield from evaluate_job(
            reference,
            deformed,
            ready,
            options,
            background_fields=candidates,
            region=region,
            outputs=outputs,
            run=run,
        )
    )


@dataclass
class ShownEvaluation:
    """An evaluation and its residual layers (layer data tuples), made in the worker so the
    panel's result slot only adds them (the residual's contrast range is a percentile of the
    whole volume: seconds on the main thread for a large scan)."""

    evaluation: object
    layers: list


def residual_layers(evaluation, placement, outputs=None, temporary_key=None) -> list:
    """The hidden residual layer of every evaluated field, carrying the evaluation's report.

    ``placement`` is ``(voxel_size, offset)``; ``outputs`` (name -> Zarr path) the residuals of
    an out-of-core run, read lazily; their folder is recorded under ``temporary_key``.
    """
    from ..layers import MARKER, residual_layer

    report = evaluation_report(evaluation)
    voxel_size, offset = placement if placement is not None else (None, None)
    tuples = []
    for item in evaluation.fields:
        residual = open_residual(outputs[item.name]) if outputs else item.residual
        data, kwargs, kind = residual_layer(
            residual, item.name, voxel_size=voxel_size, offset=offset
        )
        kwargs["metadata"][MARKER]["report"] = report
        kwargs["metadata"][MARKER]["evaluation"] = evaluation  # the report Export writes
        if outputs and temporary_key:  # the folder this layer reads lazily
            kwargs["metadata"][MARKER][temporary_key] = str(outputs[item.name].parent)
        tuples.append((data, kwargs, kind))
    return tuples


def with_residual_layers(generator, placement, outputs=None, temporary_key=None):
    """Run an evaluation ``generator``; then, still in the worker, make its residual layers
    (:func:`residual_layers`). Returns a :class:`ShownEvaluation` (a series' list as it is)."""
    evaluation = yield from generator
    if isinstance(evaluation, list):
        return evaluation
    return ShownEvaluation(
        evaluation, residual_layers(evaluation, placement, outputs, temporary_key)
    )


def evaluation_report(evaluation) -> dict:
    """A JSON-friendly summary of an :class:`~napari_dvc_correct.engine.evaluation.results.Evaluation`."""
    report = {
        "title": "DVC accuracy evaluation",
        "residual": evaluation.residual_text,
        "gray levels": evaluation.gray_levels.describe(),
        "background residual r0 (pair)": float(evaluation.pair.background.mean),
        "r0 measured with": evaluation.pair.measured_with,
        "scan noise": evaluation.pair.noise_text(),
        "thresholds (reference)": [float(t) for t in evaluation.thresholds_reference],
        "thresholds (deformed)": [float(t) for t in evaluation.thresholds_deformed],
        "phase pair": [int(p) for p in evaluation.phase_pair],
        "phase contrast |g1 - g2|": float(evaluation.contrast),
        "strain bin edges": [float(e) for e in evaluation.edges],
    }
    for label, table in (
        ("phases (reference)", evaluation.phases_reference),
        ("phases (deformed)", evaluation.phases_deformed),
    ):
        report[label] = {
            f"phase {s.phase}": {
                "gray range": [float(s.lower), float(s.upper)],
                "mean gray": float(s.mean_gray),
                "fraction": float(s.fraction),
            }
            for s in table
        }
    for item in evaluation.fields:
        error = item.error
        report[f"field: {item.name}"] = {
            "mean gray residual": float(item.mean_residual),
            "background residual r0": float(item.background_used),
            "own background residual": float(item.background.mean),
            "accuracy index p": float(item.accuracy),
            "p meaningful": bool(item.meaningful),
            "measured nodes": int(item.measured_nodes),
            "nodes": int(item.field.n_points),
            "error estimate median (voxels)": error["median"],
            "error estimate 95th percentile (voxels)": error["p95"],
            "share of nodes likely > 0.5 voxel (P >= 1/2)": error["likely_bad"],
            "share of nodes possibly > 0.5 voxel (P >= 16 %)": error["possibly_bad"],
            "residual's resolution, median (voxels)": error["resolution"],
            "share of nodes below the residual's resolution": error["below_resolution"],
            "voxels": int(item.voxels),
            "mean residual per strain bin": [float(v) for v in item.bins.mean_residual],
            "accuracy per strain bin": [float(v) for v in np.asarray(item.bin_accuracy)],
            "voxels per strain bin": [int(v) for v in item.bins.voxels],
        }
    return report


def attach_estimate(field, item, evaluation) -> None:
    """Leave ``item``'s error estimate on ``field`` (the layer's), with what it was measured
    against (:func:`..engine.evaluation.error_estimate.attach_estimate`)."""
    from ..engine.evaluation.error_estimate import attach_estimate as attach

    attach(
        field,
        item.error_estimate,
        item.error_resolution,
        background_residual=float(evaluation.pair.background.mean),
        residual=evaluation.residual_text,
        gray_levels=evaluation.gray_levels.describe(),
    )


def field_lines(item) -> list[str]:
    """The dock's lines for one field: a warning first when most nodes were not measured, then
    the mean residual, p and the error estimate."""
    from ..engine.evaluation.error_estimate import bounded_text, likely_text

    lines = []
    nodes = int(item.field.n_points)
    if not item.meaningful:
        lines.append(
            f"⚠ {item.name}: only {item.measured_nodes} of {nodes} nodes were measured (the rest "
            "inpainted): p is not meaningful"
        )
    error = item.error
    p = f"{item.accuracy:.4f}" if item.meaningful else f"({item.accuracy:.4f}, not meaningful)"
    lines.append(
        f"{item.name}: mean residual {item.mean_residual:.2f}, accuracy index p = {p}; error "
        f"estimate median {bounded_text(error, 'median')} voxel, 95 % "
        f"{bounded_text(error, 'p95')}, {likely_text(error)}"
        + (
            f"; resolution {error['resolution']:.3f} voxel (median), "
            f"{100 * error['below_resolution']:.0f} % of nodes below it (a bound there: '<')"
            if np.isfinite(error["below_resolution"])
            else ""
        )
        + f"; measured nodes {item.measured_nodes} / {nodes}"
    )
    return lines


def summary_text(evaluation) -> str:
    """Few lines for the dock: what the residual is (frame, gray levels), the pair's r0 and
    phases, then each field's residual, p and error estimate."""
    gray = ", ".join(f"{s.mean_gray:.1f}" for s in evaluation.phases_reference)
    pair = evaluation.pair
    lines = [
        f"Mean gray residual = mean of {evaluation.residual_text}; gray levels "
        f"{evaluation.gray_levels.describe()}",
        f"Background r0 = {pair.background.mean:.2f} (the pair's, measured with "
        f"'{pair.measured_with}'); mean gray per phase (reference): {gray}; contrast "
        f"{evaluation.contrast:.1f}",
    ]
    if pair.noise_text():
        lines.append(pair.noise_text()[0].upper() + pair.noise_text()[1:])
    for item in evaluation.fields:
        lines.extend(field_lines(item))
    return "\n".join(lines)


def run_groups(
    groups, thresholds, mode: str = "reference", max_memory=None, tiled=False, region=None
):
    """Evaluate fields measured on different pairs (the states of a series), pair by pair.

    Parameters
    ----------
    groups : list of (label, reference, deformed, fields[, background_fields])
        One entry per pair of volumes, e.g. ``("state 2", G0, F2, {"state 2 (total)": d})``;
        ``background_fields``: every field known on that pair (see :func:`run_evaluation`).
    max_memory, tiled
        Out of core (``tiled``): each pair read block by block within ``max_memory``; only the
        numbers are kept (the panel shows no residual layer for a series).

    Returns
    -------
    list of (label, Evaluation)
    """
    from ..engine.progress import Progress, forward_progress

    results = []
    for index, (label, reference, deformed, fields, *known) in enumerate(groups):
        stage = f"{label} ({index + 1} of {len(groups)})"  # on every stage line of the pair
        yield Progress(stage, 0, 1, "evaluating")
        evaluation = yield from forward_progress(run_evaluation(
            reference, deformed, fields, thresholds, mode, max_memory=max_memory, tiled=tiled,
            background_fields=known[0] if known else None, region=region,
        ), stage)  # fmt: skip
        results.append((label, evaluation))
    return results


def groups_text(results) -> str:
    """The per-pair summary: one block of :func:`summary_text` per state."""
    return "\n".join(f"— {label} —\n{summary_text(evaluation)}" for label, evaluation in results)


def series_rows(results, loads_text: str = "", deformed: str | None = None) -> list[dict]:
    """The rows of the series plot (:func:`..report.series.series_rows`) of a series'
    evaluations, with the load values typed in the panel (empty: the state index); ``deformed``
    names the state evaluated on the panel's own pair. Raises ValueError for a bad load list."""
    from ..report.series import parse_loads
    from ..report.series import series_rows as rows_of

    return rows_of(results, parse_loads(loads_text, len(results)), deformed)
