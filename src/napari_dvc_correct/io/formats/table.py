"""Plain CSV/TSV tables: one row per point, columns named in a header, units in brackets.

Our own convention (no other tool's), for fields from any program that can write a table
(DaVis, Avizo, OpenCorr, a script):

* one header line naming the columns (any order, case-insensitive): positions ``z y x`` and
  displacements ``uz uy ux`` (also accepted: ``u_z``, ``dz``, ``zdisp``, ``disp_z``...; and the
  DIC names ``u v w`` or pyALDVC's ``disp_u disp_v disp_w`` = displacement along **x, y, z**;
  with OpenCorr's ``u v w ux uy uz vx vy vz wx wy wz`` the ``ux``... are the gradient du/dx...;
  empty cells are NaN); optional ``valid`` (pyALDVC: 0 = not usable), ``zncc``, ``status`` (our
  :class:`.engine.fields.field.Status` codes), ``provenance``, ``iterations``;
* units in brackets or parentheses after a name: ``z [voxel]``, ``ux (mm)``. ``voxel``/``vox``/
  ``px``/``pixel`` (or no unit) are voxels; ``m``, ``mm``, ``um``/``µm``, ``nm`` need the voxel
  size (mm per voxel, one value or z, y, x) to be converted to voxels;
* comma-, tab- or whitespace-separated (from the header line); ``#`` lines are comments;
* positions are 0-based voxel indices (voxel ``i`` centred at ``i``); ``index_base=1`` reads
  1-based positions (MATLAB-style) and ``offset`` shifts positions by ``(z, y, x)`` voxels;
* a table without a header is read by position: ``z y x uz uy ux`` or, with ``xyz=True``,
  ``x y z ux uy uz``. With a header the names decide, and ``xyz`` only sets the column order
  written.
"""

from __future__ import annotations

import os
import re

import numpy as np

from ...engine.fields.field import Provenance, Status
from ...engine.fields.scattered import ScatteredField
from ..atomic import atomic_path
from ._common import as_scattered, first_line, load_numbers

UNITS_MM = {"m": 1000.0, "mm": 1.0, "um": 1e-3, "µm": 1e-3, "micron": 1e-3, "nm": 1e-6}
VOXEL_UNITS = {"", "voxel", "voxels", "vox", "px", "pixel", "pixels"}
_ALIASES = {
    "z": ("z", "zpos", "z_pos", "pos_z"),
    "y": ("y", "ypos", "y_pos", "pos_y"),
    "x": ("x", "xpos", "x_pos", "pos_x"),
    "uz": ("uz", "u_z", "dz", "zdisp", "disp_z", "displacement_z", "w", "disp_w"),
    "uy": ("uy", "u_y", "dy", "ydisp", "disp_y", "displacement_y", "v", "disp_v"),
    "ux": ("ux", "u_x", "dx", "xdisp", "disp_x", "displacement_x", "u", "disp_u"),
    "zncc": ("zncc", "cc", "correlation"),
    "status": ("status",),
    "valid": ("valid",),  # pyALDVC's CSV: 1 = a usable node, 0 = not
    "provenance": ("provenance",),
    "iterations": ("iterations", "iter", "iteration"),  # OpenCorr: "iteration"
}
#: Text columns skipped (the words of the codes in ``status`` and ``provenance``).
_TEXT_COLUMNS = ("status_name", "provenance_name")
_SPLIT = re.compile(r"^\s*([^\[\(]*?)\s*(?:[\[\(]\s*([^\]\)]*)\s*[\]\)])?\s*$")


def _parse_name(raw: str) -> tuple[str, str]:
    match = _SPLIT.match(raw)
    name, unit = (match.group(1), match.group(2) or "") if match else (raw, "")
    return name.strip().lower(), unit.strip().lower()


def _delimiter(header: str) -> str | None:
    if "\t" in header:
        return "\t"
    if "," in header:
        return ","
    if ";" in header:
        return ";"
    return None


def _has_header(header: str) -> bool:
    first = re.split(r"[\t,; ]+", header.strip())[0]
    try:
        float(first)
    except ValueError:
        return True
    return False


def looks_like(header: str) -> bool:
    """Whether a header line names the positions and displacements of a field table."""
    if not header or not _has_header(header):
        return False
    delimiter = _delimiter(header)
    names = {_parse_name(c)[0] for c in (header.split(delimiter) if delimiter else header.split())}
    keys = ("z", "y", "x", "uz", "uy", "ux")
    return all(any(alias in names for alias in _ALIASES[key]) for key in keys)


def _scale(unit: str, voxel_size, axis: int, name: str) -> float:
    if unit in VOXEL_UNITS:
        return 1.0
    if unit not in UNITS_MM:
        raise ValueError(f"column {name!r}: unknown unit {unit!r} (use voxel, mm, um, nm or m)")
    if voxel_size is None:
        raise ValueError(
            f"column {name!r} is in {unit}: give the voxel size (mm per voxel) to convert to voxels"
        )
    size = np.broadcast_to(np.asarray(voxel_size, np.float64), (3,))
    return UNITS_MM[unit] / float(size[axis])


