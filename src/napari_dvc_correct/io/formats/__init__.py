"""Fields made by other DVC tools: read them, and write results back in their formats.

One module per tool, each with ``read(path, ...) -> ScatteredField`` (the points as the file has
them, in its order) and ``write(field, path, ...)`` (a grid or a scattered field); the conventions
each follows, and where they were checked, are in its docstring:

* :mod:`.spam` — spam TSV (``spam-ldic``, ``spam-pixelSearch``);
* :mod:`.aldvc` — pyALDVC ``.npz`` and ALDVC MATLAB ``.mat``;
* :mod:`.idvc` — CCPi iDVC ``.disp``;
* :mod:`.table` — plain CSV/TSV with named columns and units;
* ``"npz"`` — our own field file (:mod:`..npz`).

:func:`read_points` sniffs the format from the suffix and the header; :func:`read_field` puts
the points on a grid (:func:`.engine.fields.scattered.to_grid`: exactly when they form one, else
interpolated, with provenance); :func:`write_field` writes any field in any of the formats.
"""

from __future__ import annotations

import os
import zipfile
from pathlib import Path

import numpy as np

from ...engine.fields.field import DisplacementField
from ...engine.fields.scattered import ScatteredField, from_grid, to_grid
from ..npz import FIELD_SUFFIX
from . import aldvc, idvc, spam, table
from ._common import first_line, unusable_as_nan

FORMATS = ("spam", "aldvc", "idvc", "table", "npz")

#: Suffixes each writer is used for by default (first = the one :func:`default_suffix` gives).
SUFFIXES = {
    "spam": (".tsv",),
    "aldvc": (".npz", ".mat"),
    "idvc": (".disp",),
    "table": (".csv", ".tsv", ".txt"),
    "npz": (".npz",),
}


def _npz_kind(path: Path) -> str:
    try:
        with zipfile.ZipFile(path) as archive:
            names = {n[:-4] if n.endswith(".npy") else n for n in archive.namelist()}
    except zipfile.BadZipFile as error:
        raise ValueError(f"{path}: not a valid .npz file") from error
    if "coordinates" in names and "U_1" in names:
        return "aldvc"
    if "u" in names and "origin" in names:
        return "npz"
    raise ValueError(
        f"{path}: an .npz that is neither ours (origin, u) nor pyALDVC's (coordinates, U_1)"
    )


#: Formats the exports write for other programs but that are not read back as a field.
EXPORT_ONLY = {".h5": "HDF5", ".hdf5": "HDF5", ".vti": "VTK", ".vtk": "VTK", ".vtu": "VTK",
               ".tif": "TIFF", ".tiff": "TIFF"}  # fmt: skip


def sniff_format(path: str | os.PathLike) -> str:
    """The format of a field file, from its suffix and, for text tables, its header line."""
    path = Path(path)
    suffix = path.suffix.lower()
    if not path.is_file():
        raise FileNotFoundError(f"field file not found: {path}")
    if suffix in EXPORT_ONLY:
        raise ValueError(
            f"{path}: a {EXPORT_ONLY[suffix]} file is an export for other programs and is not "
            "read back as a field: give the field file it was exported from (.dvcfield or "
            ".npz), or a spam .tsv, pyALDVC .npz/.mat, iDVC .disp or CSV table"
        )
    if suffix == ".disp":
        return "idvc"
    if suffix == ".mat":
        if not aldvc.is_result_mat(path):
            raise ValueError(
                f"{path}: a .mat without DVCmesh or coordinatesFEM: not an ALDVC result"
            )
        return "aldvc"
    if suffix in (".npz", FIELD_SUFFIX):  # ours carries the same contents under both names
        return _npz_kind(path)
    header = first_line(path)
    if spam.looks_like(header):
        return "spam"
    if idvc.looks_like(header):
        return "idvc"
    return "table"


def _module(name: str):
    modules = {"spam": spam, "aldvc": aldvc, "idvc": idvc, "table": table}
    if name not in FORMATS:
        raise ValueError(f"unknown field format {name!r}; choose one of {', '.join(FORMATS)}")
    return modules.get(name)


def read_points(path: str | os.PathLike, format: str | None = None, **options) -> ScatteredField:
    """Read a field file as points, in the file's order (``options`` go to the format's reader).

    ``metadata["source"]["format"]`` records the format used.
    """
    fmt = sniff_format(path) if format is None else format
    module = _module(fmt)
    if module is None:  # our own .npz
        from ..npz import load_field

        if options:
            raise ValueError(f"options {sorted(options)} do not apply to the npz format")
        scattered = from_grid(load_field(path))
        scattered.metadata.setdefault("source", {"format": "npz", "path": str(path)})
        return scattered
    try:
        points = module.read(path, **options)
    except ValueError as error:  # the engine's checks do not know the file: name it
        if str(path) in str(error):
            raise
        raise ValueError(f"{path}: {error}") from None
    except (OSError, MemoryError):
        raise
    except Exception as error:  # a library's own error (scipy's MatReadError, KeyError...)
        raise ValueError(
            f"{path}: not a readable {fmt} field file ({type(error).__name__}: {error})"
        ) from None
    if points.n_points == 0:
        raise ValueError(f"{path}: the file holds no points (a header and no rows)")
    refuse_conflicting_duplicates(path, points)
    return points


