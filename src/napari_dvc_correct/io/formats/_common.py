"""Helpers shared by the format modules: field kinds, axis order, text tables."""

from __future__ import annotations

import os
import warnings

import numpy as np

from ...engine.fields.field import DisplacementField
from ...engine.fields.scattered import ScatteredField, from_grid


def as_scattered(field: DisplacementField | ScatteredField) -> ScatteredField:
    """Any field as points (a grid field's nodes in C order)."""
    if isinstance(field, ScatteredField):
        return field
    if isinstance(field, DisplacementField):
        return from_grid(field)
    raise TypeError(f"expected a DisplacementField or ScatteredField, got {type(field).__name__}")


def unusable_as_nan(field):
    """``field`` with NaN displacement (and gradient) where it holds no usable value.

    A node (or point) without a usable value is a failed match not filled in by cleaning
    (``field.valid`` is False: diverged, low ZNCC, masked...). Every export writes this
    displacement next to the node's status code, so a node's state reads the same way in every
    format; filled-in nodes keep their value, marked by their status and provenance. The field
    itself is not changed (a copy is returned when a node is set to NaN).

    Parameters
    ----------
    field : DisplacementField or ScatteredField
        ``u`` is ``(..., 3)`` in voxels, (z, y, x).
    """
    bad = ~np.asarray(field.valid, dtype=bool)
    if not bad.any():
        return field
    out = field.copy()
    out.u = np.array(out.u, dtype=np.float64)
    out.u[bad] = np.nan
    if getattr(out, "gradient", None) is not None:
        out.gradient = np.array(out.gradient, dtype=np.float64)
        out.gradient[bad] = np.nan
    return out


def flip_vectors(values: np.ndarray) -> np.ndarray:
    """``(..., 3)`` between (z, y, x) and (x, y, z) order (its own inverse)."""
    return np.ascontiguousarray(np.asarray(values, dtype=np.float64)[..., ::-1])


def flip_tensors(values: np.ndarray) -> np.ndarray:
    """``(..., 3, 3)`` gradients ``du_i/dX_j`` between (z, y, x) and (x, y, z) order."""
    return np.ascontiguousarray(np.asarray(values, dtype=np.float64)[..., ::-1, ::-1])


def first_line(path: str | os.PathLike) -> str:
    """The first line that is neither empty nor a ``#`` comment."""
    with open(path, encoding="utf-8", errors="replace") as handle:
        for line in handle:
            stripped = line.strip()
            if stripped and not stripped.startswith("#"):
                return stripped
    return ""


def _number(text: str) -> float:
    text = text.strip()
    return float(text) if text else np.nan  # an empty cell: pyALDVC writes NaN so


def load_numbers(
    path: str | os.PathLike,
    delimiter: str | None,
    skiprows: int = 0,
    columns: int | None = None,
    usecols=None,
) -> np.ndarray:
    """The rows ``(N, C)`` of a delimited text table of numbers (``#`` lines are comments).

    Empty cells are NaN. ``columns`` is the number of columns the header names: a file with a
    header and no rows gives ``(0, columns)``. ``usecols`` (indices) reads only those columns
    (the others may hold text).

    Raises
    ------
    ValueError
        With the file's name: a cell that is not a number, or rows of different lengths.
    """
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # "input contained no data"
            rows = np.loadtxt(
                path,
                delimiter=delimiter,
                comments="#",
                skiprows=skiprows,
                ndmin=2,
                dtype=np.float64,
                converters=_number if delimiter is not None else None,
                usecols=usecols,
            )
    except ValueError as error:
        raise ValueError(f"{path}: not a table of numbers ({error})") from None
    if rows.size == 0:
        return np.zeros((0, columns or 0))
    return rows


def read_named_table(
    path: str | os.PathLike, delimiter: str | None
) -> tuple[list[str], np.ndarray]:
    """Header names and the float rows (N, columns) of a delimited text table."""
    header = first_line(path)
    if not header:
        raise ValueError(f"{path}: the file is empty")
    if delimiter is None:
        delimiter = "\t" if "\t" in header else ("," if "," in header else None)
    names = [n.strip() for n in (header.split(delimiter) if delimiter else header.split())]
    rows = load_numbers(path, delimiter, header_row(path) + 1, len(names))
    if rows.shape[1] != len(names):
        raise ValueError(
            f"{path}: the header names {len(names)} columns but the rows have {rows.shape[1]}"
        )
    return names, rows


def header_row(path) -> int:
    with open(path, encoding="utf-8", errors="replace") as handle:
        for number, line in enumerate(handle):
            stripped = line.strip()
            if stripped and not stripped.startswith("#"):
                return number
    return 0


def column(names: list[str], rows: np.ndarray, *candidates: str, required: bool = True):
    """The column named by the first candidate present (exact name), or None."""
    for name in candidates:
        if name in names:
            return rows[:, names.index(name)]
    if required:
        raise ValueError(f"missing column {candidates[0]!r} (columns present: {', '.join(names)})")
    return None
