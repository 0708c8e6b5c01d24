"""The part of a node's value its neighbourhood does not support: the error at the node scale.

The residual's error estimate (:mod:`.error_estimate`) reads a window of one grid step around a
node, over the field densified between the nodes by the cubic spline. An error confined to one
node (a bad match, an interpolated value off the trend, random errors independent from node to
node) spreads over the spline's basis function of that node, whose mean over the window is 0.51
of the node's value along each axis (0.13 in 3-D at subvolume 15, step 5): the window holds
about a third of an independent node error, and on faint texture that is below its noise. A
joint deconvolution of the windows cannot give it back: the window of half-size one step
removes almost all of the checkerboard part of the node values (the kernel ``[0.27, 0.51,
0.27]`` per axis), and its exact inverse multiplies the noise by about 78.

What the images cannot resolve, the field's own shape can: a displacement measured with
subvolumes larger than the grid step is smooth at the scale of the step, so the part of a node's
value that a smooth fit of its neighbours does not reproduce is an error of that node (or of its
neighbours), whatever the true field. Per node and component, the value is compared with the
**leave-one-out quadratic fit** of its 26 neighbours (``1, z, y, x, z², y², x², zy, zx, yx`` in
grid steps, ordinary least squares; a truncated neighbourhood at the grid's edges uses the nodes
it has): ``d = u_k - Σ_j a_j u_j``. A quadratic reproduces a band whose profile varies along one
direction of the grid (its ``x²`` coefficient is fitted from the other rows) and an affine or
quadratic true field exactly. For errors independent from node to node with variance ``σ²``,
``E|d|² = (1 + Σ a_j²) σ²`` (``Σ a_j² = 0.35`` inside the grid): :func:`node_roughness`
returns ``|d| / √(1 + Σ a_j²)``, in voxels.

It is not a measurement of the images: a true field that bends at the scale of a grid step (a
crack, a band narrower than a subvolume) also shows in it, also where the field follows the bend
(a corrected field): the error estimate takes it at most as large as its windows' steps read
along it (:func:`.error_scales.node_error_bound`). Measured in ``docs/evaluation.md``.
"""

from __future__ import annotations

import functools
import itertools

import numpy as np

#: Deviations below this many voxels count as 0 (the rounding of float32 displacements).
ROUGHNESS_FLOOR = 1e-4

#: The neighbour offsets of a node (grid steps, ``(z, y, x)``), the node itself at
#: :data:`_CENTRE`.
_OFFSETS = np.array(list(itertools.product((-1, 0, 1), repeat=3)), np.int64)
_CENTRE = 13


def _terms(offsets: np.ndarray) -> np.ndarray:
    z, y, x = (offsets[:, i].astype(np.float64) for i in range(3))
    return np.stack([np.ones(len(offsets)), z, y, x, z * z, y * y, x * x, z * y, z * x, y * x], 1)


@functools.cache
def leave_one_out_weights(mask: int) -> np.ndarray | None:
    """Weights ``a`` (27, 0 at the node and at missing neighbours) of the quadratic fit's value
    at the node from the neighbours present in ``mask`` (bit ``i`` for :data:`_OFFSETS` ``[i]``),
    or None where they cannot give it with two degrees of freedom left over."""
    use = np.array([(mask >> i) & 1 for i in range(27)], bool)
    use[_CENTRE] = False
    design = _terms(_OFFSETS[use])
    rank = np.linalg.matrix_rank(design)
    if use.sum() < rank + 2:
        return None
    weights = np.zeros(27)
    weights[use] = np.linalg.pinv(design, rcond=1e-10)[0]
    # the value at the node must be what the fit reproduces: a constant and a linear field
    if not np.isclose(weights.sum(), 1.0) or not np.allclose(weights @ _OFFSETS, 0.0, atol=1e-9):
        return None
    return weights


def node_roughness(values: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
    """Each node's deviation from the leave-one-out quadratic fit of its 3³ neighbourhood,
    scaled to read an error independent from node to node at its size (see the module).

    Parameters
    ----------
    values : ndarray, shape (nz, ny, nx, 3)
        Node displacements (voxels).
    valid : ndarray of bool, shape (nz, ny, nx), optional
        Nodes that take part (default: those with finite values).

    Returns
    -------
    ndarray, shape (nz, ny, nx), float64
        ``|d| / √(1 + Σ a²)`` in voxels; 0 where the neighbourhood is too small to fit
        (fewer than the fit's terms and two more) and where it is under
        :data:`ROUGHNESS_FLOOR`; NaN at invalid nodes.

    Raises
    ------
    ValueError
        If ``values`` is not a grid of 3-vectors or ``valid`` is not on its grid.
    """
    return deviation_size(node_deviation(values, valid))


def deviation_size(deviation: np.ndarray) -> np.ndarray:
    """:func:`node_roughness` from :func:`node_deviation`'s vectors: their norms, 0 under
    :data:`ROUGHNESS_FLOOR`, NaN at invalid nodes."""
    size = np.linalg.norm(deviation, axis=-1)
    return np.where(size < ROUGHNESS_FLOOR, 0.0, size)


def node_deviation(values: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
    """The deviation vectors ``d / √(1 + Σ a²)`` whose norms :func:`node_roughness` gives
    (voxels, shape ``(nz, ny, nx, 3)``; 0 where the neighbourhood is too small to fit, NaN at
    invalid nodes; same parameters and errors)."""
    values = np.asarray(values, dtype=np.float64)
    if values.ndim != 4 or values.shape[-1] != 3:
        raise ValueError(f"values must have shape (nz, ny, nx, 3), got {values.shape}")
    shape = values.shape[:3]
    finite = np.all(np.isfinite(values), axis=-1)
    if valid is not None and np.shape(valid) != shape:
        raise ValueError(f"valid {np.shape(valid)} is not on the grid {shape}")
    valid = finite if valid is None else np.asarray(valid, bool) & finite
    padded = np.pad(valid, 1, constant_values=False)
    filled = np.pad(np.where(valid[..., None], values, 0.0), ((1, 1), (1, 1), (1, 1), (0, 0)))
    masks = np.zeros(shape, np.int64)
    for i, (dz, dy, dx) in enumerate(_OFFSETS):
        if i != _CENTRE:
            near = padded[1 + dz : 1 + dz + shape[0], 1 + dy : 1 + dy + shape[1]]
            masks |= near[:, :, 1 + dx : 1 + dx + shape[2]].astype(np.int64) << i
    out = np.where(valid[..., None], 0.0, np.nan) * np.ones(3)
    for mask in np.unique(masks[valid]):
        weights = leave_one_out_weights(int(mask))
        if weights is None:
            continue
        where = valid & (masks == mask)
        index = np.nonzero(where)
        deviation = values[where].copy()
        for a, (dz, dy, dx) in zip(weights, _OFFSETS):
            if a != 0.0:
                deviation -= a * filled[index[0] + 1 + dz, index[1] + 1 + dy, index[2] + 1 + dx]
        out[where] = deviation / np.sqrt(1.0 + np.sum(weights * weights))
    return out