def refuse_conflicting_duplicates(path, points: ScatteredField) -> None:
    """Refuse a point given twice with two displacements: which one holds cannot be guessed
    (identical repeated rows are harmless and kept).

    Raises
    ------
    ValueError
        Naming the file, how many points conflict and the first of them (z, y, x voxels).
    """
    keys = np.round(np.asarray(points.points, np.float64), 6)
    _, inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    repeated = np.flatnonzero(counts[inverse] > 1)
    if repeated.size == 0:
        return
    u = np.asarray(points.u, np.float64)
    conflicts = []
    for group in np.unique(inverse[repeated]):
        rows = np.flatnonzero(inverse == group)
        values = u[rows]
        same = np.all(np.isclose(values, values[0], rtol=0, atol=1e-9, equal_nan=True))
        if not same:
            conflicts.append(rows)
    if conflicts:
        first = conflicts[0]
        raise ValueError(
            f"{path}: {len(conflicts)} point(s) appear more than once with different "
            f"displacements, e.g. z, y, x = {tuple(float(v) for v in points.points[first[0]])} "
            f"in rows {', '.join(str(r + 1) for r in first[:4])}: keep one row per point"
        )


def refuse_single_point(path, points: ScatteredField) -> None:
    """Refuse a file of one point as a field: a spam-reg registration (one Φ for the whole
    volume) was put on a 1-node grid, and ``correct`` asked for ``--grid-step``.

    Raises
    ------
    ValueError
        Naming the file, the point (z, y, x voxels) and, for spam, what to give instead.
    """
    if points.n_points != 1:
        return
    where = tuple(round(float(v), 3) for v in points.points[0])
    what = (
        "a spam-reg registration (one Φ for the whole volume), not a field: give the spam-ldic "
        "TSV computed with -pf on it"
        if points.metadata.get("source", {}).get("format") == "spam"
        else "a field needs points spread over the volume"
    )
    raise ValueError(f"{path}: holds a single point (z, y, x = {where}): {what}")


def read_field(
    path: str | os.PathLike, format: str | None = None, grid=None, **options
) -> DisplacementField:
    """Read a field file onto a regular grid (its own when the points form one).

    Parameters
    ----------
    path : path
    format : {"spam", "aldvc", "idvc", "table", "npz"}, optional
        Default: sniffed (:func:`sniff_format`).
    grid : (origin, step, shape), optional
        Target grid in voxels; default: the points' own grid, or one over their bounding box at
        their typical spacing (:func:`.engine.fields.scattered.default_grid`).
    **options
        Passed to the format's reader (``xyz``, ``voxel_size``, ``frame``, ``bin_ratio``...).
    """
    points = read_points(path, format, **options)
    refuse_single_point(path, points)
    try:
        return to_grid(points, grid=grid)
    except ValueError as error:  # e.g. points in one plane: say which file (napari's File ▸ Open)
        if str(path) in str(error):
            raise
        raise ValueError(f"{path}: {error}") from None


def default_suffix(format: str) -> str:
    return SUFFIXES[format][0]


def write_field(
    field: DisplacementField | ScatteredField,
    path: str | os.PathLike,
    format: str | None = None,
    **options,
) -> Path:
    """Write ``field`` to ``path`` in ``format`` (default: from the suffix: ``.tsv`` → spam,
    ``.disp`` → idvc, ``.mat`` → aldvc, ``.csv``/``.txt`` → table, ``.npz`` → ours)."""
    path = Path(path)
    if format is None:
        format = {
            ".tsv": "spam",
            ".disp": "idvc",
            ".mat": "aldvc",
            ".csv": "table",
            ".txt": "table",
        }.get(path.suffix.lower(), "npz" if path.suffix.lower() == ".npz" else None)
        if format is None:
            raise ValueError(
                f"cannot tell the format from {path.name!r}: name it with one of "
                ".tsv .disp .mat .csv .txt .npz, or give the format"
            )
    module = _module(format)
    if module is None:
        from ..npz import save_field

        if isinstance(field, ScatteredField):
            field = to_grid(field)
        save_field(field, path)
        return path
    module.write(unusable_as_nan(field), path, **options)  # a failed node: NaN and its status
    return path


__all__ = [
    "FORMATS",
    "default_suffix",
    "read_field",
    "read_points",
    "sniff_format",
    "write_field",
]
