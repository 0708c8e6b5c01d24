"""CCPi iDVC / CCPi DVC ``.disp`` result files.

Conventions, read from iDVC's documentation, ``docs/source/results.rst`` ("Results Files"), and
its reader ``src/idvc/utils/manipulate_result_files.py`` (``extractDataFromDispResultFile``):

* tab-delimited text, one header line naming the columns, then one row per point of the point
  cloud: ``n x y z status objmin u v w`` and, when the search had 6 or 12 degrees of freedom,
  ``phi theta psi`` (subvolume rotation) and ``exx eyy ezz exy eyz exz`` (subvolume strain);
  iDVC's reader takes ``objmin`` from column 5 and the displacement from columns 6-8;
* ``n`` is the point identifier; ``x, y, z`` the point's location in the reference volume, in
  **x, y, z** order (x along the fastest image axis, i.e. the last numpy axis of ``vol[z, y, x]``),
  voxels; ``u, v, w`` the displacement along x, y, z = location in the target volume minus
  location in the reference volume, voxels;
* ``status``: 0 = successful, -1 = ``Range_Fail``, -2 = ``Convg_Fail``;
* the rotation and strain columns are not read (a strain without its rotation is not the
  displacement gradient);
* ``objmin`` is the objective function at the end of the search, one of ``sad, ssd, zssd,
  nssd, znssd`` (``obj_function`` in the dvc control file, ``ccpi/dvc/apps/dvc_config_template.txt``);
  we assume ``znssd`` by default, for which ``znssd = 2 (1 - ZNCC)``; ``objective="none"`` keeps
  the ZNCC unknown for the others. Positions and displacements are in voxels (``disp_max`` and
  ``rigid_trans`` are "in voxels" there too).

Point positions: iDVC's regular point cloud (``cilRegularPointCloudToPolyData`` in
``src/idvc/pointcloud_conversion.py``) puts points at ``n * point_spacing * image_spacing`` from 0
along VTK's x, y, z (the image origin is not added), looping x slowest and z fastest. With the
usual image spacing of 1 these are 0-based voxel indices, which is what we assume; a run on an
image with another spacing has positions in those units (divide by the spacing first). Rows may
come in any order: a regular cloud is recognised as a grid whatever the order.

Mapping of status: 0 → ``CONVERGED``, -1 → ``OUT_OF_BOUNDS``, -2 → ``DIVERGED``, other → ``NOT_COMPUTED``;
written back: ``CONVERGED``/``MAX_ITERATIONS`` → 0, ``OUT_OF_BOUNDS`` → -1, any other → -2.

**Degenerate rows** (:func:`degenerate_rows`): CCPi ``dvc`` can report ``status 0`` with an
objective of exactly 0 at a whole-voxel displacement (the search's start, ``rigid_trans``) for
points whose subvolume it could not read (points at the volume's edge with a large
``disp_max``; ``../shared/data/formats`` README, ``snow48_edge``: 4 rows 0.4–1.3 voxel off).
A perfect match of real scans is not a measurement: where the file's other successful rows
show a non-zero objective, such rows are read as ``DIVERGED`` (failed; counted in
``metadata["source"]["degenerate_rows"]``), so cleaning replaces them and the evaluation does
not count them as measured.
"""

from __future__ import annotations

import os

import numpy as np

from ...engine.fields.field import Provenance, Status
from ...engine.fields.scattered import ScatteredField
from ..atomic import atomic_path
from ._common import as_scattered, column, flip_vectors, load_numbers, read_named_table

COLUMNS = ("n", "x", "y", "z", "status", "objmin", "u", "v", "w")
OBJECTIVES = ("znssd", "none")


def looks_like(header: str) -> bool:
    names = header.split()
    return names[:6] == ["n", "x", "y", "z", "status", "objmin"]


#: An objective at or below this is "exactly 0" (a row's ``objmin`` is printed to ~1e-7 at best;
#: the degenerate rows of the formats README hold 0 and 2e-15).
ZERO_OBJECTIVE = 1e-12


def degenerate_rows(codes, objmin, u_xyz) -> np.ndarray:
    """Rows (N,) that report success (``codes == 0``) with an objective of exactly 0 at a
    whole-voxel displacement, in a file whose other successful rows have a non-zero median
    objective (real scans: noise and interpolation leave some): searches that read no data."""
    success = np.asarray(codes) == 0
    objmin = np.asarray(objmin, np.float64)
    u_xyz = np.asarray(u_xyz, np.float64)
    whole = np.all(np.abs(u_xyz - np.rint(u_xyz)) < 1e-9, axis=1)
    zero = success & (np.abs(objmin) <= ZERO_OBJECTIVE) & whole
    others = np.abs(objmin[success & ~zero])
    others = others[np.isfinite(others)]
    if others.size == 0 or not np.median(others) > ZERO_OBJECTIVE:
        return np.zeros(len(objmin), bool)  # a noise-free pair: a zero objective can be true
    return zero


