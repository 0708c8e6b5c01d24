"""The Export panel without Qt: the formats it offers, its checks and texts.

What an export writes (the field, its provenance, the extras) is :mod:`..jobs.export`, the code
path the command line's ``export`` uses too; its names are re-exported here for the panel.
"""

from __future__ import annotations

from pathlib import Path

from ..engine.fields.field import DisplacementField
from ..engine.fields.scattered import ScatteredField
from ..jobs.export import (  # noqa: F401  (the panel's worker runs these)
    WITH_METADATA,
    ExportRequest,
    check_request,
    evaluation_report_files,
    is_points,
    point_strain,
    provenance,
    run_export,
)

#: Formats offered in the panel: label -> file suffix.
FORMATS = {
    "DVC field (.dvcfield: opens in napari with this plugin)": ".dvcfield",
    "NPZ (napari-dvc-correct field, the same contents)": ".npz",
    "HDF5": ".h5",
    "VTK image data, XML (.vti, ParaView)": ".vti",
    "VTK legacy structured points (.vtk)": ".vtk",
    "TIFF stacks (one per component)": ".tif",
    "CSV (one row per POI)": ".csv",
    # the other tools' formats, one row per node (a field opened from them goes back there)
    "spam TSV (.tsv, spam-ldic's columns)": ".tsv",
    "iDVC (.disp)": ".disp",
    "ALDVC MATLAB (.mat)": ".mat",
}

#: Formats offered for a result at points of interest: label -> file suffix (the files of
#: :func:`..io.export.export_points`, as the command line's ``correlate --points`` writes them).
POINT_FORMATS = {
    "CSV (one row per point)": ".csv",
    "NPZ at the points (pyALDVC layout, as correlate --points --out-format aldvc)": ".npz",
    "VTK points (.vtu, ParaView)": ".vtu",
    "spam TSV (.tsv)": ".tsv",
    "iDVC (.disp)": ".disp",
    "ALDVC MATLAB (.mat)": ".mat",
}


def formats_for(field) -> dict:
    """The formats the panel offers for ``field``: label -> suffix."""
    return POINT_FORMATS if is_points(field) else FORMATS


def check_format(field, suffix: str) -> None:
    """Refuse a format ``suffix`` not offered for ``field`` (ValueError that says which are)."""
    formats = formats_for(field)
    if suffix in formats.values():
        return
    if is_points(field):
        raise ValueError(
            f"a result at points of interest has no grid for {suffix or 'this format'}: export "
            f"it as {', '.join(POINT_FORMATS.values())}"
        )
    raise ValueError(f"unknown export format {suffix!r}; use one of {', '.join(formats.values())}")


def describe(field: DisplacementField | ScatteredField, source: str) -> str:
    """One line for the panel: which field the export writes."""
    info = provenance(field, source)
    if is_points(field):
        layer = field.metadata.get("points_layer")
        text = f"the '{source}' result at {field.n_points:,} points of interest"
        text += f" of '{layer}'" if layer else ""
        return text + " (no grid: no VTK image, TIFF, HDF5, residual or report)"
    text = f"the '{source}' field, {field.n_points:,} POIs, "
    if not info["corrected"]:
        return text + "not self-corrected"
    before, after = info["mean_gray_residual_before"], info["mean_gray_residual_after"]
    text += f"self-corrected ({info['passes_applied']} pass(es)"
    if before is not None and after is not None:
        text += f", mean gray residual {before:.3g} → {after:.3g}"
    return text + ")"


def default_name(source: str, suffix: str = ".dvcfield") -> str:
    """File name the panel proposes for the field ``source``, e.g. ``dvc_corrected.dvcfield``."""
    slug = "".join(c if c.isalnum() else "_" for c in source).strip("_")
    while "__" in slug:
        slug = slug.replace("__", "_")
    return f"dvc_{slug or 'field'}{suffix}"


def check_path(path: str, suffix: str) -> Path:
    """The target path with the format's suffix; its folder must exist and take files."""
    if not path or not str(path).strip():
        raise ValueError("choose a file to export to")
    target = Path(str(path).strip()).expanduser()
    if target.suffix.lower() != suffix and not (
        suffix == ".tif" and target.suffix.lower() == ".tiff"
    ):
        target = target.with_name(target.name + suffix)
    if not target.parent.exists():
        raise ValueError(f"the folder {target.parent} does not exist")
    from ..io.atomic import check_writable

    try:  # (read-only, /proc...: the write would fail on its temporary file's name)
        check_writable(target.parent)
    except PermissionError as error:
        raise ValueError(f"{error}: choose another folder") from None
    return target


def check_not_open(target: Path, open_files) -> None:
    """Refuse an export that would write over a file a layer was opened from: ``target`` itself
    (the scans' ``.npz`` chosen as an NPZ export) or a file written next to it, named
    ``STEM_...`` (TIFF stacks, provenance, strain, residual, report). ``open_files``: the
    layers' source paths (None for layers not opened from a file)."""
    import os

    stem = target.with_suffix("")
    for item in open_files:
        if not item:
            continue
        path = Path(item)
        try:
            same = path.exists() and target.exists() and os.path.samefile(path, target)
            beside = path.exists() and path.parent.resolve() == stem.parent.resolve()
        except OSError:
            continue
        if same or (beside and path.name.startswith(f"{stem.name}_")):
            raise ValueError(
                f"the export would write over {path.name}, the file of an open layer: choose "
                "another file name"
            )
