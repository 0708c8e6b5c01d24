"""Exporting a field, without Qt: the one code path of the Export panel and of the command line's
``export``.

Every export carries the field's provenance (:func:`provenance`: which field, corrected or not,
passes, gray residuals, DVC parameters, voxel size): inside the file for NPZ and HDF5 (the
field's ``metadata["provenance"]``), in a ``STEM_provenance.json`` next to it for the formats
that have no place for it (VTK, TIFF, CSV, the other tools' formats).

A field at points of interest (a :class:`..engine.fields.scattered.ScatteredField`) is written
in the point formats of :data:`..io.export.POINT_FORMATS`, always with the provenance side file;
the formats and extras that need a grid (VTK image data, TIFF stacks, HDF5, the strain TIFF,
residual and report) are refused for it (:func:`check_request`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..engine.fields.field import DisplacementField
from ..engine.fields.scattered import ScatteredField
from ..engine.progress import Progress


@dataclass
class ExportRequest:
    """A checked export: the field, its strain, where to, and the extras.

    Attributes
    ----------
    field : DisplacementField or ScatteredField
        A grid field, or a result at points of interest (positions and displacements
        ``(z, y, x)`` in reference voxels).
    source : str
        The panel's name of the field (recorded in its provenance).
    path : Path
        Target of the field file; the extras are written next to it, named after its stem.
    equivalent_strain : ndarray (nz, ny, nx) or None
        Equivalent strain on the field's grid.
    strain_with_field : bool
        Write the strain into the field file as an extra grid array (all formats but NPZ,
        which holds the field only); for points, an ``equivalent_strain`` column of the CSV
        (each point's strain from its matched gradient, as the View panel shows it).
    strain_tiff : bool
        Also write the strain on the grid as ``STEM_equivalent_strain.tif``.
    residual : ndarray (NZ, NY, NX) or None
        Dense gray residual written as ``STEM_residual.tif``.
    report : dict or None
        Evaluation summary written as ``STEM_report.json``.
    evaluation : Evaluation or None
        The evaluation behind ``report``: its report is written into the folder ``STEM_report/``
        by :func:`..report.write_report`, as ``evaluate --out-dir`` writes it (``report.md`` with
        the plots, the CSV tables; no volumes).
    """

    field: DisplacementField | ScatteredField
    path: Path
    source: str = "field"
    equivalent_strain: np.ndarray | None = None
    strain_with_field: bool = True
    strain_tiff: bool = False
    residual: np.ndarray | None = None
    report: dict | None = None
    evaluation: object | None = None
    voxel_size: tuple = (1.0, 1.0, 1.0)
    offset: tuple = (0.0, 0.0, 0.0)
    written: list = field(default_factory=list)


#: Formats that keep the field's metadata inside the file (the others get a JSON side file).
WITH_METADATA = (".dvcfield", ".npz", ".h5", ".hdf5")


def is_points(field) -> bool:
    """True for a result at points of interest (no grid)."""
    return isinstance(field, ScatteredField)


def check_request(request: ExportRequest) -> None:
    """Refuse what a result at points of interest cannot be written as (ValueError that says
    what to choose instead); grid fields pass."""
    if not is_points(request.field):
        return
    from ..io.export import POINT_FORMATS

    suffix = request.path.suffix.lower()
    if suffix not in POINT_FORMATS:
        raise ValueError(
            f"a result at points of interest has no grid for {suffix or 'this format'}: export "
            f"it as {', '.join(POINT_FORMATS)}"
        )
    if request.strain_tiff or request.equivalent_strain is not None:
        raise ValueError(
            "the equivalent strain as a TIFF stack needs a grid field: a result at points has "
            "its strain per point (the CSV's equivalent_strain column)"
        )
    if request.residual is not None or request.report is not None or request.evaluation is not None:
        raise ValueError(
            "the gray residual and the report come from Evaluate on a grid field, not from a "
            "result at points of interest"
        )


def point_strain(field: ScatteredField) -> np.ndarray | None:
    """Equivalent strain (N,) at each point, from its matched displacement gradient (physical
    axes, as the View panel shows it); None without gradients."""
    from ..quantities import point_quantities

    return point_quantities(field).get("εeq")


def provenance(field: DisplacementField | ScatteredField, source: str) -> dict:
    """Where an exported field comes from, JSON-friendly.

    Keys: ``source`` (the panel's name of the field), ``corrected`` (bool), ``passes_applied``,
    ``mean_gray_residual_before``/``_after`` (gray levels, None when not corrected),
    ``correction`` (the options), ``params`` (DVC parameters), ``voxel_size`` (z, y, x),
    ``unit``, ``reference``/``deformed`` (layer names), ``status_counts``.
    """
    info = field.metadata.get("correction") or {}
    corrected = bool(info) or "correction_passes" in field.metadata
    return {
        "source": source,
        "corrected": corrected,
        "passes_applied": int(info.get("passes_applied", 0)) if corrected else 0,
        "mean_gray_residual_before": info.get("mean_gray_residual_before"),
        "mean_gray_residual_after": info.get("mean_gray_residual_after"),
        "correction": {k: v for k, v in info.items() if k != "seconds"},
        "params": dict(field.params),
        "voxel_size": list(field.metadata.get("voxel_size", (1.0, 1.0, 1.0))),
        "unit": field.metadata.get("unit") or "voxel",
        "reference": field.metadata.get("reference_layer"),
        "deformed": field.metadata.get("deformed_layer"),
        "status_counts": field.status_counts(),
    }


def evaluation_report_files(request: ExportRequest, stem: Path) -> list[Path]:
    """The evaluation report of the command line (``evaluate --out-dir``), written into
    ``STEM_report/``: ``report.md``, its plots and CSV tables (no volumes)."""
    from ..report import write_report

    inputs = {"field": request.source}
    origin = request.field.metadata.get("provenance") or {}
    for key in ("reference", "deformed"):
        name = request.field.metadata.get(key) or origin.get(key)
        if name:
            inputs[key] = name
    files = write_report(
        request.evaluation, stem.parent / f"{stem.name}_report", inputs=inputs, volumes=False
    )
    return [path for paths in files.values() for path in paths]


def side_files_kept(side: Path, report: dict, path: Path) -> list[str]:
    """The files an existing provenance side file ``side`` describes that it goes on describing
    once ``path`` is written with ``report`` (the side file's new content, without ``files``).

    All formats of one stem share ``STEM_provenance.json``; its ``files`` names the files it
    describes. The same field written in another format (the same provenance, metadata
    included) adds its file to the list. Another field may replace the side file only where it
    replaces every file the old one described (the same ``path``, or the same TIFF stacks) or
    those are gone; else the old files would be mis-described, and the export is refused. A
    side file without ``files`` (written before they were listed) is replaced.

    Raises
    ------
    ValueError
        Another field's files of this stem would be left described by this one's provenance.
    """
    import json

    from ..io.report_file import to_json

    try:
        old = json.loads(side.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return []  # none yet, or unreadable: written anew
    if not isinstance(old, dict):
        return []
    named = old.pop("files", None) or []
    present = [n for n in named if isinstance(n, str) and (side.parent / n).is_file()]
    if to_json(old, sort_keys=True) == to_json(json.loads(to_json(report)), sort_keys=True):
        return present  # the same field: one more format of it
    stem = path.with_suffix("").name
    tiff = path.suffix.lower() in (".tif", ".tiff")

    def replaced(name: str) -> bool:
        if name == path.name:
            return True
        return tiff and name.startswith(f"{stem}_") and name.lower().endswith(path.suffix.lower())

    others = [n for n in present if not replaced(n)]
    if others:
        raise ValueError(
            f"{side.name} describes {', '.join(others)}, written from another field "
            f"({old.get('source', 'unknown')}); this export would leave them with the provenance "
            f"of {report.get('source', 'this field')}: write to another name, or remove "
            f"{', '.join(others)} first"
        )
    return []


def write_with_side(write_field, target: Path, side: Path, report: dict) -> list[Path]:
    """Write a field (``write_field(path)`` writes it to ``path``, returns its files) to
    ``target`` and its provenance side file ``side`` (``report`` and the ``files`` it describes,
    :func:`side_files_kept`) as one: under a lock on the folder, so that two exports into it take
    turns between reading the side file and replacing it, and, for a one-file format, both
    renamed into place together (:func:`..io.atomic.atomic_files`: an interrupted or failed
    export leaves the old field with its old provenance). TIFF stacks (several files named after
    the stem) are written first and the side file after them.
    """
    from ..io import report_file
    from ..io.atomic import atomic_files, locked_folder

    with locked_folder(side.parent):
        kept = side_files_kept(side, report, target)
        if target.suffix.lower() in (".tif", ".tiff"):
            files = write_field(target)
            names = sorted({*kept, *(p.name for p in files)})
            report_file.export_report({**report, "files": names}, side)
            return [*files, side]
        names = sorted({*kept, target.name})
        with atomic_files(target, side) as (temp_field, temp_side):
            write_field(temp_field)
            report_file.export_report({**report, "files": names}, temp_side)
        return [target, side]


def run_export(request: ExportRequest):
    """Write everything the request asks for; yields Progress per file, returns the paths."""
    from ..io import export, report_file

    check_request(request)
    points = is_points(request.field)
    origin = provenance(request.field, request.source)
    field = request.field.copy()
    field.metadata["provenance"] = origin
    extra = None
    suffix = request.path.suffix.lower()
    if request.strain_with_field and points and suffix == ".csv":
        strain = point_strain(field)
        extra = None if strain is None else {"equivalent_strain": strain}
    elif request.strain_with_field and request.equivalent_strain is not None:
        if suffix not in (".dvcfield", ".npz"):  # (the native file holds the field only)
            extra = {"equivalent_strain": request.equivalent_strain}
    stem = request.path.with_suffix("")

    def write_field(path=request.path):
        return [Path(p) for p in export.export_field(
            field, path, extra=extra, voxel_size=request.voxel_size
        )]  # fmt: skip

    jobs = [("field", write_field)]
    if points or suffix not in WITH_METADATA:  # (the points' .npz has no room for it either)
        side = stem.parent / f"{stem.name}_provenance.json"
        report = {"title": "DVC field provenance", **origin, "metadata": field.metadata}
        side_files_kept(side, report, request.path)  # refused before anything is written
        jobs = [
            (
                "field and its provenance",
                lambda: write_with_side(write_field, request.path, side, report),
            )
        ]
    if request.strain_tiff and request.equivalent_strain is not None:
        placement = {
            "scale": np.asarray(request.field.step) * np.asarray(request.voxel_size),
            "translate": np.asarray(request.offset)
            + np.asarray(request.field.origin) * np.asarray(request.voxel_size),
        }
        jobs.append(
            (
                "equivalent strain",
                lambda: [
                    export.export_volume_tiff(
                        request.equivalent_strain,
                        stem.parent / f"{stem.name}_equivalent_strain.tif",
                        description={"quantity": "equivalent strain"},
                        **placement,
                    )
                ],
            )
        )
    if request.residual is not None:
        jobs.append(
            (
                "residual",
                lambda: [
                    export.export_volume_tiff(
                        request.residual,
                        stem.parent / f"{stem.name}_residual.tif",
                        scale=request.voxel_size,
                        translate=request.offset,
                        description={"quantity": "gray residual"},
                    )
                ],
            )
        )
    if request.report is not None:
        jobs.append(
            (
                "report",
                lambda: [
                    report_file.export_report(
                        request.report, stem.parent / f"{stem.name}_report.json"
                    )
                ],
            )
        )
    if request.evaluation is not None:
        jobs.append(("report", lambda: evaluation_report_files(request, stem)))
    written = []
    for index, (name, job) in enumerate(jobs):
        yield Progress("export", index, len(jobs), f"writing the {name}")
        written += [Path(p) for p in job()]
    yield Progress("export", len(jobs), len(jobs), f"{len(written)} files written")
    return written
