"""The error estimate over windows of several sizes: each node read at the finest that resolves.

The residual's step (:func:`.error_estimate.residual_error`) measures the mean error over a
node's window. A window of one grid step averages an error that varies inside it: a field that
misses a band narrower than its subvolume is off by 0.5-0.7 voxel at the band's core and much
less three voxels away, and a window of half-size 6 reads those nodes at 0.2-0.4. A smaller
window reads the node's own error, but with more noise (its resolution grows about as the
window's volume to the power -1/2). The windows' moments are gathered at half-sizes from 2
voxels up to the largest (:func:`window_ladder`), and each node takes the finest window whose
resolution is at most :data:`FINE_RESOLUTION` voxel and whose reading is at least
:data:`RESOLVED_RATIO` times that resolution (the largest where none is): on clear texture a
node well off is read at 2 voxels, on noisy texture where the noise allows, on faint texture and
below a finer window's noise in the largest window as before.

The node's departure from its neighbourhood ``d`` (:mod:`.node_roughness`) stands for an error
confined to the node, which the windows hold only in part. A true field that bends at the
grid's scale (a narrow band the correction followed) shows in ``d`` too, without any error. The
windows tell the two apart where they resolve: a node off by the vector ``d`` moves each of its
windows' steps by ``share · d``, ``share`` the mean over the window of the node's own cubic
spline cardinal function (:func:`window_share`: 0.14 for the window of one step, 0.72 for
half-size 2 at step 6). So ``d`` is taken at most as large as its window's step allows along
its direction: ``(max(Δu·d̂, 0) + k σ) / share`` with ``σ = resolution/√3`` the step's noise
along a direction and ``k`` = :data:`NODE_SIGMAS`, in the window where ``σ / share`` is least.
Where the texture cannot see it (noise), the bound is loose and ``d`` stays what it was built
for. Measured in ``docs/evaluation.md`` (``benchmarks/bench_error_estimate_dvc.py``).
"""

from __future__ import annotations

import functools

import numpy as np

#: A node is read in the finest window whose resolution (voxels, the norm of the step's noise)
#: is at most this: a fifth of the limit of a likely bad node (0.5 voxel).
FINE_RESOLUTION = 0.1

#: How many standard deviations of a window step's noise the node's departure may exceed the
#: step's reading of it (:func:`node_error_bound`).
NODE_SIGMAS = 2.0

#: A finer window is read only where its reading is at least this many times its resolution.
RESOLVED_RATIO = 3.0

#: The finest window's half-size (voxels).
FINEST_HALF = 2


def window_ladder(coarse: int) -> tuple[int, ...]:
    """Half-sizes from ``coarse`` down to :data:`FINEST_HALF` by factors of about √2, finest
    first (6 -> (2, 3, 4, 6), 8 -> (2, 3, 4, 6, 8), 5 -> (2, 3, 4, 5))."""
    coarse = int(coarse)
    if coarse < 1:
        raise ValueError(f"the window's half-size must be at least 1 voxel, got {coarse}")
    halves = [coarse]
    while halves[-1] > FINEST_HALF:
        halves.append(max(FINEST_HALF, int(round(halves[-1] / np.sqrt(2.0)))))
    return tuple(sorted(set(halves)))


@functools.lru_cache(maxsize=256)
def _share_1d(step: float, half: int) -> float:
    from scipy import ndimage

    n = 2 * int(np.ceil((half + 1) / step)) + 41
    delta = np.zeros(n)
    delta[n // 2] = 1.0
    coefficients = ndimage.spline_filter1d(delta, order=3, mode="mirror")
    x = n // 2 + np.arange(-half, half + 1) / step
    values = ndimage.map_coordinates(coefficients, [x], order=3, prefilter=False, mode="mirror")
    return float(values.mean())


def window_share(step, half: int) -> float:
    """Mean over a node's window of half-size ``half`` (voxels) of the node's own cardinal
    function of the cubic spline that densifies a field of grid ``step`` (voxels per axis): the
    share of an error confined to the node that the window's mean error holds (0.142 at
    ``half`` = step = 6, 0.724 at half 2)."""
    steps = np.broadcast_to(np.asarray(step, dtype=np.float64), (3,))
    return float(np.prod([_share_1d(float(s), int(half)) for s in steps]))


def finest_resolved(residuals) -> tuple[np.ndarray, np.ndarray]:
    """Per node, ``e_r`` and the resolution of the finest window whose resolution is at most
    :data:`FINE_RESOLUTION` and whose ``e_r`` is at least :data:`RESOLVED_RATIO` times it,
    else of the last (largest).

    Parameters
    ----------
    residuals : sequence of :class:`.error_estimate.ResidualError`
        One per window, finest first, on the same grid.
    """
    resolved = np.array(residuals[-1].resolved, dtype=np.float64)
    resolution = np.array(residuals[-1].resolution, dtype=np.float64)
    chosen = np.zeros(resolved.shape, bool)
    for residual in residuals[:-1]:
        sharp = np.where(np.isnan(residual.resolution), np.inf, residual.resolution)
        seen = np.where(np.isnan(residual.resolved), 0.0, residual.resolved)
        fine = ~chosen & (sharp <= FINE_RESOLUTION) & (seen >= RESOLVED_RATIO * sharp)
        resolved = np.where(fine, residual.resolved, resolved)
        resolution = np.where(fine, residual.resolution, resolution)
        chosen |= fine
    return resolved, resolution


def node_error_bound(residuals, halves, step, deviation: np.ndarray) -> np.ndarray:
    """How large a node's departure from its neighbourhood may be as an error of the node,
    given what its windows' steps read along it (see the module; voxels, ``inf`` where no
    window sees it).

    Parameters
    ----------
    residuals : sequence of :class:`.error_estimate.ResidualError`
        One per window.
    halves : sequence of int
        The windows' half-sizes (voxels).
    step : sequence of float
        The grid's step per axis (voxels).
    deviation : ndarray, shape (nz, ny, nx, 3)
        The departure vectors (:func:`.node_roughness.node_deviation`).
    """
    size = np.linalg.norm(np.nan_to_num(deviation), axis=-1)
    direction = np.nan_to_num(deviation) / np.where(size > 0, size, 1.0)[..., None]
    best = np.full(size.shape, np.inf)
    bound = np.full(size.shape, np.inf)
    for residual, half in zip(residuals, halves):
        share = window_share(step, half)
        sigma = np.asarray(residual.resolution, dtype=np.float64) / np.sqrt(3.0)
        noise = np.where(np.isfinite(sigma), sigma / share, np.inf)
        along = np.nan_to_num(np.sum(residual.shift * direction, axis=-1), nan=0.0)
        here = (np.maximum(along, 0.0) + NODE_SIGMAS * sigma) / share
        better = noise < best
        bound = np.where(better, here, bound)
        best = np.where(better, noise, best)
    return bound
