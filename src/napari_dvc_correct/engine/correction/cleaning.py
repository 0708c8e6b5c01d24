"""Field cleaning (paper step b): find bad nodes, refill them from good neighbours.

* :func:`normalized_median_test` — the normalised median test of Westerweel & Scarano (2005),
  ``r0 = |u0 - um| / (rm + eps)`` with ``um`` the median of the neighbours and ``rm`` the median
  of their residuals ``|ui - um|``, per component; the node's residual is the largest component's.
* :func:`detect_outliers` — failed matches (any status but converged / max-iterations), low ZNCC,
  and median-test outliers, applied repeatedly so a cluster of outliers cannot shield itself.
* :func:`inpaint` — fills holes of any size on a 3-D grid with the smoothest field that agrees
  with the known nodes: it minimises the discrete thin-plate energy
  ``Σ u_zz² + u_yy² + u_xx² + 2 (u_zy² + u_zx² + u_yx²)`` over the unknown nodes (a sparse
  least-squares problem, solved directly for small holes and by conjugate gradients for large
  ones). Affine fields are reproduced exactly, also near the grid's borders; nothing is set to 0.
* :func:`smooth` — optional Gaussian smoothing "so the field roughly satisfies deformation
  compatibility" (paper, step b).
* :func:`clean` — all of the above on a :class:`DisplacementField`, recording per node where
  each value comes from (:class:`Provenance`) and what was done in ``metadata["cleaning"]``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit, prange
from scipy import ndimage

from .._numba_setup import KERNEL_OPTIONS
from ..fields.field import GOOD_STATUSES, DisplacementField, Provenance, Status
from .options import CleaningOptions

#: Unknown nodes up to which the inpainting uses a direct sparse solver.
DIRECT_SOLVE_LIMIT = 3_000

#: The same where the unknown nodes reach the grid's border (a specimen's exterior mask: a shell
#: open to the border). There the thin-plate energy holds the fill only weakly, so conjugate
#: gradients need many iterations, while the factor of a shell stays sparse: measured 3-4x
#: faster than them at 2 200-15 500 such nodes. Enclosed compact holes are the other way round
#: (the factor 1.4-1.8x slower at 4 000-8 000 nodes), hence this bound for a compact hole that
#: touches the border.
OPEN_DIRECT_SOLVE_LIMIT = 8_000


# --- normalised median test -------------------------------------------------------------------
@njit(parallel=True, **KERNEL_OPTIONS)
def _median_test_kernel(u, valid, tested, radius, epsilon, min_neighbours, out):
    nz, ny, nx, nc = u.shape
    size = (2 * radius + 1) ** 3
    for flat in prange(nz * ny * nx):
        i = flat // (ny * nx)
        j = (flat // nx) % ny
        k = flat % nx
        if not tested[i, j, k]:
            out[i, j, k] = np.nan
            continue
        values = np.empty(size)
        deviations = np.empty(size)
        worst = 0.0
        complete = True
        for c in range(nc):
            n = 0
            for a in range(max(0, i - radius), min(nz, i + radius + 1)):
                for b in range(max(0, j - radius), min(ny, j + radius + 1)):
                    for d in range(max(0, k - radius), min(nx, k + radius + 1)):
                        if (a == i and b == j and d == k) or not valid[a, b, d]:
                            continue
                        values[n] = u[a, b, d, c]
                        n += 1
            if n < min_neighbours:
                complete = False
                break
            median = np.median(values[:n])
            for m in range(n):
                deviations[m] = abs(values[m] - median)
            spread = np.median(deviations[:n])
            residual = abs(u[i, j, k, c] - median) / (spread + epsilon)
            worst = max(worst, residual)
        out[i, j, k] = worst if complete else np.nan


def _pad_for_test(u: np.ndarray, valid: np.ndarray, width: int):
    """Pad the grid by ``width`` nodes with values extrapolated linearly from the interior.

    A padded node at distance ``k`` beyond a border node is predicted from the two nodes next
    to the border one (not from the border node itself, which is the one under test), so a
    linear field is continued exactly and a border outlier cannot vouch for itself. Axes with
    fewer than 3 nodes are padded with invalid nodes.
    """
    for axis in range(3):
        n = u.shape[axis]
        if n < 3:
            low_u = np.zeros_like(np.take(u, [0] * width, axis=axis))
            high_u = low_u
            low_ok = high_ok = np.zeros_like(np.take(valid, [0] * width, axis=axis))
        else:
            distance = np.arange(width, 0, -1, dtype=np.float64) + 1.0  # far to near
            shape = [1, 1, 1, 1]
            shape[axis] = width
            distance = distance.reshape(shape)
            inner, next_inner = np.take(u, [1], axis=axis), np.take(u, [2], axis=axis)
            low_u = inner - distance * (next_inner - inner)
            inner, next_inner = np.take(u, [n - 2], axis=axis), np.take(u, [n - 3], axis=axis)
            high_u = inner - np.flip(distance, axis=axis) * (next_inner - inner)
            low_ok = np.take(valid, [1] * width, axis=axis) & np.take(valid, [2] * width, axis=axis)
            high_ok = np.take(valid, [n - 2] * width, axis=axis) & np.take(
                valid, [n - 3] * width, axis=axis
            )
        u = np.concatenate([low_u, u, high_u], axis=axis)
        valid = np.concatenate([low_ok, valid, high_ok], axis=axis)
    return np.ascontiguousarray(u), np.ascontiguousarray(valid)


def normalized_median_test(
    u: np.ndarray,
    valid: np.ndarray | None = None,
    *,
    radius: int = 1,
    epsilon: float = 0.1,
    min_neighbours: int = 3,
) -> np.ndarray:
    """Normalised median residual of every node (Westerweel & Scarano 2005).

    Beyond the grid's borders the neighbourhood is completed by linear extrapolation from the
    interior (:func:`_pad_for_test`). Without that, a homogeneous strain makes the one-sided
    neighbourhoods of border nodes look biased (their median lies about a step's displacement
    away), and a test repeated over passes would eat the grid from its borders inwards.

    Parameters
    ----------
    u : ndarray, shape (nz, ny, nx, 3)
        Displacement on the grid, voxels.
    valid : ndarray of bool, shape (nz, ny, nx), optional
        Nodes that take part (as tested nodes and as neighbours); default: finite nodes.
    radius : int
        Neighbourhood half-width in nodes: the ``(2 radius + 1)³ - 1`` surrounding nodes.
    epsilon : float
        Minimum normalisation level in voxels (the expected matching noise), > 0.
    min_neighbours : int
        Nodes with fewer valid neighbours are not tested.

    Returns
    -------
    ndarray, shape (nz, ny, nx), float64
        ``max over components of |u0 - um| / (rm + epsilon)``; NaN for invalid or untested
        nodes. The usual outlier threshold is 2.
    """
    u = np.ascontiguousarray(u, dtype=np.float64)
    if u.ndim != 4:
        raise ValueError(f"u must have shape (nz, ny, nx, C), got {u.shape}")
    finite = np.all(np.isfinite(u), axis=-1)
    valid = finite if valid is None else (np.asarray(valid, dtype=bool) & finite)
    if valid.shape != u.shape[:3]:
        raise ValueError(f"valid must have the grid shape {u.shape[:3]}, got {valid.shape}")
    if int(radius) < 1:
        raise ValueError(f"radius must be >= 1 node, got {radius!r}")
    if not epsilon > 0:
        raise ValueError(f"epsilon must be > 0 voxels, got {epsilon!r}")
    r = int(radius)
    padded, padded_valid = _pad_for_test(np.where(valid[..., None], u, 0.0), valid, r)
    tested = np.zeros(padded_valid.shape, bool)
    inner = tuple(slice(r, r + n) for n in u.shape[:3])
    tested[inner] = valid
    out = np.empty(padded_valid.shape, np.float64)
    _median_test_kernel(padded, padded_valid, tested, r, float(epsilon), int(min_neighbours), out)
    return out[inner]


@dataclass
class OutlierReport:
    """Which nodes :func:`detect_outliers` rejects, and why (boolean grids (nz, ny, nx)).

    Attributes
    ----------
    failed : bool grid
        The match failed (status not converged / max-iterations) or the value is not finite.
    low_zncc : bool grid
        A good status but a ZNCC below the threshold.
    median : bool grid
        Rejected by the normalised median test.
    masked : bool grid
        Outside the mask (status or provenance ``MASKED``); never tested nor counted as bad.
    residual : float grid
        Normalised median residual of the last test pass (NaN where untested).
    """

    failed: np.ndarray
    low_zncc: np.ndarray
    median: np.ndarray
    masked: np.ndarray
    residual: np.ndarray

    @property
    def rejected(self) -> np.ndarray:
        """Nodes to replace: failed, low ZNCC or median outliers (not masked ones)."""
        return (self.failed | self.low_zncc | self.median) & ~self.masked

    def counts(self) -> dict[str, int]:
        return {
            "failed": int((self.failed & ~self.masked).sum()),
            "low_zncc": int(self.low_zncc.sum()),
            "median_test": int(self.median.sum()),
            "masked": int(self.masked.sum()),
            "rejected": int(self.rejected.sum()),
        }


def masked_nodes(field: DisplacementField) -> np.ndarray:
    """Nodes outside the mask (status or provenance ``MASKED``), bool (nz, ny, nx)."""
    return (field.status == Status.MASKED) | (field.provenance == Provenance.MASKED)


def _options(options: CleaningOptions | None, overrides: dict) -> CleaningOptions:
    options = CleaningOptions() if options is None else options
    if "min_zncc" in overrides:  # the keyword's older name: the absolute floor
        overrides = dict(overrides)
        overrides["zncc_floor"] = overrides.pop("min_zncc")
    return options.replace(**overrides) if overrides else options


def detect_outliers(
    field: DisplacementField, options: CleaningOptions | None = None, **overrides
) -> OutlierReport:
    """Bad nodes of ``field``: failed matches, low ZNCC, and normalised-median-test outliers.

    Parameters
    ----------
    field : DisplacementField
    options : CleaningOptions, optional
        The test's settings (defaults when None); keyword ``overrides`` (``threshold=3``...)
        change single ones.

    Returns
    -------
    OutlierReport
    """
    options = _options(options, overrides)
    threshold, radius, epsilon = options.threshold, options.radius, options.epsilon
    zncc_floor, passes = options.zncc_floor, options.passes
    masked = masked_nodes(field)
    finite = np.all(np.isfinite(field.u), axis=-1)
    good_status = np.isin(field.status, [int(s) for s in GOOD_STATUSES])
    filled = np.isin(field.provenance, [Provenance.REPLACED, Provenance.CORRECTED])
    failed = ~(good_status | filled) | ~finite
    low_zncc = np.zeros(field.shape, bool)
    if zncc_floor is not None:
        low_zncc = ~failed & ~masked & ~(field.zncc >= float(zncc_floor))
    median = np.zeros(field.shape, bool)
    residual = np.full(field.shape, np.nan)
    for _ in range(int(passes)):
        usable = ~(failed | low_zncc | median | masked)
        residual = normalized_median_test(field.u, usable, radius=radius, epsilon=epsilon)
        new = usable & (residual > threshold)
        if not new.any():
            break
        median |= new
    return OutlierReport(failed, low_zncc, median, masked, residual)


# --- inpainting -------------------------------------------------------------------------------
def direct_solve_limit(unknown: np.ndarray) -> int:
    """Most unknown nodes the inpainting solves directly: :data:`OPEN_DIRECT_SOLVE_LIMIT` where
    ``unknown`` (bool, (nz, ny, nx)) reaches a face of the grid, else :data:`DIRECT_SOLVE_LIMIT`."""
    faces = (np.s_[0], np.s_[-1], np.s_[:, 0], np.s_[:, -1], np.s_[..., 0], np.s_[..., -1])
    if any(unknown[face].any() for face in faces):
        return OPEN_DIRECT_SOLVE_LIMIT
    return DIRECT_SOLVE_LIMIT


def _stencils(step) -> list[tuple[np.ndarray, np.ndarray]]:
    """Offsets (m, 3) and weights (m,) of the discrete thin-plate energy terms."""
    step = np.asarray(step, dtype=np.float64)
    stencils = []
    for a in range(3):
        offsets = np.zeros((3, 3), np.intp)
        offsets[:, a] = (0, 1, 2)
        stencils.append((offsets, np.array([1.0, -2.0, 1.0]) / step[a] ** 2))
    for a in range(3):
        for b in range(a + 1, 3):
            offsets = np.zeros((4, 3), np.intp)
            offsets[1, a] = 1
            offsets[2, b] = 1
            offsets[3, a] = offsets[3, b] = 1
            weights = np.sqrt(2.0) * np.array([1.0, -1.0, -1.0, 1.0]) / (step[a] * step[b])
            stencils.append((offsets, weights))
    return stencils


def _thin_plate_system(values, unknown, step):
    """Sparse ``D_U`` (rows × unknowns) and right-hand side ``-D_K k`` (rows × C)."""
    from scipy import sparse  # here: scipy.sparse is slow to import (CLI start-up)

    shape = unknown.shape
    number = np.full(shape, -1, np.intp)
    number[unknown] = np.arange(int(unknown.sum()))
    known_values = np.where(unknown[..., None], 0.0, values)
    rows, cols, data, rhs = [], [], [], []
    n_rows = 0
    for offsets, weights in _stencils(step):
        extent = offsets.max(axis=0)
        anchors = tuple(n - e for n, e in zip(shape, extent))
        if min(anchors) < 1:
            continue
        windows = [tuple(slice(o[a], o[a] + anchors[a]) for a in range(3)) for o in offsets]
        needed = np.zeros(anchors, bool)
        for window in windows:
            needed |= unknown[window]
        count = int(needed.sum())
        if count == 0:
            continue
        row_ids = n_rows + np.arange(count)
        b = np.zeros((count, values.shape[-1]))
        for window, weight in zip(windows, weights):
            ids = number[window][needed]
            is_unknown = ids >= 0
            rows.append(row_ids[is_unknown])
            cols.append(ids[is_unknown])
            data.append(np.full(int(is_unknown.sum()), weight))
            b -= weight * known_values[window][needed]
        rhs.append(b)
        n_rows += count
    matrix = sparse.csr_matrix(
        (np.concatenate(data), (np.concatenate(rows), np.concatenate(cols))),
        shape=(n_rows, int(unknown.sum())),
    )
    return matrix, np.concatenate(rhs, axis=0)


def jacobi_cg(normal, rhs: np.ndarray, start: np.ndarray, rtol: float, max_iterations: int):
    """Conjugate gradients with the Jacobi preconditioner on every column of ``rhs`` at once.

    Each column follows exactly the iteration of ``scipy.sparse.linalg.cg`` (same start,
    preconditioner ``x / diag(normal)``, stop when ``‖r‖ < rtol ‖b‖``, at most
    ``max_iterations``), so each column's result is the one that function returns, to the bit
    (tested); the columns share each product with ``normal`` (one sparse product with several
    vectors instead of one per column, and one Python loop instead of one per column).

    Parameters
    ----------
    normal : scipy.sparse matrix, shape (n, n), CSC
        Symmetric positive definite.
    rhs, start : ndarray, shape (n, C) float64
        Right-hand sides and starting points.
    rtol : float
    max_iterations : int

    Returns
    -------
    ndarray, shape (n, C) float64
    """
    b = np.ascontiguousarray(np.asarray(rhs, dtype=np.float64).T)  # (C, n): rows contiguous
    out = np.array(np.asarray(start, dtype=np.float64).T, order="C")
    diagonal = normal.diagonal()
    limit = np.array([rtol * float(np.linalg.norm(row)) for row in b])
    out[limit == 0.0] = b[limit == 0.0]  # a zero right-hand side: cg returns it
    columns = np.flatnonzero(limit > 0.0)  # the columns still iterating, in rows of x, r, p
    x, b, limit = out[columns], b[columns], limit[columns]
    r = b.copy()
    moved = np.flatnonzero([row.any() for row in x])
    if moved.size:
        r[moved] = b[moved] - (normal @ x[moved].T).T
    p = None
    rho_prev = None
    for _ in range(max_iterations):
        going = np.array([not np.linalg.norm(row) < bound for row, bound in zip(r, limit)])
        if not going.all():  # columns done: keep their result, iterate on the others
            out[columns[~going]] = x[~going]
            columns, x, r, limit = columns[going], x[going], r[going], limit[going]
            if p is not None:
                p, rho_prev = p[going], rho_prev[going]
        if not columns.size:
            break
        z = r / diagonal
        rho = np.array([np.dot(row, zrow) for row, zrow in zip(r, z)])
        if p is not None:
            p *= (rho / rho_prev)[:, None]
            p += z
        else:
            p = z
        q = np.ascontiguousarray((normal @ np.ascontiguousarray(p.T)).T)  # rows contiguous, as cg's
        alpha = rho / np.array([np.dot(prow, qrow) for prow, qrow in zip(p, q)])
        x += alpha[:, None] * p
        r -= alpha[:, None] * q
        rho_prev = rho
    out[columns] = x
    return np.ascontiguousarray(out.T)


def inpaint(
    values: np.ndarray,
    known: np.ndarray,
    step=(1.0, 1.0, 1.0),
    *,
    max_iterations: int = 2000,
) -> np.ndarray:
    """Fill the unknown nodes of a grid quantity from the known ones (thin-plate inpainting).

    Parameters
    ----------
    values : ndarray, shape (nz, ny, nx) or (nz, ny, nx, C)
        Grid values; those at unknown nodes are ignored (may be NaN).
    known : ndarray of bool, shape (nz, ny, nx)
        Nodes whose values are kept.
    step : tuple of 3 floats
        Grid spacing ``(z, y, x)`` (voxels), so the energy is isotropic in space.
    max_iterations : int
        Conjugate-gradient iterations when there are too many unknown nodes for the direct
        solver (:func:`direct_solve_limit`; the start is the nearest known value, so even a
        truncated solve is a sensible fill).

    Returns
    -------
    ndarray, float64, same shape as ``values``
        Known nodes unchanged; unknown nodes minimise the discrete thin-plate energy, which
        reproduces affine fields exactly.

    Raises
    ------
    ValueError
        If no node is known.
    """
    values = np.asarray(values, dtype=np.float64)
    scalar = values.ndim == 3
    if scalar:
        values = values[..., None]
    known = np.asarray(known, dtype=bool)
    if values.ndim != 4 or known.shape != values.shape[:3]:
        raise ValueError(
            f"values must be (nz, ny, nx[, C]) and known (nz, ny, nx); got {values.shape} and "
            f"{known.shape}"
        )
    known = known & np.all(np.isfinite(values), axis=-1)
    result = values.copy()
    unknown = ~known
    if not unknown.any():
        return result[..., 0] if scalar else result
    if not known.any():
        raise ValueError("cannot inpaint: no node holds a known finite value")
    from scipy import sparse  # here: scipy.sparse is slow to import (CLI start-up)
    from scipy.sparse import linalg as sparse_linalg

    matrix, rhs = _thin_plate_system(values, unknown, step)
    normal = (matrix.T @ matrix).tocsc()
    normal_rhs = matrix.T @ rhs
    # a tiny ridge towards the known mean fixes the solution where the energy cannot (e.g.
    # holes that no stencil links to the known nodes, or degenerate grids)
    ridge = 1e-11 * float(normal.diagonal().max() if normal.nnz else 1.0)
    mean = values[known].mean(axis=0)
    normal = normal + ridge * sparse.identity(normal.shape[0], format="csc")
    normal_rhs = normal_rhs + ridge * mean
    n_unknown = normal.shape[0]
    if n_unknown <= direct_solve_limit(unknown):
        factor = sparse_linalg.splu(normal)
        solution = factor.solve(np.ascontiguousarray(normal_rhs))
    else:
        _, nearest = ndimage.distance_transform_edt(unknown, return_indices=True)
        start = values[tuple(nearest)][unknown]
        solution = jacobi_cg(normal, normal_rhs, start, 1e-10, max_iterations)
    result[unknown] = solution
    return result[..., 0] if scalar else result


# --- smoothing --------------------------------------------------------------------------------
def smooth(values: np.ndarray, sigma: float, valid: np.ndarray | None = None) -> np.ndarray:
    """Gaussian smoothing over the grid by normalised convolution (invalid nodes ignored).

    Parameters
    ----------
    values : ndarray, shape (nz, ny, nx, C)
    sigma : float
        Standard deviation in nodes (0 returns a copy).
    valid : ndarray of bool, shape (nz, ny, nx), optional
        Nodes that contribute (default: finite nodes). Invalid nodes keep their value.

    Returns
    -------
    ndarray, float64, same shape
    """
    values = np.asarray(values, dtype=np.float64)
    if sigma < 0:
        raise ValueError(f"smoothing sigma must be >= 0 nodes, got {sigma!r}")
    if sigma == 0:
        return values.copy()
    finite = np.all(np.isfinite(values), axis=-1)
    valid = finite if valid is None else (np.asarray(valid, bool) & finite)
    weight = ndimage.gaussian_filter(valid.astype(np.float64), sigma, mode="constant")
    result = values.copy()
    for c in range(values.shape[-1]):
        filled = np.where(valid, values[..., c], 0.0)
        blurred = ndimage.gaussian_filter(filled, sigma, mode="constant")
        result[..., c] = np.where(valid, blurred / np.maximum(weight, 1e-12), values[..., c])
    return result


# --- the whole step ---------------------------------------------------------------------------
def clean(
    field: DisplacementField, options: CleaningOptions | None = None, **overrides
) -> DisplacementField:
    """Replace failed and outlying nodes by thin-plate inpainting from the good ones.

    Parameters
    ----------
    field : DisplacementField
    options : CleaningOptions, optional
        The outlier test, whether masked nodes are filled and the optional smoothing (defaults
        when None); keyword ``overrides`` (``fill_masked=True``...) change single ones.

    Returns
    -------
    DisplacementField
        A new field. Replaced nodes get ``Provenance.REPLACED``; nodes that matched with a good
        status but failed the median test or the ZNCC threshold also get
        ``Status.OUTLIER_REPLACED`` (other statuses are kept, so the reason for a failed match
        stays visible). ``metadata["cleaning"]`` records the options and the counts. The
        ``uncertainty`` of replaced nodes is NaN: an inpainted value was not measured, and the
        field cannot say how far it is from the truth (its provenance says so).
    """
    options = _options(options, overrides)
    fill_masked, smoothing = options.fill_masked, options.smoothing
    report = detect_outliers(field, options)
    rejected = report.rejected
    keep = ~(rejected | report.masked)
    if not keep.any():
        raise ValueError(
            "no node of the field is usable (all failed, outlying or masked): check the "
            "correlation parameters (subvolume, search radius) before cleaning"
        )
    fill = rejected | (report.masked if fill_masked else np.zeros_like(rejected))
    result = field.copy()
    flat = None if field.gradient is None else field.gradient.reshape(*field.shape, 9)
    together = None  # u and the gradient filled in one solve where they are known at the same nodes
    if fill.any() and flat is not None:
        known_u = keep & np.all(np.isfinite(field.u), axis=-1)
        if np.array_equal(known_u, keep & np.all(np.isfinite(flat), axis=-1)):
            together = inpaint(np.concatenate([field.u, flat], axis=-1), keep, field.step)
    if fill.any():
        result.u = (
            inpaint(field.u, keep, field.step) if together is None else together[..., :3].copy()
        )
        if not fill_masked:
            result.u[report.masked] = field.u[report.masked]
    if smoothing > 0:
        result.u = smooth(result.u, smoothing, valid=keep | rejected)
    result.provenance[rejected] = Provenance.REPLACED
    if result.uncertainty is not None:
        result.uncertainty[rejected] = np.nan
    result.provenance[report.masked] = Provenance.MASKED
    good_status = np.isin(field.status, [int(s) for s in GOOD_STATUSES])
    result.status[rejected & good_status] = Status.OUTLIER_REPLACED
    if result.gradient is not None and fill.any():
        gradient = (
            inpaint(flat, keep & np.all(np.isfinite(flat), axis=-1), field.step)
            if together is None
            else together[..., 3:].copy()
        )
        if not fill_masked:
            gradient[report.masked] = flat[report.masked]
        result.gradient = gradient.reshape(*field.shape, 3, 3)
    result.metadata["cleaning"] = {**options.as_dict(), **report.counts()}
    return result
