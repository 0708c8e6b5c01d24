"""Strain from a displacement field on its POI grid: gradients, tensors, equivalent strain.

Everything here works on the grid (no densification) and returns grid arrays, so a strain map
overlays the volume in napari with the field's ``scale = step`` and ``translate = origin``.

Conventions: axis order ``(z, y, x)``; the displacement gradient ``H[..., i, j]`` is
``du_i / dX_j`` with ``i, j`` in (z, y, x) order, dimensionless (voxels per voxel); tensors are
``(..., 3, 3)`` in the same order. Nodes where the field is not usable
(:attr:`DisplacementField.valid` is False) get NaN, and they never contribute to the gradient at
their neighbours.

Two gradient estimators (paper: "strain from the displacement gradient"):

``"central"``
    Central differences ``(u[i+1] - u[i-1]) / (2 step)`` along each axis, falling back to a
    one-sided difference where one neighbour is missing (grid edge or invalid node), NaN where
    both are missing. Exact for an affine field; the noisiest choice for measured fields.
``"least-squares"``
    A local least-squares fit of ``u = a + H (X - X0)`` over the valid nodes of a cubic strain
    window of ``window`` nodes per edge centred on the node (truncated at the grid edges). Exact
    for an affine field, and it smooths measurement noise the way commercial DVC codes' "strain
    window" does. At least 4 non-coplanar valid nodes are needed, else NaN.
``"shape-function"``
    The gradient the matcher's first-order shape function measured (``field.gradient``).
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from .._numba_setup import KERNEL_OPTIONS
from ..fields.field import DisplacementField
from .options import GRADIENT_METHODS, STRAIN_MEASURES


# --- displacement gradient --------------------------------------------------------------------
def displacement_gradient(
    field: DisplacementField, method: str = "central", window: int = 5
) -> np.ndarray:
    """Displacement gradient ``du_i/dX_j`` at every node of the field's grid.

    Parameters
    ----------
    field : DisplacementField
        Field on a grid of shape ``(nz, ny, nx)``, displacement in voxels; the (possibly
        anisotropic) ``field.step`` gives the node spacing in voxels.
    method : {"central", "least-squares", "shape-function"}
        Gradient estimator (see the module docstring).
    window : int
        Odd strain-window edge in nodes for ``"least-squares"`` (>= 3); ignored otherwise.

    Returns
    -------
    ndarray, shape (nz, ny, nx, 3, 3), float64
        ``H[..., i, j] = du_i/dX_j``, (z, y, x) order, dimensionless. NaN at invalid nodes and
        where the estimator has too few valid neighbours (e.g. along an axis with a single node).

    Raises
    ------
    ValueError
        For an unknown method, a bad window, or ``"shape-function"`` on a field without gradient.
    """
    if method not in GRADIENT_METHODS:
        raise ValueError(f"unknown gradient method {method!r}: use one of {GRADIENT_METHODS}")
    valid = field.valid
    if method == "shape-function":
        if field.gradient is None:
            raise ValueError(
                "this field holds no shape-function gradient: use method 'central' or "
                "'least-squares'"
            )
        out = field.gradient.copy()
        out[~valid] = np.nan
        return out
    u = np.where(valid[..., None], field.u, np.nan)
    step = np.asarray(field.step, dtype=np.float64)
    if method == "central":
        return _central_gradient(u, valid, step)
    window = int(window)
    if window < 3 or window % 2 == 0:
        raise ValueError(f"the strain window must be an odd number of nodes >= 3, got {window}")
    return _least_squares_gradient(u, valid, step, window // 2)


def _central_gradient(u: np.ndarray, valid: np.ndarray, step: np.ndarray) -> np.ndarray:
    """Central differences with one-sided fallbacks; ``u`` (nz, ny, nx, 3) is NaN where invalid."""
    out = np.full((*valid.shape, 3, 3), np.nan)
    for axis in range(3):
        n = valid.shape[axis]
        if n < 2:
            continue  # no neighbour along this axis: the derivative stays NaN

        def shifted(array, offset, axis=axis, n=n):
            """``array`` at node ``i + offset`` along ``axis`` (invalid/False beyond the edges)."""
            result = np.full_like(array, np.nan if array.dtype.kind == "f" else False)
            source = [slice(None)] * array.ndim
            target = [slice(None)] * array.ndim
            if offset > 0:
                source[axis], target[axis] = slice(offset, n), slice(0, n - offset)
            else:
                source[axis], target[axis] = slice(0, n + offset), slice(-offset, n)
            result[tuple(target)] = array[tuple(source)]
            return result

        up, down = shifted(u, 1), shifted(u, -1)
        up_ok, down_ok = shifted(valid, 1), shifted(valid, -1)
        central = (up - down) / (2.0 * step[axis])
        forward = (up - u) / step[axis]
        backward = (u - down) / step[axis]
        derivative = np.where(
            (up_ok & down_ok)[..., None],
            central,
            np.where(up_ok[..., None], forward, np.where(down_ok[..., None], backward, np.nan)),
        )
        derivative[~valid] = np.nan
        out[..., :, axis] = derivative
    return out


def _least_squares_gradient(
    u: np.ndarray, valid: np.ndarray, step: np.ndarray, half: int
) -> np.ndarray:
    out = np.full((*valid.shape, 3, 3), np.nan)
    _least_squares_kernel(u, valid, half, out)
    # the kernel works in node units: divide column j by the node spacing along j
    return out / step[None, None, None, None, :]


@njit(parallel=True, **KERNEL_OPTIONS)
def _least_squares_kernel(u, valid, half, out):  # pragma: no cover - compiled
    nz, ny, nx = valid.shape
    total = nz * ny * nx
    for flat in prange(total):
        k = flat % nx
        j = (flat // nx) % ny
        i = flat // (nx * ny)
        if not valid[i, j, k]:
            continue
        normal = np.zeros((4, 4))
        rhs = np.zeros((4, 3))
        basis = np.empty(4)
        count = 0
        for a in range(max(0, i - half), min(nz, i + half + 1)):
            for b in range(max(0, j - half), min(ny, j + half + 1)):
                for c in range(max(0, k - half), min(nx, k + half + 1)):
                    if not valid[a, b, c]:
                        continue
                    basis[0] = 1.0
                    basis[1] = a - i
                    basis[2] = b - j
                    basis[3] = c - k
                    for p in range(4):
                        for q in range(4):
                            normal[p, q] += basis[p] * basis[q]
                        for d in range(3):
                            rhs[p, d] += basis[p] * u[a, b, c, d]
                    count += 1
        if count < 4:
            continue
        # Gaussian elimination with partial pivoting on the 4x4 normal equations
        scale = 0.0
        for p in range(4):
            scale = max(scale, abs(normal[p, p]))
        singular = False
        for col in range(4):
            pivot = col
            for row in range(col + 1, 4):
                if abs(normal[row, col]) > abs(normal[pivot, col]):
                    pivot = row
            if abs(normal[pivot, col]) <= 1e-9 * scale:
                singular = True
                break
            if pivot != col:
                for q in range(4):
                    tmp = normal[col, q]
                    normal[col, q] = normal[pivot, q]
                    normal[pivot, q] = tmp
                for d in range(3):
                    tmp = rhs[col, d]
                    rhs[col, d] = rhs[pivot, d]
                    rhs[pivot, d] = tmp
            for row in range(col + 1, 4):
                factor = normal[row, col] / normal[col, col]
                for q in range(col, 4):
                    normal[row, q] -= factor * normal[col, q]
                for d in range(3):
                    rhs[row, d] -= factor * rhs[col, d]
        if singular:
            continue  # the valid nodes are coplanar: no 3-D gradient here
        solution = np.zeros((4, 3))
        for row in range(3, -1, -1):
            for d in range(3):
                acc = rhs[row, d]
                for q in range(row + 1, 4):
                    acc -= normal[row, q] * solution[q, d]
                solution[row, d] = acc / normal[row, row]
        for d in range(3):
            for axis in range(3):
                out[i, j, k, d, axis] = solution[axis + 1, d]


# --- tensors ---------------------------------------------------------------------------------
def _check_tensor(array: np.ndarray, name: str) -> np.ndarray:
    array = np.asarray(array, dtype=np.float64)
    if array.shape[-2:] != (3, 3):
        raise ValueError(f"{name} must have shape (..., 3, 3), got {array.shape}")
    return array


def small_strain(gradient: np.ndarray) -> np.ndarray:
    """Infinitesimal strain ``eps = (H + H^T) / 2``.

    Parameters
    ----------
    gradient : ndarray, shape (..., 3, 3)
        Displacement gradient ``du_i/dX_j``, (z, y, x) order.

    Returns
    -------
    ndarray, shape (..., 3, 3), float64
        Symmetric tensor with *tensor* (not engineering) shear components.
    """
    h = _check_tensor(gradient, "gradient")
    return 0.5 * (h + np.swapaxes(h, -1, -2))


# small_strain and green_lagrange_strain have the same shape of checks and docstring on purpose:
# two measures of one gradient, side by side.
def green_lagrange_strain(gradient: np.ndarray) -> np.ndarray:
    """Green–Lagrange strain ``E = (H + H^T + H^T H) / 2`` (finite strain, reference frame).

    Parameters
    ----------
    gradient : ndarray, shape (..., 3, 3)
        Displacement gradient ``du_i/dX_j``, (z, y, x) order.

    Returns
    -------
    ndarray, shape (..., 3, 3), float64
    """
    h = _check_tensor(gradient, "gradient")
    ht = np.swapaxes(h, -1, -2)
    return 0.5 * (h + ht + ht @ h)


def principal_strains(tensor: np.ndarray) -> np.ndarray:
    """Principal values of a symmetric strain tensor, largest first.

    Parameters
    ----------
    tensor : ndarray, shape (..., 3, 3)
        Symmetric strain tensor (NaN entries allowed).

    Returns
    -------
    ndarray, shape (..., 3), float64
        Eigenvalues in decreasing order; NaN where the tensor has a NaN.
    """
    tensor = _check_tensor(tensor, "tensor")
    bad = ~np.all(np.isfinite(tensor), axis=(-2, -1))
    clean = np.where(bad[..., None, None], 0.0, tensor)
    values = np.linalg.eigvalsh(clean)[..., ::-1]
    values[bad] = np.nan
    return values


def equivalent_strain(tensor: np.ndarray) -> np.ndarray:
    """Equivalent (octahedral) strain, paper eq. 3, with tensor shear components.

    ``sqrt(2/9 [(exx-eyy)^2 + (eyy-ezz)^2 + (ezz-exx)^2 + 6 (exy^2 + eyz^2 + ezx^2)])``

    For uniaxial strain ``diag(e, 0, 0)`` it is ``2|e|/3``; for a pure tensor shear ``exy = g``
    it is ``2|g|/sqrt(3)``; it is zero for any isotropic (volumetric) strain.

    Parameters
    ----------
    tensor : ndarray, shape (..., 3, 3)
        Symmetric strain tensor in (z, y, x) order (small or Green–Lagrange).

    Returns
    -------
    ndarray, shape (...), float64
        NaN where the tensor has a NaN.
    """
    t = _check_tensor(tensor, "tensor")
    ezz, eyy, exx = t[..., 0, 0], t[..., 1, 1], t[..., 2, 2]
    ezy = 0.5 * (t[..., 0, 1] + t[..., 1, 0])
    eyx = 0.5 * (t[..., 1, 2] + t[..., 2, 1])
    ezx = 0.5 * (t[..., 0, 2] + t[..., 2, 0])
    total = (
        (exx - eyy) ** 2 + (eyy - ezz) ** 2 + (ezz - exx) ** 2 + 6.0 * (ezy**2 + eyx**2 + ezx**2)
    )
    return np.sqrt(2.0 / 9.0 * total)


def strain_tensor(
    field: DisplacementField,
    measure: str = "small",
    method: str = "central",
    window: int = 5,
) -> np.ndarray:
    """Strain tensor at every node of the field's grid.

    Parameters
    ----------
    field : DisplacementField
        Field of grid shape ``(nz, ny, nx)``.
    measure : {"small", "green-lagrange"}
        Infinitesimal strain or Green–Lagrange strain.
    method, window
        Gradient estimator, see :func:`displacement_gradient`.

    Returns
    -------
    ndarray, shape (nz, ny, nx, 3, 3), float64
        NaN at invalid nodes.
    """
    if measure not in STRAIN_MEASURES:
        raise ValueError(f"unknown strain measure {measure!r}: use one of {STRAIN_MEASURES}")
    gradient = displacement_gradient(field, method=method, window=window)
    return small_strain(gradient) if measure == "small" else green_lagrange_strain(gradient)


def equivalent_strain_field(
    field: DisplacementField,
    measure: str = "small",
    method: str = "central",
    window: int = 5,
) -> np.ndarray:
    """Equivalent strain (eq. 3) on the grid, shape ``(nz, ny, nx)``, float64, NaN at invalid nodes.

    See :func:`strain_tensor` for the parameters.
    """
    return equivalent_strain(strain_tensor(field, measure=measure, method=method, window=window))
