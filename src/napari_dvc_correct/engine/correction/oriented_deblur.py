"""The window's blur taken out of oriented matches, from the node field's own local quadratic.

A first-order match under a window ``w`` reads, to second order, the window's weighted mean of
the field rather than its value at the node: ``M = u + tr(Σ_w H)/2``, with ``Σ_w`` the window's
second-moment tensor (``Σ w ξξᵀ / Σ w``, voxel²) and ``H`` the field's Hessian at the node. An
oriented window (:mod:`.oriented`) is narrow across the field's plane and wide along it, so
``Σ_w`` is small across and large along: the blur is the band's curvature across the plane
times a few voxel², plus the slow bending along it times some 50–100 voxel².

Here the node field of the oriented matches is fitted, around every node, by a quadratic in the
node's own frame ``(t, e₁, e₂)`` (``t`` along the plane's normal), weighted by a Gaussian narrow
across the plane (only the next layer of nodes counts) and wide along it (the in-plane average
that lowers the matching noise); the estimate at the node is the fit's value less
``tr(Σ_w Q)`` (``Q`` the fit's quadratic form, ``H = 2Q``). Where the fit cannot hold a
quadratic, or would carry more noise than the node's own match, the node keeps its match. See
``docs/method.md`` (the heavy-noise narrow band).
"""

from __future__ import annotations

import numpy as np
from numba import get_num_threads, njit, prange

#: Reach of the local quadratic across the plane (Gaussian std, in grid steps): the next layer of
#: nodes across, no further (the band's curvature changes sign within a few voxels).
ACROSS_REACH = 0.5

#: Reach of the local quadratic along the plane, in units of the oriented window's own standard
#: deviation along it: the in-plane average over about two windows' widths.
ALONG_REACH = 2.0

#: Neighbours whose weight falls below this are left out of a node's fit.
MIN_WEIGHT = 1e-3

#: A node keeps its match where the deblurred value's noise gain (``‖L‖₂``, the norm of the
#: linear map from the matched values to the estimate, against 1 for the match itself) exceeds
#: this: an estimate read mostly from an extrapolated quadratic (a node with no layer across on
#: one side) is noisier than the blur it removes.
MAX_NOISE_GAIN = 1.0

#: Columns of the local quadratic: 1, t, a, b, t², a², b², ab, ta, tb.
_COLUMNS = 10


def window_moments(weights: np.ndarray) -> np.ndarray:
    """Second moments ``Σ w ξξᵀ / Σ w`` (voxel², axes z, y, x) of a cubic box of weights about
    its centre.

    Parameters
    ----------
    weights : ndarray, shape (n, n, n), n odd
        Non-negative weights, not all zero.
    """
    weights = np.asarray(weights, np.float64)
    if weights.ndim != 3 or len(set(weights.shape)) != 1 or weights.shape[0] % 2 != 1:
        raise ValueError(f"the weights must be an odd cubic box, got shape {weights.shape}")
    total = float(weights.sum())
    if not np.isfinite(total) or total <= 0 or np.any(weights < 0):
        raise ValueError("the weights must be finite, non-negative and not all zero")
    half = weights.shape[0] // 2
    r = np.arange(-half, half + 1, dtype=np.float64)
    axes = np.meshgrid(r, r, r, indexing="ij")
    moments = np.empty((3, 3))
    for a in range(3):
        for b in range(a, 3):
            moments[a, b] = moments[b, a] = float(np.sum(weights * axes[a] * axes[b])) / total
    return moments


