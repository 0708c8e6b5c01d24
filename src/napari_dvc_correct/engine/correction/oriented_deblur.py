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


def _frame(normal: np.ndarray) -> np.ndarray:
    """Rows: the unit normal and two unit vectors spanning its plane."""
    normal = normal / np.linalg.norm(normal)
    helper = np.zeros(3)
    helper[int(np.argmin(np.abs(normal)))] = 1.0
    first = np.cross(normal, helper)
    first /= np.linalg.norm(first)
    return np.stack([normal, first, np.cross(normal, first)])


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
    radius = np.ceil(np.sqrt(-2.0 * np.log(MIN_WEIGHT)) * along_reach / step).astype(int)
    deblurred = u.copy()
    taken = np.zeros(grid, bool)
    for index in zip(*np.nonzero(nodes)):
        box = tuple(slice(max(i - r, 0), min(i + r + 1, n)) for i, r, n in zip(index, radius, grid))
        data = nodes[box]
        offsets = points[box][data] - points[index]
        frame = _frame(np.asarray(normals[index], np.float64))
        t, a, b = (offsets @ frame.T).T
        weight = np.exp(-0.5 * (t / across_reach) ** 2 - 0.5 * (a * a + b * b) / along_reach**2)
        keep = weight >= MIN_WEIGHT
        if int(keep.sum()) < 2 * _COLUMNS:
            continue
        t, a, b, weight = t[keep], a[keep], b[keep], weight[keep]
        design = np.stack([np.ones_like(t), t, a, b, t * t, a * a, b * b, a * b, t * a, t * b], 1)
        root = np.sqrt(weight)[:, None]
        normal_matrix = (design * root).T @ (design * root)
        # the estimate as a functional of the coefficients: value less tr(Σ_w Q)
        sigma = frame @ np.asarray(moments[index], np.float64) @ frame.T
        read = np.array(
            [1.0, 0, 0, 0, -sigma[0, 0], -sigma[1, 1], -sigma[2, 2],
             -sigma[1, 2], -sigma[0, 1], -sigma[0, 2]]
        )  # fmt: skip
        try:
            solved = np.linalg.solve(normal_matrix, read)
        except np.linalg.LinAlgError:
            continue
        if not np.all(np.isfinite(solved)) or np.linalg.cond(normal_matrix) > 1e12:
            continue
        linear = (design @ solved) * weight  # the estimate = linear · (the neighbours' values)
        if float(np.linalg.norm(linear)) > MAX_NOISE_GAIN:
            continue
        deblurred[index] = linear @ u[box][data][keep]
        taken[index] = True
    return deblurred, taken
