"""Command-line options for where the points go: ``--roi``, ``--cylinder``, ``--origin``,
``--points``, and (``correct``) ``--grid-step`` to put an imported field on another grid.

Syntax (voxels of the reference volume, 0-based, z, y, x):

* ``--roi z0:z1,y0:y1,x0:x1`` — half-open ranges like numpy slices; an empty bound means the
  volume's edge (``--roi :,10:50,``  limits y only);
* ``--cylinder Y,X,R`` or ``--cylinder Y,X,R,Z0:Z1`` — a cylinder along z with centre (y, x),
  radius R and an optional z range (default: the whole height);
* ``--origin Z,Y,X`` — the first node, whole voxels;
* ``--points FILE`` — a list of points of interest: a CSV/TSV whose header names the columns
  ``z, y, x`` (any order, other columns ignored), an ``.npy`` of shape (N, 3) in z, y, x, a CCPi
  ``.roi`` point cloud (``n x y z``), or a field file whose points are wanted (spam TSV, iDVC
  ``.disp``, pyALDVC ``.npz``/``.mat``/``.csv``, ours), read in its own axis order.
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path

import numpy as np


def add_grid_arguments(parser: argparse.ArgumentParser, points: bool = True) -> None:
    group = parser.add_argument_group("where the points go")
    group.add_argument(
        "--roi",
        default=None,
        metavar="Z0:Z1,Y0:Y1,X0:X1",
        help="region of interest (voxels, half-open like numpy slices; empty = volume edge)",
    )
    group.add_argument(
        "--cylinder",
        default=None,
        metavar="Y,X,R[,Z0:Z1]",
        help="cylindrical region along z: centre (y, x), radius, optional z range",
    )
    group.add_argument(
        "--origin", default=None, metavar="Z,Y,X", help="position of the first node (voxels)"
    )
    if points:
        group.add_argument(
            "--points",
            default=None,
            metavar="FILE",
            help="points of interest: CSV/TSV with a header naming z,y,x, .npy (N, 3) z,y,x, "
            "a CCPi .roi (n x y z), or another field file's points (spam .tsv, .disp, "
            "pyALDVC .npz/.mat/.csv); results at exactly those points",
        )


def _range(text: str, axis: str, size: int | None) -> tuple[float, float]:
    text = text.strip()
    if text in ("", ":"):
        if size is None:
            raise ValueError(f"--roi: give both bounds along {axis}")
        return 0.0, float(size)
    match = re.fullmatch(r"\s*(-?[\d.]*)\s*:\s*(-?[\d.]*)\s*", text)
    if not match:
        raise ValueError(f"--roi: {axis} range {text!r} is not START:STOP")
    lo = float(match.group(1)) if match.group(1) else 0.0
    if match.group(2):
        hi = float(match.group(2))
    elif size is not None:
        hi = float(size)
    else:
        raise ValueError(f"--roi: {axis} range {text!r} needs a stop")
    return lo, hi


def parse_roi(text: str, volume_shape=None):
    """``"z0:z1,y0:y1,x0:x1"`` -> :class:`..engine.correlation.placement.Box`."""
    from ..engine.correlation.placement import Box

    parts = text.split(",")
    if len(parts) != 3:
        raise ValueError(f"--roi needs three ranges z0:z1,y0:y1,x0:x1, got {text!r}")
    sizes = [None] * 3 if volume_shape is None else list(volume_shape)
    bounds = [_range(p, a, s) for p, a, s in zip(parts, "zyx", sizes)]
    return Box(tuple(b[0] for b in bounds), tuple(b[1] for b in bounds))


def parse_cylinder(text: str):
    """``"Y,X,R"`` or ``"Y,X,R,Z0:Z1"`` -> :class:`..engine.correlation.placement.Cylinder`."""
    from ..engine.correlation.placement import Cylinder

    parts = [p.strip() for p in text.split(",")]
    if len(parts) not in (3, 4):
        raise ValueError(f"--cylinder needs Y,X,R or Y,X,R,Z0:Z1, got {text!r}")
    try:
        yc, xc, radius = (float(p) for p in parts[:3])
    except ValueError as error:
        raise ValueError(f"--cylinder: Y, X and R must be numbers, got {text!r}") from error
    z_range = None
    if len(parts) == 4:
        z_range = _range(parts[3], "z", None)
    return Cylinder((yc, xc), radius, z_range)


def parse_origin(text: str) -> tuple[int, int, int]:
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError as error:
        raise ValueError(f"--origin needs Z,Y,X numbers, got {text!r}") from error
    if len(values) != 3:
        raise ValueError(f"--origin needs three values Z,Y,X, got {text!r}")
    return tuple(values)


def load_points(path: str) -> np.ndarray:
    """Points of interest ``(N, 3)`` in z, y, x.

    From a CSV/TSV whose header names ``z, y, x``; an ``.npy`` (N, 3) in z, y, x; a CCPi ``dvc``
    point cloud ``.roi`` (``n x y z`` rows, no header: x is the fastest image axis); or the
    points of a field file another tool (or this program) wrote: a spam TSV (``Zpos Ypos
    Xpos``), an iDVC ``.disp``, a pyALDVC ``.npz``/``.mat``/``.csv``, our ``.npz`` or table
    (``z [voxel]``...), each read in its own axis order (:mod:`..io.formats`).
    """
    file = Path(path)
    if not file.is_file():
        raise FileNotFoundError(f"points file not found: {file}")
    suffix = file.suffix.lower()
    if suffix == ".npy":
        return _npy_points(file)
    if suffix == ".roi":
        return _roi_points(file)
    if suffix in (".npz", ".mat", ".dvcfield"):
        return _field_file_points(file)
    with open(file, encoding="utf-8", errors="replace") as handle:
        header = next((line for line in handle if line.strip() and not line.startswith("#")), "")
    delimiter = "\t" if "\t" in header else ("," if "," in header else None)
    names = [n.strip().lower() for n in (header.split(delimiter) if delimiter else header.split())]
    if not all(a in names for a in "zyx"):
        from ..io.formats import sniff_format, table

        if sniff_format(file) != "table" or table.looks_like(header):
            return _field_file_points(file)  # spam's Zpos..., a table with units
        raise ValueError(
            f"{file}: the header must name the columns z, y, x (found {names}); a CCPi point "
            "cloud without a header needs the suffix .roi (n x y z)"
        )
    from ..io.formats._common import header_row, load_numbers

    rows = load_numbers(file, delimiter, header_row(file) + 1, len(names))
    if len(rows) == 0:
        raise ValueError(f"{file}: no points (a header and no rows)")
    if rows.shape[1] != len(names):
        raise ValueError(
            f"{file}: the header names {len(names)} columns but the rows have {rows.shape[1]}"
        )
    return _finite(file, rows[:, [names.index(a) for a in "zyx"]])


def _finite(file: Path, points: np.ndarray) -> np.ndarray:
    if not np.all(np.isfinite(points)):
        raise ValueError(f"{file}: a point has an empty or non-finite coordinate")
    return np.ascontiguousarray(points, dtype=np.float64)


def _npy_points(file: Path) -> np.ndarray:
    try:
        points = np.load(file, allow_pickle=False, mmap_mode="r")
    except (ValueError, OSError, EOFError) as error:
        raise ValueError(f"{file}: not a readable .npy of points ({error})") from None
    if points.ndim != 2 or points.shape[1] != 3 or len(points) == 0:
        raise ValueError(
            f"{file}: an .npy of points must have shape (N, 3), N >= 1, got {points.shape}"
        )
    if points.dtype.kind not in "uif":
        raise ValueError(f"{file}: points must be numbers, got dtype {points.dtype}")
    return _finite(file, np.asarray(points, np.float64))


def _roi_points(file: Path) -> np.ndarray:
    from ..io.formats.idvc import read_roi

    return read_roi(file)


def _field_file_points(file: Path) -> np.ndarray:
    from ..io.formats import read_points

    points = read_points(file).points  # every point of the file, failed matches included
    return _finite(file, np.asarray(points, np.float64))


def region_from_args(args, volume_shape=None):
    roi, cylinder = getattr(args, "roi", None), getattr(args, "cylinder", None)
    if roi and cylinder:
        raise ValueError("give --roi or --cylinder, not both")
    if roi:
        return parse_roi(roi, volume_shape)
    if cylinder:
        return parse_cylinder(cylinder)
    return None


def wants_placement(args) -> bool:
    return any(getattr(args, name, None) for name in ("roi", "cylinder", "origin", "points"))


def grid_from_args(args, volume_shape, params):
    """The POI grid for ``correlate``; None when no placement option is given."""
    from ..engine.correlation.placement import grid_for_region

    if not any(getattr(args, name, None) for name in ("roi", "cylinder", "origin")):
        return None
    origin = parse_origin(args.origin) if getattr(args, "origin", None) else None
    return grid_for_region(
        volume_shape, params.subvolume, params.step, region_from_args(args, volume_shape), origin
    )


def finish_grid_field(args, field, volume_shape):
    """Drop the nodes outside a cylinder (a box needs nothing: the grid is inside it)."""
    from ..engine.correlation.placement import describe_region, restrict_to_region

    region = region_from_args(args, volume_shape)
    if region is None:
        return field
    field = restrict_to_region(field, region)
    field.metadata["region"] = describe_region(region)
    return field