def read(path: str | os.PathLike, objective: str = "znssd") -> ScatteredField:
    """Read an iDVC ``.disp`` file as points, in row order.

    ``objective="znssd"`` turns ``objmin`` into a ZNCC (``1 - objmin / 2``); ``"none"`` keeps ZNCC
    unknown (for runs with another objective). ``objmin`` is kept in ``metadata``.
    """
    if objective not in OBJECTIVES:
        raise ValueError(f"objective must be one of {OBJECTIVES}, got {objective!r}")
    names, rows = read_named_table(path, None)
    if not looks_like(" ".join(names)):
        # files without a header: the documented column order
        rows = load_numbers(path, None)
        names = list(COLUMNS) + [f"c{i}" for i in range(len(COLUMNS), rows.shape[1])]
    points_xyz = np.column_stack([column(names, rows, a) for a in "xyz"])
    u_xyz = np.column_stack([column(names, rows, a) for a in "uvw"])
    codes = np.rint(column(names, rows, "status")).astype(np.int64)
    status = np.full(len(rows), int(Status.NOT_COMPUTED), np.uint8)
    status[codes == 0] = int(Status.CONVERGED)
    status[codes == -1] = int(Status.OUT_OF_BOUNDS)
    status[codes == -2] = int(Status.DIVERGED)
    objmin = column(names, rows, "objmin")
    degenerate = degenerate_rows(codes, objmin, u_xyz)
    status[degenerate] = int(Status.DIVERGED)
    codes = np.where(degenerate, -2, codes)
    zncc = 1.0 - objmin / 2.0 if objective == "znssd" else np.full(len(rows), np.nan)
    zncc = np.where(codes == 0, zncc, np.nan)
    provenance = np.where(codes == 0, int(Provenance.MEASURED), int(Provenance.NOT_COMPUTED))
    return ScatteredField(
        points=flip_vectors(points_xyz),
        u=flip_vectors(u_xyz),
        zncc=zncc,
        status=status,
        provenance=provenance,
        metadata={
            "source": {
                "format": "idvc",
                "path": str(path),
                "objective": objective,
                "point_ids": column(names, rows, "n").astype(int).tolist(),
                "objmin": objmin.tolist(),
                "degenerate_rows": int(degenerate.sum()),
            }
        },
    )


def read_roi(path: str | os.PathLike) -> np.ndarray:
    """A CCPi ``dvc`` point cloud ``.roi``: the points ``(N, 3)`` in z, y, x (voxels, 0-based).

    Rows ``n x y z`` (tab-separated, no header; ``n`` the label, x along the image's fastest
    axis; non-integer positions allowed: ``Core/InputRead.cpp``), or ``x y z``.

    Raises
    ------
    ValueError
        Naming the file: not numbers, no rows, or rows of another width.
    """
    rows = load_numbers(path, None)
    if len(rows) == 0 or rows.shape[1] not in (3, 4):
        raise ValueError(
            f"{path}: a .roi point cloud has rows 'n x y z' (or 'x y z'), got "
            f"{rows.shape[1] if len(rows) else 0} columns"
        )
    points = flip_vectors(rows[:, -3:])
    if not np.all(np.isfinite(points)):
        raise ValueError(f"{path}: a point has an empty or non-finite coordinate")
    return points


def write(field, path: str | os.PathLike, point_ids=None) -> None:
    """Write a field (grid or points) as an iDVC ``.disp`` file (``znssd`` objmin).

    ``point_ids`` (N,) are the labels ``n`` of the rows (default 1..N), e.g. those of the
    ``.roi`` cloud the points came from. Points without a ZNCC get ``objmin`` NaN.
    """
    field = as_scattered(field)
    n = field.n_points
    ids = np.arange(1, n + 1) if point_ids is None else np.asarray(point_ids, np.int64)
    if ids.shape != (n,):
        raise ValueError(f"point_ids must hold one label per point ({n}), got {ids.shape}")
    codes = np.full(n, -2, np.int64)
    codes[np.isin(field.status, [Status.CONVERGED, Status.MAX_ITERATIONS])] = 0
    codes[field.status == int(Status.OUT_OF_BOUNDS)] = -1
    table = np.column_stack(
        [
            ids,
            flip_vectors(field.points),
            codes,
            2.0 * (1.0 - field.zncc.astype(np.float64)),
            flip_vectors(field.u),
        ]
    )
    with atomic_path(path) as temp:
        np.savetxt(
            temp,
            table,
            fmt=["%d", "%.9g", "%.9g", "%.9g", "%d", "%.9g", "%.9g", "%.9g", "%.9g"],
            delimiter="\t",
            header="\t".join(COLUMNS),
            comments="",
        )
