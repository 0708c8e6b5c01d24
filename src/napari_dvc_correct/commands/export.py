"""``napari-dvc-correct export FIELD OUT [--format NAME]``: convert a field file.

Reads ``FIELD`` in any format of :mod:`..io.formats` (ours, ``.dvcfield`` or ``.npz``; spam TSV;
pyALDVC/ALDVC; iDVC; plain tables) and writes it with the writers of the Export panel
(:func:`..jobs.export.run_export`, one code path): our field file, HDF5, VTK (``.vti``, ``.vtk``,
``.vtu``), CSV, TIFF stacks, spam, iDVC, ALDVC (:data:`..io.export.EXPORT_FORMATS`). The format
comes from ``OUT``'s suffix or ``--format``. A format without room for metadata gets
``STEM_provenance.json`` next to it, as from the panel. Every file is written atomically; an
output that is the input is refused before any work.

A field on scattered points (a tool's irregular points) is written at its points in the point
formats (``.csv``, ``.vtu``, ``.tsv``, ``.disp``, ``.mat``); the grid formats get it put on a
grid (interpolated, with provenance ``INTERPOLATED``), which the command says.
"""

from __future__ import annotations

import argparse
from pathlib import Path

#: Suffixes accepted for a format besides its own (``--format tiff`` with ``OUT.tiff``).
_ALSO = {".tiff": ".tif", ".hdf5": ".h5"}


def add_parser(subparsers) -> argparse.ArgumentParser:
    from ..io.export import EXPORT_FORMATS, FIELD_FORMATS
    from ._field_formats import _add_input_arguments

    formats = ", ".join(f"{name} ({suffix})" for name, suffix in EXPORT_FORMATS.items())
    parser = subparsers.add_parser(
        "export",
        help="convert a field file to VTK, HDF5, CSV, TIFF, spam, iDVC, ALDVC or ours",
        description="Convert a displacement field file (ours or another DVC tool's) to another "
        f"format: {formats}. The format is OUT's suffix ({', '.join(FIELD_FORMATS)}) unless "
        "--format names it. The writers are the Export panel's.",
    )
    parser.add_argument("field", help="field file to convert (any format 'correct' reads)")
    parser.add_argument("out", help="file to write (TIFF: OUT_uz.tif, OUT_uy.tif, ...)")
    parser.add_argument(
        "--format",
        choices=tuple(EXPORT_FORMATS),
        default=None,
        help="format to write (default: from OUT's suffix); OUT without a suffix gets the format's",
    )
    group = parser.add_argument_group("the input field")
    _add_input_arguments(group, flag="--in-format")
    for action in group._group_actions:
        if action.dest == "in_format":
            action.help = action.help.replace("format of --field", "format of FIELD")
        if action.dest == "voxel_size":
            action.help = (
                "voxel size in mm: of an input table in physical units, and of the physical "
                "coordinates the outputs write (VTK, CSV, HDF5, TIFF; default: the field's own, "
                "else 1)"
            )
    group.add_argument(
        "--xyz",
        action="store_true",
        help="input table without a header: columns x y z ux uy uz (default z y x uz uy ux)",
    )
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    parser.set_defaults(run=run)
    return parser


def output_path(out: str, fmt: str | None) -> Path:
    """``OUT`` with the suffix of ``--format`` (appended when it has none); refuses a suffix that
    names no format, or another format than ``--format``."""
    from ..io.export import EXPORT_FORMATS, FIELD_FORMATS

    path = Path(out)
    suffix = path.suffix.lower()
    if fmt is None:
        if suffix not in FIELD_FORMATS:
            names = ", ".join(FIELD_FORMATS)
            raise ValueError(
                f"cannot tell the format of {path.name!r}: end it with one of {names}, or give "
                f"--format ({', '.join(EXPORT_FORMATS)})"
            )
        return path
    wanted = EXPORT_FORMATS[fmt]
    if not suffix:
        return path.with_name(path.name + wanted)
    if _ALSO.get(suffix, suffix) != wanted:
        raise ValueError(
            f"{path.name} ends with {path.suffix} but --format {fmt} writes {wanted}: name it "
            f"{path.stem}{wanted} or leave out --format"
        )
    return path


def _check_outputs(field_path: str, out: Path) -> None:
    """Refuse, before reading, an output that is the input field: ``OUT`` itself, or the
    ``OUT_provenance.json`` written next to a format without room for metadata. (The TIFF
    stacks ``OUT_uz.tif``... cannot be an input: no reader takes a TIFF as a field.)"""
    from ..jobs.export import WITH_METADATA
    from ._common import _same_file, check_output_path

    check_output_path(str(out), suffixes=None, inputs=[field_path], option="OUT")
    if out.suffix.lower() in WITH_METADATA:
        return
    stem = out.with_suffix("")
    side = stem.parent / f"{stem.name}_provenance.json"
    if _same_file(side, Path(field_path)):
        raise ValueError(
            f"{out} would write {side.name}, which is the input field: choose another OUT"
        )


def run(args) -> int:
    import numpy as np

    from ..io.export import POINT_FORMATS
    from ..jobs.export import ExportRequest, run_export
    from ._common import ProgressBar, drive
    from ._field_formats import read_input_field

    out = output_path(args.out, args.format)
    _check_outputs(args.field, out)
    reading = argparse.Namespace(**{**vars(args), "format": args.in_format})
    imported = read_input_field(reading, args.field)
    field = imported.field
    note = None
    if imported.points is not None:
        if out.suffix.lower() in POINT_FORMATS and out.suffix.lower() != ".npz":
            field = imported.points  # written at the tool's own points
        else:
            note = f"put on a grid for {out.suffix}: {imported.describe()}"
    voxel_size = args.voxel_size or field.metadata.get("voxel_size") or 1.0
    request = ExportRequest(
        field=field,
        path=out,
        source=str(args.field),
        strain_with_field=False,
        voxel_size=tuple(float(v) for v in np.broadcast_to(voxel_size, (3,))),
    )
    written = drive(run_export(request), ProgressBar(args.quiet))
    if note:
        print(note)
    print(
        f"read {args.field} ({imported.format}, {field.n_points} "
        f"{'points' if imported.points is not None and field is imported.points else 'nodes'}); "
        f"wrote {len(written)} file(s): {', '.join(str(p) for p in written)}"
    )
    return 0
