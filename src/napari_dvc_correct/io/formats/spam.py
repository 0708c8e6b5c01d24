"""spam TSV field files (``spam-ldic``, ``spam-pixelSearch``, ``spam-ddic``, registrations).

Conventions, read from spam's own reader and writer, ``spam/helpers/tsvio.py``
(``readCorrelationTSV``, ``writeRegistrationTSV``), spam's ``register()`` docstring (return
status) and the ``spam-pixelSearch`` script (``pixelSearchCC``):

* tab-separated, one header line of column names, ``%.7f`` numbers;
* columns ``NodeNumber Zpos Ypos Xpos Fzz Fzy Fzx Zdisp Fyz Fyy Fyx Ydisp Fxz Fxy Fxx Xdisp error
  iterations returnStatus deltaPhiNorm`` for ``spam-ldic``; ``spam-pixelSearch`` adds
  ``pixelSearchCC`` (older files: ``PSCC``); ``spam-ddic`` has ``Label`` instead of
  ``NodeNumber``;
* positions and displacements in **z, y, x** order, in pixels of the image the field was measured
  on, 0-based array indices (spam works on numpy arrays ``im[z, y, x]``; a registration is written
  at ``(shape - 1) / 2``);
* the 12 ``F..``/``..disp`` columns are the top three rows of the 4x4 operator
  ``Phi = [[F, t], [0, 1]]``: ``F`` is the *deformation* gradient ``I + du/dX`` (z, y, x), ``t``
  the displacement at the node;
* for a regular grid (``NodeNumber`` present) the rows are in C order of the node grid (z
  slowest): spam reshapes the columns to ``fieldDims`` (the counts of unique Z, Y, X positions);
* ``returnStatus``: 2 = converged (desired precision on ``deltaPhiNorm``), 1 = hit the maximum
  number of iterations, -1 = diverging, -2 = singular matrix, -3 = displacement too large; any
  value < 1 is a failure (spam uses 0 and -5 for nodes not correlated, e.g. in the background).

Mapping to :class:`.engine.fields.field.Status`: 2 → ``CONVERGED``, 1 → ``MAX_ITERATIONS``, -1 →
``DIVERGED``, -2 → ``SINGULAR``, -3 → ``OUT_OF_BOUNDS``, anything else < 1 → ``NOT_COMPUTED``.
``pixelSearchCC`` becomes the ZNCC. Written files also carry three extra columns, ``ndcZNCC
ndcStatus ndcProvenance`` (our ZNCC, status and provenance codes), which spam's reader ignores
(it reads columns by name) and ours uses to give back exactly what was written.
"""

from __future__ import annotations

import os

import numpy as np

from ...engine.fields.field import Provenance, Status
from ...engine.fields.scattered import ScatteredField
from ..atomic import atomic_path
from ._common import as_scattered, column, read_named_table

COLUMNS = (
    "NodeNumber Zpos Ypos Xpos Fzz Fzy Fzx Zdisp Fyz Fyy Fyx Ydisp Fxz Fxy Fxx Xdisp "
    "error iterations returnStatus deltaPhiNorm"
).split()
EXTRA = ("ndcZNCC", "ndcStatus", "ndcProvenance")

_FROM_SPAM = {
    2: Status.CONVERGED,
    1: Status.MAX_ITERATIONS,
    -1: Status.DIVERGED,
    -2: Status.SINGULAR,
    -3: Status.OUT_OF_BOUNDS,
}
_TO_SPAM = {
    Status.CONVERGED: 2,
    Status.MAX_ITERATIONS: 1,
    Status.DIVERGED: -1,
    Status.SINGULAR: -2,
    Status.OUT_OF_BOUNDS: -3,
}


def looks_like(header: str) -> bool:
    """Whether a header line is a spam correlation TSV's."""
    names = header.split("\t")
    return "Zpos" in names and ("Zdisp" in names or "F14" in names)


def status_from_spam(codes: np.ndarray) -> np.ndarray:
    codes = np.rint(np.asarray(codes, dtype=np.float64)).astype(np.int64)
    out = np.full(codes.shape, int(Status.NOT_COMPUTED), np.uint8)
    for spam_code, status in _FROM_SPAM.items():
        out[codes == spam_code] = int(status)
    return out


def status_to_spam(status: np.ndarray) -> np.ndarray:
    status = np.asarray(status)
    out = np.zeros(status.shape, np.int64)  # < 1: failed / not correlated
    for ours, spam_code in _TO_SPAM.items():
        out[status == int(ours)] = spam_code
    return out