def deblur_across(
    u: np.ndarray,
    points: np.ndarray,
    nodes: np.ndarray,
    normals: np.ndarray,
    moments: np.ndarray,
    step,
    along: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Oriented matches less their window's blur, from the local quadratic of the node field.

    Parameters
    ----------
    u : ndarray, shape (nz, ny, nx, 3)
        The matched displacements (voxels); only ``nodes`` are read.
    points : ndarray, shape (nz, ny, nx, 3)
        The nodes' positions (voxels, z, y, x).
    nodes : ndarray of bool, shape (nz, ny, nx)
        The nodes holding an oriented match: the data of every fit and the nodes deblurred.
    normals : ndarray, shape (nz, ny, nx, 3)
        The plane's normal per node (any length > 0 at ``nodes``).
    moments : ndarray, shape (nz, ny, nx, 3, 3)
        The second-moment tensor (voxel², z, y, x) of the window each node was matched with
        (:func:`window_moments`).
    step : sequence of 3 floats
        The grid step (voxels).
    along : float
        The oriented window's standard deviation along the plane (voxels); the fit reaches
        :data:`ALONG_REACH` times as far.

    Returns
    -------
    deblurred : ndarray, shape (nz, ny, nx, 3)
        ``u`` with the deblurred estimate at the nodes where it was taken.
    taken : ndarray of bool, shape (nz, ny, nx)
        Those nodes (the others keep their match: too few neighbours for a quadratic, or a noise
        gain above :data:`MAX_NOISE_GAIN`).
    """
    u = np.asarray(u, np.float64)
    nodes = np.asarray(nodes, bool)
    grid = u.shape[:3]
    if u.ndim != 4 or u.shape[-1] != 3:
        raise ValueError(f"u must have shape (nz, ny, nx, 3), got {u.shape}")
    for name, array, tail in (
        ("points", points, (3,)), ("normals", normals, (3,)), ("moments", moments, (3, 3)),
    ):  # fmt: skip
        if np.shape(array) != grid + tail:
            raise ValueError(f"{name} must have shape {grid + tail}, got {np.shape(array)}")
    if nodes.shape != grid:
        raise ValueError(f"nodes must have the grid's shape {grid}, got {nodes.shape}")
    step = np.broadcast_to(np.asarray(step, np.float64), (3,))
    if not (np.all(step > 0) and np.isfinite(along) and along > 0):
        raise ValueError(
            f"the grid step and the window's along std must be > 0, got {step}, {along}"
        )
    nodes = nodes & np.all(np.isfinite(u), axis=-1)
    across_reach = ACROSS_REACH * float(step.min())
    along_reach = ALONG_REACH * float(along)
    # neighbours beyond sqrt(-2 ln MIN_WEIGHT) stds along the plane weigh nothing
    radius = np.ceil(np.sqrt(-2.0 * np.log(MIN_WEIGHT)) * along_reach / step).astype(np.int64)
    deblurred = u.copy()
    taken = np.zeros(grid, bool)
    where = np.argwhere(nodes).astype(np.int64)
    if len(where):
        _deblur_nodes(
            u, np.ascontiguousarray(points, np.float64), nodes,
            np.ascontiguousarray(normals, np.float64), np.ascontiguousarray(moments, np.float64),
            where, radius, across_reach, along_reach, deblurred, taken,
            min(len(where), 4 * get_num_threads()),
        )  # fmt: skip
    return deblurred, taken


@njit(nogil=True, cache=True)
def _frame(normal):
    """Rows the unit normal and two unit vectors of its plane."""
    frame = np.empty((3, 3))
    length = np.sqrt(normal[0] * normal[0] + normal[1] * normal[1] + normal[2] * normal[2])
    for k in range(3):
        frame[0, k] = normal[k] / length
    smallest = 0  # the axis of the smallest component (the first of equals, as np.argmin)
    for k in range(1, 3):
        if abs(frame[0, k]) < abs(frame[0, smallest]):
            smallest = k
    helper = np.zeros(3)
    helper[smallest] = 1.0
    n = frame[0]
    first = np.array(
        [n[1] * helper[2] - n[2] * helper[1], n[2] * helper[0] - n[0] * helper[2],
         n[0] * helper[1] - n[1] * helper[0]]
    )  # fmt: skip
    length = np.sqrt(first[0] * first[0] + first[1] * first[1] + first[2] * first[2])
    for k in range(3):
        frame[1, k] = first[k] / length
    f = frame[1]
    frame[2, 0] = n[1] * f[2] - n[2] * f[1]
    frame[2, 1] = n[2] * f[0] - n[0] * f[2]
    frame[2, 2] = n[0] * f[1] - n[1] * f[0]
    return frame


@njit(nogil=True, cache=True, parallel=True)
def _deblur_nodes(
    u, points, nodes, normals, moments, where, radius, across_reach, along_reach, deblurred, taken,
    chunks,
):  # fmt: skip
    """:func:`deblur_across`'s per-node work: writes ``deblurred`` and ``taken`` at ``where``'s
    nodes (shape (K, 3), grid indices) where the fit holds (see there for the fall-backs), in
    ``chunks`` runs of nodes (each with its own scratch)."""
    grid = nodes.shape
    capacity = (2 * radius[0] + 1) * (2 * radius[1] + 1) * (2 * radius[2] + 1)
    count = where.shape[0]
    beyond = -2.0 * np.log(0.5 * MIN_WEIGHT)
    for chunk in prange(chunks):
        # one chunk's scratch: t, a, b, weight and the three components per neighbour
        kept = np.empty((capacity, 7))
        for j in range(chunk * count // chunks, (chunk + 1) * count // chunks):
            i0, i1, i2 = where[j, 0], where[j, 1], where[j, 2]
            frame = _frame(normals[i0, i1, i2])
            centre = points[i0, i1, i2]
            m = 0
            for z in range(max(i0 - radius[0], 0), min(i0 + radius[0] + 1, grid[0])):
                for y in range(max(i1 - radius[1], 0), min(i1 + radius[1] + 1, grid[1])):
                    for x in range(max(i2 - radius[2], 0), min(i2 + radius[2] + 1, grid[2])):
                        if not nodes[z, y, x]:
                            continue
                        o0 = points[z, y, x, 0] - centre[0]
                        o1 = points[z, y, x, 1] - centre[1]
                        o2 = points[z, y, x, 2] - centre[2]
                        t = o0 * frame[0, 0] + o1 * frame[0, 1] + o2 * frame[0, 2]
                        if (t / across_reach) ** 2 > beyond:
                            continue  # its weight is below MIN_WEIGHT / 2 whatever a and b
                        a = o0 * frame[1, 0] + o1 * frame[1, 1] + o2 * frame[1, 2]
                        b = o0 * frame[2, 0] + o1 * frame[2, 1] + o2 * frame[2, 2]
                        weight = np.exp(
                            -0.5 * (t / across_reach) ** 2 - 0.5 * (a * a + b * b) / along_reach**2
                        )
                        if not weight >= MIN_WEIGHT:
                            continue
                        kept[m, 0], kept[m, 1], kept[m, 2], kept[m, 3] = t, a, b, weight
                        for c in range(3):
                            kept[m, 4 + c] = u[z, y, x, c]
                        m += 1
            if m < 2 * _COLUMNS:
                continue
            normal_matrix = np.zeros((_COLUMNS, _COLUMNS))
            row = np.empty(_COLUMNS)
            for n in range(m):
                _design_row(kept[n, 0], kept[n, 1], kept[n, 2], row)
                root = np.sqrt(kept[n, 3])
                for c in range(_COLUMNS):
                    row[c] *= root
                for c in range(_COLUMNS):
                    for d in range(c, _COLUMNS):
                        normal_matrix[c, d] += row[c] * row[d]
            for c in range(_COLUMNS):
                for d in range(c):
                    normal_matrix[c, d] = normal_matrix[d, c]
            if not np.all(np.isfinite(normal_matrix)):
                continue
            singular = np.linalg.svd(normal_matrix)[1]
            if not singular[-1] > 0.0 or singular[0] / singular[-1] > 1e12:
                continue
            # the estimate as a functional of the coefficients: value less tr(Σ_w Q)
            sigma = frame @ moments[i0, i1, i2] @ frame.T
            read = np.array(
                [1.0, 0.0, 0.0, 0.0, -sigma[0, 0], -sigma[1, 1], -sigma[2, 2],
                 -sigma[1, 2], -sigma[0, 1], -sigma[0, 2]]
            )  # fmt: skip
            solved = np.linalg.solve(normal_matrix, read)
            if not np.all(np.isfinite(solved)):
                continue
            # the estimate = linear · (the neighbours' values); its norm is the noise gain
            gain = 0.0
            estimate = np.zeros(3)
            for n in range(m):
                _design_row(kept[n, 0], kept[n, 1], kept[n, 2], row)
                linear = 0.0
                for c in range(_COLUMNS):
                    linear += row[c] * solved[c]
                linear *= kept[n, 3]
                gain += linear * linear
                for c in range(3):
                    estimate[c] += linear * kept[n, 4 + c]
            if np.sqrt(gain) > MAX_NOISE_GAIN:
                continue
            for c in range(3):
                deblurred[i0, i1, i2, c] = estimate[c]
            taken[i0, i1, i2] = True


@njit(nogil=True, cache=True)
def _design_row(t, a, b, row):
    """The local quadratic's columns at ``(t, a, b)``: 1, t, a, b, t², a², b², ab, ta, tb."""
    row[0], row[1], row[2], row[3] = 1.0, t, a, b
    row[4], row[5], row[6] = t * t, a * a, b * b
    row[7], row[8], row[9] = a * b, t * a, t * b
