"""The Export panel without Qt: what to write for a field, as a generator for the worker."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..engine.field import DisplacementField
from ..engine.progress import Progress

#: Formats offered in the panel: label -> file suffix.
FORMATS = {
    "NPZ (napari-dvc-correct field)": ".npz",
    "HDF5": ".h5",
    "VTK image data, XML (.vti, ParaView)": ".vti",
    "VTK legacy structured points (.vtk)": ".vtk",
    "TIFF stacks (one per component)": ".tif",
    "CSV (one row per POI)": ".csv",
}


@dataclass
class ExportRequest:
    """A checked export: the field, its strain, where to, and the extras.

    Attributes
    ----------
    field : DisplacementField
    path : Path
        Target of the field file; the extras are written next to it, named after its stem.
    equivalent_strain : ndarray (nz, ny, nx) or None
        Equivalent strain on the field's grid.
    strain_with_field : bool
        Write the strain into the field file as an extra grid array (all formats but NPZ,
        which holds the field only).
    strain_tiff : bool
        Also write the strain on the grid as ``STEM_equivalent_strain.tif``.
    residual : ndarray (NZ, NY, NX) or None
        Dense gray residual written as ``STEM_residual.tif``.
    report : dict or None
        Evaluation report written as ``STEM_report.md`` and ``STEM_report.json``.
    """

    field: DisplacementField
    path: Path
    equivalent_strain: np.ndarray | None = None
    strain_with_field: bool = True
    strain_tiff: bool = False
    residual: np.ndarray | None = None
    report: dict | None = None
    voxel_size: tuple = (1.0, 1.0, 1.0)
    offset: tuple = (0.0, 0.0, 0.0)
    written: list = field(default_factory=list)


def check_path(path: str, suffix: str) -> Path:
    """The target path with the format's suffix; its folder must exist."""
    if not path or not str(path).strip():
        raise ValueError("choose a file to export to")
    target = Path(str(path).strip()).expanduser()
    if target.suffix.lower() != suffix and not (
        suffix == ".tif" and target.suffix.lower() == ".tiff"
    ):
        target = target.with_name(target.name + suffix)
    if not target.parent.exists():
        raise ValueError(f"the folder {target.parent} does not exist")
    return target


def run_export(request: ExportRequest):
    """Write everything the request asks for; yields Progress per file, returns the paths."""
    from ..io import export

    extra = None
    if request.strain_with_field and request.equivalent_strain is not None:
        if request.path.suffix.lower() != ".npz":
            extra = {"equivalent_strain": request.equivalent_strain}
    stem = request.path.with_suffix("")

    def write_field():
        return export.export_field(
            request.field, request.path, extra=extra, voxel_size=request.voxel_size
        )

    jobs = [("field", write_field)]
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
                    export.export_report(request.report, stem.parent / f"{stem.name}_report.md"),
                    export.export_report(request.report, stem.parent / f"{stem.name}_report.json"),
                ],
            )
        )
    written = []
    for index, (name, job) in enumerate(jobs):
        yield Progress("export", index, len(jobs), f"writing the {name}")
        written += [Path(p) for p in job()]
    yield Progress("export", len(jobs), len(jobs), f"{len(written)} files written")
    return written
