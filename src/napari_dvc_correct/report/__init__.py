"""Reports of an accuracy evaluation: CSV tables, PNG plots, TIFF volumes and a Markdown page.

:func:`write_report` writes everything into one folder; each file is written atomically, so an
interrupted run never leaves a half-written table or image behind.
"""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from ..engine.evaluation.results import Evaluation

__all__ = ["file_stem", "render_markdown", "unique_names", "write_report", "write_volumes"]


def __getattr__(name: str):
    # the Markdown, table and plot modules (and the evaluation's results they read) load when a
    # report is written: `correct` and `correlate --self-correct` print the pass table through
    # `report.passes` alone and need none of them (docs/performance.md: start-up)
    if name == "render_markdown":
        from .markdown import render_markdown

        return render_markdown
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def file_stem(name: str) -> str:
    """A file-name-safe version of a field name (``"field 1"`` -> ``"field_1"``)."""
    stem = re.sub(r"[^A-Za-z0-9_.-]+", "_", name.strip()).strip("._")
    return stem or "field"


def unique_names(names, template: str = "{name}_{k}") -> list[str]:
    """``names`` with repeats made unique by ``template`` (``k`` = 2, 3, ...), order kept."""
    result, seen = [], set()
    for base in names:
        name, k = base, 2
        while name in seen:
            name, k = template.format(name=base, k=k), k + 1
        seen.add(name)
        result.append(name)
    return result


def _stems(evaluation: Evaluation) -> list[str]:
    return unique_names([file_stem(item.name) for item in evaluation.fields])


def _written_at(volume, target: Path) -> bool:
    """True for a lazy volume that is the file ``target`` already (tiled evaluation wrote it)."""
    path = getattr(volume, "path", None)
    if isinstance(volume, np.ndarray) or path is None or not target.exists():
        return False
    return os.path.samefile(path, target)


def write_volumes(evaluation: Evaluation, out_dir: str | os.PathLike) -> list[Path]:
    """Write the residual, label and strain volumes of an evaluation as TIFF stacks.

    Files: ``labels_reference.tif``, ``labels_deformed.tif`` (uint8 phases),
    ``residual_<field>.tif`` (float32 voxels, NaN where undefined), ``labels_mapped_<field>.tif``
    (phases of the other state brought over by the field, 255 where undefined) and
    ``equivalent_strain_<field>.tif``, ``error_estimate_<field>.tif`` and
    ``error_resolution_<field>.tif`` (voxels; float32 on the POI grid, with ``scale = step`` and
    ``translate = origin`` in its description so it overlays the volume).
    """
    from ..io.export import export_volume_tiff

    out_dir = Path(out_dir)
    written = []
    for state, labels in (
        ("reference", evaluation.labels_reference),
        ("deformed", evaluation.labels_deformed),
    ):
        if labels is not None:
            target = out_dir / f"labels_{state}.tif"
            if not _written_at(labels, target):
                export_volume_tiff(labels, target, description={"quantity": f"phases, {state}"})
            written.append(target)
    for stem, item in zip(_stems(evaluation), evaluation.fields):
        for prefix, volume, quantity in (
            ("residual", item.residual, "gray residual"),
            ("labels_mapped", item.labels_mapped, "phases mapped by the field"),
        ):
            if volume is not None:
                target = out_dir / f"{prefix}_{stem}.tif"
                if not _written_at(volume, target):
                    export_volume_tiff(
                        volume, target, description={"quantity": quantity, "field": item.name}
                    )
                written.append(target)
        grids = [("equivalent_strain", item.equivalent_strain, "equivalent strain (grid)")]
        if item.error_estimate is not None:
            grids.append(("error_estimate", item.error_estimate, "error estimate (voxels, grid)"))
        if item.error_resolution is not None:
            grids.append(
                (
                    "error_resolution",
                    item.error_resolution,
                    "the error estimate's resolution (voxels, grid): a bound below it",
                )
            )
        for prefix, values, quantity in grids:
            target = out_dir / f"{prefix}_{stem}.tif"
            export_volume_tiff(
                values.astype(np.float32),
                target,
                scale=item.field.step,
                translate=item.field.origin,
                description={"quantity": quantity, "field": item.name},
            )
            written.append(target)
    return written


def write_report(
    evaluation: Evaluation,
    out_dir: str | os.PathLike,
    *,
    inputs: dict | None = None,
    volumes: bool = True,
    title: str = "DVC accuracy evaluation",
) -> dict[str, list[Path]]:
    """Write tables (CSV), plots (PNG), volumes (TIFF) and ``report.md`` into ``out_dir``.

    Parameters
    ----------
    evaluation : Evaluation
        From :func:`napari_dvc_correct.engine.evaluation.accuracy.evaluate_fields`.
    out_dir : path
        Existing or new folder (created if missing; its parent must exist).
    inputs : dict, optional
        What was evaluated, listed at the top of the report.
    volumes : bool
        Also write the TIFF volumes (:func:`write_volumes`).

    Returns
    -------
    dict of str -> list of Path
        Files written, by kind: ``"tables"``, ``"plots"``, ``"volumes"``, ``"report"``.
    """
    from .markdown import render_markdown, write_markdown
    from .plots import (
        plot_accuracy_vs_strain,
        plot_residual_histogram,
        plot_residual_slices,
        plot_residual_vs_strain,
    )
    from .tables import background_rows, bin_rows, phase_rows, summary_rows, write_csv

    out_dir = Path(out_dir)
    if not out_dir.parent.exists():
        raise FileNotFoundError(f"the folder that should hold {out_dir} does not exist")
    out_dir.mkdir(exist_ok=True)
    files: dict[str, list[Path]] = {"tables": [], "plots": [], "volumes": [], "report": []}
    for name, rows in (
        ("summary.csv", summary_rows(evaluation)),
        ("phases.csv", phase_rows(evaluation)),
        ("strain_bins.csv", bin_rows(evaluation)),
        ("background.csv", background_rows(evaluation)),
    ):
        files["tables"].append(write_csv(rows, out_dir / name))
    for name, plot in (
        ("residual_vs_strain.png", plot_residual_vs_strain),
        ("accuracy_vs_strain.png", plot_accuracy_vs_strain),
        ("residual_slices.png", plot_residual_slices),
        ("residual_histogram.png", plot_residual_histogram),
    ):
        path = plot(evaluation, out_dir / name)
        if path is not None:
            files["plots"].append(path)
    if volumes:
        files["volumes"] = write_volumes(evaluation, out_dir)
    text = render_markdown(evaluation, files, inputs=inputs, title=title)
    files["report"].append(write_markdown(text, out_dir / "report.md"))
    return files