def read(path: str | os.PathLike, bin_ratio: float = 1.0) -> ScatteredField:
    """Read a spam correlation TSV as points, in the file's row order.

    Parameters
    ----------
    path : path
    bin_ratio : float
        spam's ``fieldBinRatio``: the field was measured on images binned by this factor;
        positions and displacements are multiplied by it (gradients are unchanged).

    Returns
    -------
    ScatteredField
        ``(z, y, x)`` positions and displacements in voxels of the full-resolution image; the
        displacement gradient ``F - I`` when the ``F..`` columns are there.
    """
    names, rows = read_named_table(path, "\t")
    if not looks_like("\t".join(names)):
        raise ValueError(f"{path}: not a spam TSV (no Zpos/Zdisp columns): {' '.join(names)}")
    points = np.column_stack([column(names, rows, a + "pos") for a in "ZYX"]) * bin_ratio
    u = np.column_stack(
        [column(names, rows, a + "disp", f"F{i}4") for i, a in zip((1, 2, 3), "ZYX")]
    ) * float(bin_ratio)
    gradient = None
    if all(f"F{a}{b}" in names for a in "zyx" for b in "zyx"):
        phi = np.stack(
            [np.column_stack([column(names, rows, f"F{a}{b}") for b in "zyx"]) for a in "zyx"],
            axis=1,
        )
        gradient = phi - np.eye(3)
    n = len(rows)
    spam_status = column(names, rows, "returnStatus", "SubPixReturnStat", required=False)
    status = (
        np.full(n, int(Status.CONVERGED), np.uint8)
        if spam_status is None
        else status_from_spam(spam_status)
    )
    zncc = column(names, rows, "pixelSearchCC", "PSCC", required=False)
    zncc = np.full(n, np.nan) if zncc is None else zncc
    iterations = column(names, rows, "iterations", "SubPixIterations", required=False)
    provenance = None
    if "ndcStatus" in names:  # written by us: exact codes
        status = column(names, rows, "ndcStatus").astype(np.uint8)
        zncc = column(names, rows, "ndcZNCC")
        provenance = column(names, rows, "ndcProvenance").astype(np.uint8)
    else:
        provenance = np.where(
            np.isin(status, [Status.CONVERGED, Status.MAX_ITERATIONS]),
            int(Provenance.MEASURED),
            int(Provenance.NOT_COMPUTED),
        ).astype(np.uint8)
    metadata = {"source": {"format": "spam", "path": str(path), "columns": names}}
    if spam_status is not None:
        metadata["source"]["spam_return_status"] = {
            str(int(c)): int(k) for c, k in zip(*np.unique(spam_status, return_counts=True))
        }
    return ScatteredField(
        points=points,
        u=u,
        zncc=zncc,
        status=status,
        iterations=None if iterations is None else np.rint(iterations).astype(np.int32),
        provenance=provenance,
        gradient=gradient,
        metadata=metadata,
    )


def write(field, path: str | os.PathLike) -> None:
    """Write a field (grid or points) as a ``spam-ldic`` TSV (plus our three extra columns).

    Grid fields are written node by node in C order, as ``spam-ldic`` does. ``error`` and
    ``deltaPhiNorm`` have no counterpart here and are written as 0; a missing gradient is written
    as ``F = I``. Displacements of failed points are written as they are (NaN where unknown).
    """
    field = as_scattered(field)
    n = field.n_points
    gradient = np.zeros((n, 3, 3)) if field.gradient is None else np.nan_to_num(field.gradient)
    phi = gradient + np.eye(3)
    table = np.zeros((n, len(COLUMNS) + len(EXTRA)))
    table[:, 0] = np.arange(n)
    table[:, 1:4] = field.points
    for row in range(3):  # Fz. Zdisp | Fy. Ydisp | Fx. Xdisp
        start = 4 + 4 * row
        table[:, start : start + 3] = phi[:, row, :]
        table[:, start + 3] = field.u[:, row]
    table[:, 16] = 0.0
    table[:, 17] = field.iterations
    table[:, 18] = status_to_spam(field.status)
    table[:, 19] = 0.0
    table[:, 20] = field.zncc
    table[:, 21] = field.status
    table[:, 22] = field.provenance
    formats = ["%d"] + ["%.7f"] * 15 + ["%.7f", "%d", "%d", "%.7f"] + ["%.7f", "%d", "%d"]
    with atomic_path(path) as temp:
        np.savetxt(
            temp,
            table,
            fmt=formats,
            delimiter="\t",
            header="\t".join(COLUMNS + list(EXTRA)),
            comments="",
        )