def read(
    path: str | os.PathLike,
    xyz: bool = False,
    voxel_size=None,
    index_base: int = 0,
    offset=(0.0, 0.0, 0.0),
) -> ScatteredField:
    """Read a plain table of points and displacements (see the module docstring)."""
    header = first_line(path)
    if not header:
        raise ValueError(f"{path}: the file is empty")
    delimiter = _delimiter(header)
    if _has_header(header):
        raw = [c for c in (header.split(delimiter) if delimiter else header.split())]
        parsed = [_parse_name(c) for c in raw]
        # our export's CSV names each status and provenance in words next to its code
        numeric = [i for i, (name, _) in enumerate(parsed) if name not in _TEXT_COLUMNS]
        subset = numeric if len(numeric) < len(parsed) else None
        rows = load_numbers(path, delimiter, _skip(path), len(numeric), usecols=subset)
        parsed = [parsed[i] for i in numeric]
    else:
        rows = load_numbers(path, delimiter)
        order = ("x", "y", "z", "ux", "uy", "uz") if xyz else ("z", "y", "x", "uz", "uy", "ux")
        if rows.shape[1] < 6:
            raise ValueError(f"{path}: a table without a header needs 6 columns {order}")
        parsed = [(name, "") for name in order] + [
            (f"extra{i}", "") for i in range(rows.shape[1] - 6)
        ]
    if rows.shape[1] != len(parsed):
        raise ValueError(
            f"{path}: the header names {len(parsed)} columns, rows have {rows.shape[1]}"
        )
    names = [p[0] for p in parsed]
    found = {}
    dic = _dic_gradient_names(names)
    for key, aliases in _ALIASES.items():
        if dic and key in ("uz", "uy", "ux"):  # ux... are du/dx...: displacements are u v w
            found[key] = names.index({"uz": "w", "uy": "v", "ux": "u"}[key])
            continue
        for alias in aliases:
            if alias in names:
                found[key] = names.index(alias)
                break
    missing = [k for k in ("z", "y", "x", "uz", "uy", "ux") if k not in found]
    if missing:
        raise ValueError(
            f"{path}: missing column(s) {', '.join(missing)}; the header names "
            f"{', '.join(raw if _has_header(header) else names)} (expected z, y, x, uz, uy, ux)"
        )
    points = np.zeros((len(rows), 3))
    u = np.zeros((len(rows), 3))
    for axis, (p_key, u_key) in enumerate((("z", "uz"), ("y", "uy"), ("x", "ux"))):
        i, j = found[p_key], found[u_key]
        points[:, axis] = rows[:, i] * _scale(parsed[i][1], voxel_size, axis, names[i])
        u[:, axis] = rows[:, j] * _scale(parsed[j][1], voxel_size, axis, names[j])
    points = points - int(index_base) + np.asarray(offset, np.float64)
    n = len(rows)
    finite = np.all(np.isfinite(u), axis=1)
    if "valid" in found and "status" not in found:
        finite &= rows[:, found["valid"]] == 1
        u[~finite] = np.nan
    status = (
        rows[:, found["status"]].astype(np.uint8)
        if "status" in found
        else np.where(finite, Status.CONVERGED, Status.NOT_COMPUTED).astype(np.uint8)
    )
    provenance = (
        rows[:, found["provenance"]].astype(np.uint8)
        if "provenance" in found
        else np.where(finite, Provenance.MEASURED, Provenance.NOT_COMPUTED).astype(np.uint8)
    )
    gradient = None
    if dic:  # du_i/dX_j, i and j in (z, y, x): w, v, u along z, y, x
        gradient = np.stack(
            [np.column_stack([rows[:, names.index(c + a)] for a in "zyx"]) for c in "wvu"], 1
        )
        gradient[~finite] = np.nan
    return ScatteredField(
        points=points,
        u=u,
        gradient=gradient,
        zncc=rows[:, found["zncc"]] if "zncc" in found else np.full(n, np.nan),
        status=status,
        iterations=rows[:, found["iterations"]].astype(np.int32) if "iterations" in found else None,
        provenance=provenance,
        metadata={
            "source": {
                "format": "table",
                "path": str(path),
                "columns": names,
                "header": _has_header(header),  # False: the columns were read by position
            }
        },
    )


def _dic_gradient_names(names: list[str]) -> bool:
    """Whether the header uses the DIC names of OpenCorr's tables: displacements ``u v w``
    (along x, y, z) and gradients ``ux uy uz vx vy vz wx wy wz`` (``ux`` = du/dx, not a
    displacement)."""
    gradient = {c + a for c in "uvw" for a in "xyz"}
    return {"u", "v", "w"} <= set(names) and gradient <= set(names)


def _skip(path) -> int:
    with open(path, encoding="utf-8", errors="replace") as handle:
        for number, line in enumerate(handle):
            stripped = line.strip()
            if stripped and not stripped.startswith("#"):
                return number + 1
    return 0


def write(field, path: str | os.PathLike, xyz: bool = False, voxel_size=None) -> None:
    """Write a field (grid or points) as a table: comma-separated for ``.csv``, else tabs.

    ``voxel_size`` (mm per voxel) writes positions and displacements in mm; else in voxels.
    ``xyz`` writes ``x y z ux uy uz`` instead of ``z y x uz uy ux``.
    """
    field = as_scattered(field)
    scale = (
        np.ones(3)
        if voxel_size is None
        else np.broadcast_to(np.asarray(voxel_size, np.float64), (3,))
    )
    unit = "voxel" if voxel_size is None else "mm"
    order = [2, 1, 0] if xyz else [0, 1, 2]
    axes = "zyx"
    columns = [f"{axes[a]} [{unit}]" for a in order] + [f"u{axes[a]} [{unit}]" for a in order]
    columns += ["zncc", "status", "provenance", "iterations"]
    table = np.column_stack(
        [
            (field.points * scale)[:, order],
            (field.u * scale)[:, order],
            field.zncc.astype(np.float64),
            field.status,
            field.provenance,
            field.iterations,
        ]
    )
    delimiter = "," if str(path).lower().endswith(".csv") else "\t"
    with atomic_path(path) as temp:
        np.savetxt(
            temp,
            table,
            fmt=["%.9g"] * 7 + ["%d"] * 3,
            delimiter=delimiter,
            header=delimiter.join(columns),
            comments="",
        )
