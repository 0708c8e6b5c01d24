"""Command-line options for fields made by other tools: ``--format``, ``--out-format`` and the
per-format switches, and the two functions the subcommands call to read and write fields.

``correct`` and ``evaluate`` read ``--field`` in any format of :mod:`..io.formats`; a field on
scattered points is put on a grid for the work (interpolated, with provenance) and the result is
written at the user's original points as well. ``correct`` and ``correlate`` write ``--out`` in
any of those formats (from the suffix, or ``--out-format``).
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..engine.correlation.params import CorrelationParams
from ..io.formats import FORMATS

#: Output suffix -> format when ``--out-format`` is not given (``.txt`` is not guessed).
OUTPUT_SUFFIXES = {
    ".npz": "npz",
    ".dvcfield": "npz",  # the same file, under the name only this plugin's napari reader claims
    ".tsv": "spam",
    ".csv": "table",
    ".disp": "idvc",
    ".mat": "aldvc",
    ".vti": "vti",  # VTK image data (grids), for ParaView
    ".vtu": "vtu",  # VTK points (scattered fields)
}


def add_field_format_arguments(
    parser: argparse.ArgumentParser, output: bool = True, field_input: bool = True
) -> None:
    """``--format`` (of ``--field``), ``--out-format`` and the per-format switches."""
    group = parser.add_argument_group("field formats (fields from other DVC tools)")
    if field_input:
        _add_input_arguments(group)
    if output:
        group.add_argument(
            "--out-format",
            choices=("auto", *FORMATS),
            default="auto",
            help="format of --out (default: from the suffix: .npz ours, .tsv spam, .csv table, "
            ".disp iDVC, .mat ALDVC, .vti VTK image, .vtu VTK points)",
        )
    group.add_argument(
        "--xyz",
        action="store_true",
        help="table without a header: columns x y z ux uy uz (default z y x uz uy ux); "
        "tables written: x, y, z order",
    )


def _add_input_arguments(group, flag: str = "--format") -> None:
    group.add_argument(
        flag,
        choices=("auto", *FORMATS),
        default="auto",
        help="format of --field: spam TSV, pyALDVC/ALDVC .npz/.mat, iDVC .disp, a plain "
        "CSV/TSV table, or ours (.npz); default: from the suffix and the header",
    )
    group.add_argument(
        "--voxel-size",
        type=float,
        default=None,
        help="voxel size in mm, for tables whose columns are in physical units (mm, um, m)",
    )
    group.add_argument(
        "--frame-pair",
        type=int,
        default=1,
        help="pyALDVC/ALDVC frame pair to read (1-based, as in U_1; default 1)",
    )
    group.add_argument(
        "--idvc-objective",
        choices=("znssd", "none"),
        default="znssd",
        help="iDVC objective of the run: znssd gives ZNCC = 1 - objmin/2; none for the others",
    )
    group.add_argument(
        "--bin-ratio",
        type=float,
        default=1.0,
        help="spam fieldBinRatio: the field was measured on images binned by this factor",
    )


def _reader_options(args, fmt: str) -> dict:
    if fmt == "table":
        return {"xyz": args.xyz, "voxel_size": args.voxel_size}
    if fmt == "aldvc":
        return {"frame": args.frame_pair}
    if fmt == "spam":
        return {"bin_ratio": args.bin_ratio}
    if fmt == "idvc":
        return {"objective": args.idvc_objective}
    return {}


@dataclass
class InputField:
    """A field read for a subcommand: the grid it is worked on, and its original points."""

    field: object  # DisplacementField
    points: object | None  # ScatteredField when the file was not a regular grid
    format: str
    #: What was done to absurd nodes (:func:`..engine.pair_checks.flag_absurd_nodes`), or None.
    note: str | None = None
    #: The file's points as read when they form the grid (``points`` is None): their order and
    #: labels, so a field written back in the file's format keeps them (iDVC's ``n``).
    rows: object | None = None

    def describe(self) -> str:
        scattered = self.field.metadata.get("scattered", {})
        if self.points is None:
            return f"{self.format} field on a {'x'.join(map(str, self.field.shape))} grid"
        return (
            f"{self.format} field at {self.points.n_points} scattered points, put on a "
            f"{'x'.join(map(str, self.field.shape))} grid (step {self.field.step[0]:g}; "
            f"{scattered.get('interpolated', 0)} nodes interpolated, "
            f"{scattered.get('outside_hull', 0)} outside the points)"
        )


def read_input_field(
    args, path: str, grid=None, sniff: bool = False, volume_shape=None
) -> InputField:
    """Read ``path`` (``--field``) in ``args.format`` (or its sniffed format when ``sniff``); a
    grid field when it is not one already.

    With ``volume_shape`` (z, y, x voxels), a few nodes displaced by more than the volume (a
    tool's diverged matches) are marked failed before the field is put on a grid, so they are
    cleaned instead of spread by the interpolation; a field mostly made of them is refused
    (:func:`..engine.pair_checks.flag_absurd_nodes`). ``InputField.note`` then says so.
    """
    from ..engine.fields.absurd_nodes import flag_absurd_nodes
    from ..engine.fields.scattered import to_grid
    from ..io.formats import read_points, refuse_single_point, sniff_format

    if not Path(path).is_file():
        raise FileNotFoundError(f"field file not found: {path}")
    fmt = "auto" if sniff else getattr(args, "format", "auto")
    fmt = sniff_format(path) if fmt in (None, "auto") else fmt
    points = read_points(path, fmt, **_reader_options(args, fmt))
    refuse_single_point(path, points)
    source = points.metadata.get("source", {})
    if source.get("format") == "table" and source.get("header") is False:
        from ._common import warn

        order = " ".join(source["columns"][:6])
        other = "" if getattr(args, "xyz", False) else "; --xyz reads x y z ux uy uz"
        warn(
            args,
            f"{Path(path).name} has no header line: its columns were read by position as "
            f"{order} (voxels, 0-based){other}; a header naming the columns (z, y, x, uz, uy, "
            "ux, any order) removes the guess",
        )
    if source.get("frames", 1) > 1:
        from ._common import warn

        warn(
            args,
            f"{Path(path).name} holds {source['frames']} frame pairs: read pair "
            f"{source['frame']} (--frame-pair K reads another)",
        )
    note = None
    if volume_shape is not None:
        points, note = flag_absurd_nodes(points, volume_shape, f"field {Path(path).name}")
    field = to_grid(points, grid=grid)
    scattered = field.metadata.get("scattered", {})
    regular = (
        grid is None
        and scattered.get("interpolated", 0) == 0
        and (scattered.get("outside_hull", 0) == 0)
    )
    return InputField(
        field=field,
        points=None if regular else points,
        format=fmt,
        note=note,
        rows=points if regular else None,
    )


def output_format(args, out: str) -> str:
    """The format ``--out`` will be written in; refuses unknown suffixes before any work."""
    path = Path(out)
    chosen = getattr(args, "out_format", "auto")
    if chosen not in (None, "auto"):
        fmt = chosen
    else:
        fmt = OUTPUT_SUFFIXES.get(path.suffix.lower())
        if fmt is None:
            raise ValueError(
                f"output {path} must end with {', '.join(OUTPUT_SUFFIXES)} (or give --out-format)"
            )
    if not path.parent.exists():
        raise FileNotFoundError(f"output folder does not exist: {path.parent}")
    return fmt


def check_points_output(fmt: str) -> None:
    """Refuse an output format that needs a grid for a field at a list of points."""
    if fmt == "vti":
        raise ValueError("a field at a list of points is written as .vtu, not .vti")
    if fmt == "npz":
        raise ValueError(
            "a field at a list of points cannot be written as our grid .npz: "
            "name --out .csv, .tsv, .disp, .mat or .vtu"
        )


def side_path(out: str | Path, fmt: str) -> Path:
    """The side file written next to ``out`` for a field on points: ``<stem>_points.csv`` (the
    points) beside our ``.npz`` grid, ``<stem>_grid.npz`` (the grid) beside another format."""
    out = Path(out)
    return out.with_name(out.stem + ("_points.csv" if fmt == "npz" else "_grid.npz"))


def _writer_options(args, fmt: str) -> dict:
    if fmt == "table":
        return {"xyz": getattr(args, "xyz", False)}
    return {}


def write_output_field(args, field, out: str, points=None, rows=None) -> list[Path]:
    """Write ``field`` to ``out`` in the output format; returns the files written.

    ``points`` (a ScatteredField: the user's original points) makes the result be reported there
    too: in another tool's format ``out`` holds the field at those points and ``<stem>_grid.npz``
    the grid; in our ``.npz`` ``out`` holds the grid and ``<stem>_points.csv`` the points.
    ``rows`` (the points of an iDVC file that formed the grid, :attr:`InputField.rows`) makes an
    iDVC ``out`` list the nodes in that file's order under its labels ``n`` (iDVC's own clouds
    run x slowest: the grid's C order under labels 1..N gave each label another point).
    """
    from ..engine.fields.scattered import ScatteredField, sample_field
    from ..io.formats import write_field

    fmt = output_format(args, out)
    out = Path(out)
    if fmt in ("vti", "vtu"):
        from ..io.export import export_vtk, export_vtk_points

        if isinstance(field, ScatteredField):
            check_points_output(fmt)
        if fmt == "vtu":
            export_vtk_points(field if points is None else sample_field(field, points.points), out)
        else:
            export_vtk(field, out)
        return [out]
    if isinstance(field, ScatteredField):
        check_points_output(fmt)
        write_field(field, out, fmt, **_writer_options(args, fmt))
        return [out]
    if points is None:
        ordered = _in_file_rows(field, rows) if fmt == "idvc" else None
        if ordered is not None:
            write_field(ordered[0], out, fmt, point_ids=ordered[1])
        else:
            write_field(field, out, fmt, **_writer_options(args, fmt))
        return [out]
    from ..io.atomic import atomic_files

    at_points = sample_field(field, points.points)
    side = side_path(out, fmt)
    with atomic_files(out, side) as (temp_out, temp_side):  # both files new, or neither
        if fmt == "npz":
            write_field(field, temp_out, "npz")
            write_field(at_points, temp_side, "table", **_writer_options(args, "table"))
        else:
            options = _writer_options(args, fmt)
            ids = _file_labels(points)
            if fmt == "idvc" and ids is not None:  # the file's own labels n, same rows
                options["point_ids"] = ids
            write_field(at_points, temp_out, fmt, **options)
            write_field(field, temp_side, "npz")
    return [out, side]


def _file_labels(rows):
    """The labels ``n`` of an iDVC file's rows (one each, all different), or None."""
    ids = (getattr(rows, "metadata", None) or {}).get("source", {}).get("point_ids")
    if ids is None or len(ids) != rows.n_points or len(set(ids)) != len(ids):
        return None
    return np.asarray(ids, np.int64)


def _in_file_rows(field, rows):
    """The grid ``field``'s nodes in the order of an iDVC file's ``rows`` that formed that grid,
    with the file's labels; None when ``rows`` are not such a file or not all on its nodes."""
    from ..engine.fields.scattered import from_grid

    ids = _file_labels(rows)
    if ids is None:
        return None
    index = (np.asarray(rows.points) - np.asarray(field.origin)) / np.asarray(field.step)
    whole = np.rint(index)
    shape = np.asarray(field.shape)
    if np.max(np.abs(index - whole)) > 1e-6 or np.any(whole < 0) or np.any(whole >= shape):
        return None
    flat = np.ravel_multi_index(tuple(whole.astype(np.intp).T), tuple(field.shape))
    if len(np.unique(flat)) != field.n_points:  # the rows are not every node once
        return None
    ordered = from_grid(field)
    for name in ("points", "u", "zncc", "status", "iterations", "provenance", "gradient",
                 "uncertainty"):  # fmt: skip
        value = getattr(ordered, name)
        if value is not None:
            setattr(ordered, name, np.asarray(value)[flat])
    return ordered, ids


def _grid_step(text: str) -> int:
    """``--grid-step``: a whole number of voxels >= 1."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number of voxels") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1 voxel, got {text!r}")
    return value


def add_correction_field_arguments(parser: argparse.ArgumentParser) -> None:
    """``correct``'s options for imported fields: the subvolume and, if wanted, a new grid."""
    group = parser.add_argument_group("imported fields")
    group.add_argument(
        "--subvolume",
        type=int,
        default=None,
        help="odd subvolume edge (voxels) of the correction's DVC; default: the field's own "
        f"parameters, else {CorrelationParams.subvolume} (spam and iDVC files do not record it)",
    )
    group.add_argument(
        "--grid-step",
        type=_grid_step,
        default=None,
        help="put the field on a new grid with this spacing (voxels) before correcting; "
        "default: keep the field's own grid (or, with --roi/--cylinder/--origin, its step)",
    )


def prepare_correction_field(args, volume_shape):
    """Read ``--field`` for ``correct``: the InputField and the DVC parameters (or None).

    The field keeps its own grid unless ``--grid-step``, ``--roi``, ``--cylinder`` or
    ``--origin`` ask for another one (then it is interpolated onto it, with provenance).
    """
    from ..engine.correlation.placement import grid_for_region, restrict_to_region
    from ..engine.fields.scattered import from_grid, to_grid
    from . import _grid_options

    imported = read_input_field(args, args.field, volume_shape=volume_shape)
    field = imported.field
    params = None
    subvolume = getattr(args, "subvolume", None)
    if subvolume is not None or not field.params:
        values = dict(field.params)
        values["subvolume"] = subvolume or field.params.get(
            "subvolume", CorrelationParams.subvolume
        )
        params = CorrelationParams.from_dict(values)
    if not (getattr(args, "grid_step", None) or _grid_options.wants_placement(args)):
        nodes = np.concatenate([np.asarray(field.origin), np.asarray(field.step)])
        if np.max(np.abs(nodes - np.rint(nodes))) > 1e-6:
            raise ValueError(
                f"the field's grid (origin {field.origin}, step {field.step}) is not on whole "
                "voxels, where the correction's subvolumes are centred: give --grid-step N to "
                "correct it on a whole-voxel grid"
            )
        return imported, params
    used = params or CorrelationParams.from_dict(field.params)
    step = args.grid_step or int(round(max(field.step)))
    region = _grid_options.region_from_args(args, volume_shape)
    origin = _grid_options.parse_origin(args.origin) if getattr(args, "origin", None) else None
    grid = grid_for_region(volume_shape, used.subvolume, step, region, origin)
    source = imported.points if imported.points is not None else from_grid(field)
    regridded = to_grid(source, grid=grid)
    if region is not None:
        regridded = restrict_to_region(regridded, region)
    regridded.params = dict(field.params)
    return InputField(regridded, imported.points, imported.format, imported.note), params


def run_points(args, params, out, started, run=None) -> int:
    """``--points FILE``: DVC at exactly those points, written in the output format.

    ``run`` (:class:`..engine.run_options.RunOptions`, default: in memory) out of core: the
    volumes are read lazily, only the regions the points need
    (:func:`..jobs.correlate.points_job`), with the large-volume options.
    """
    import time

    from ..engine.run_options import RunOptions
    from ..jobs.correlate import points_job
    from ..jobs.volumes import load_volume
    from ._common import ProgressBar, check_search, drive
    from ._grid_options import load_points
    from ._tiled_options import _plan_reporter

    if getattr(args, "self_correct", False):
        raise ValueError("--points does not combine with --self-correct")
    check_points_output(output_format(args, out))  # before any work
    run = RunOptions() if run is None else run
    points = load_points(args.points)
    reference = load_volume(args.reference, run)
    check_search(params, reference.shape)
    deformed = load_volume(args.deformed, run)
    mask = load_volume(args.mask, run) if args.mask else None
    job = points_job(reference, deformed, points, params, mask=mask, run=run)
    result = drive(job, _plan_reporter(args, ProgressBar(args.quiet).update, "tiled points"))
    result.metadata["reference"] = str(args.reference)
    result.metadata["deformed"] = str(args.deformed)
    result.metadata["points_file"] = str(args.points)
    write_output_field(args, result, out)
    print(
        f"POIs: {result.n_points} from {args.points}; {result.node_counts().text()}; "
        f"time {time.perf_counter() - started:.2f} s; wrote {out}"
    )
    return 0
