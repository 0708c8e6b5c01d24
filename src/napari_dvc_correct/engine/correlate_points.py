"""Local DVC at a list of points of interest, any spacing: results at exactly those points.

``correlate_points(G, F, points, params) -> ScatteredField``:

1. a guide field from :func:`.correlate.correlate` on a grid over the points' bounding box (one
   step beyond it on every side): it gives every point a robust initial warp (global shift,
   pyramid, reliability-guided repair), which an isolated point could not get alone;
2. IC-GN at each point's nearest voxel (the subvolume centre must be a whole voxel), starting from
   the guide's warp interpolated there;
3. the matched first-order warp carried from that voxel to the exact point,
   ``u(p) = u(c) + ∇u · (p - c)`` with ``|p - c| <= 0.87`` voxel.

A point whose subvolume does not fit in the volume is ``OUT_OF_BOUNDS`` (NaN displacement).
"""

from __future__ import annotations

import time

import numpy as np

from . import shape_function
from .backend import select_device
from .correlate import PyramidLevel, correlate, validate_pair
from .field import GOOD_STATUSES, DisplacementField, Provenance, Status
from .params import CorrelationParams
from .placement import Box, grid_for_region
from .scattered import ScatteredField, sample_field

GOOD_CODES = np.array([int(s) for s in GOOD_STATUSES])


def _guide(reference, deformed, points, params, mask, device) -> DisplacementField:
    lo = points.min(axis=0) - params.step
    hi = points.max(axis=0) + params.step + 1
    grid = grid_for_region(reference.shape, params.subvolume, params.step, Box(lo, hi))
    return correlate(reference, deformed, params, mask=mask, grid=grid, device=device)


def _fill_from_nearest(values: np.ndarray, good: np.ndarray, points: np.ndarray) -> np.ndarray:
    if good.all() or not good.any():
        return np.nan_to_num(values)
    from scipy.spatial import cKDTree

    _, nearest = cKDTree(points[good]).query(points[~good])
    out = values.copy()
    out[~good] = values[good][nearest]
    return out


def correlate_points(
    reference: np.ndarray,
    deformed: np.ndarray,
    points,
    params: CorrelationParams | None = None,
    *,
    mask: np.ndarray | None = None,
    guide: DisplacementField | None = None,
    device="cpu",
) -> ScatteredField:
    """Correlate ``reference`` (G) with ``deformed`` (F) at the given points.

    Parameters
    ----------
    reference, deformed : ndarray, shape (nz, ny, nx)
        The two volumes, axis order (z, y, x).
    points : array-like, shape (N, 3)
        Positions ``(z, y, x)`` of the points of interest in reference voxels (0-based), any
        spacing, fractional positions allowed.
    params : CorrelationParams, optional
        Subvolume, shape-function order, search radius... (``step`` is only the guide grid's).
    mask : ndarray of bool, shape (nz, ny, nx), optional
        Material mask, as in :func:`.correlate.correlate`.
    guide : DisplacementField, optional
        Initial-guess field (default: correlated here on a grid around the points).
    device : {"cpu", "cuda", "auto"}
        Where IC-GN runs.

    Returns
    -------
    ScatteredField
        One entry per input point, in the input order: ``u`` and ``gradient`` at exactly the
        point, ZNCC, status, iterations; ``metadata["guide_grid"]`` describes the guide.
    """
    params = CorrelationParams() if params is None else params
    started = time.perf_counter()
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or len(points) == 0:
        raise ValueError(f"points must have shape (N, 3) with N >= 1, got {points.shape}")
    if not np.all(np.isfinite(points)):
        raise ValueError("point positions must be finite")
    device = select_device(device)
    reference, deformed, mask = validate_pair(reference, deformed, params, mask)
    half = params.half
    centers = np.rint(points).astype(np.int64)
    inside = np.all((centers >= half) & (centers <= np.array(reference.shape) - 1 - half), axis=1)
    if not inside.any():
        raise ValueError(
            f"no point keeps its subvolume ({params.subvolume} voxels) inside the volume "
            f"{reference.shape}: move the points at least {half} voxels from the border"
        )
    if guide is None:
        guide = _guide(reference, deformed, points[inside], params, mask, device)
    guess = sample_field(guide, centers[inside].astype(np.float64))
    good = np.all(np.isfinite(guess.u), axis=1)
    if not good.any():
        raise ValueError("the guide field has no usable node near the points")
    u0 = _fill_from_nearest(guess.u, good, centers[inside].astype(np.float64))
    g0 = None
    if guess.gradient is not None:
        g0 = _fill_from_nearest(
            guess.gradient.reshape(-1, 9), good, centers[inside].astype(np.float64)
        ).reshape(-1, 3, 3)
        g0 = np.nan_to_num(g0)
    order = params.order
    trial = np.ascontiguousarray(shape_function.displacement_to_params(u0, g0, order))
    level = PyramidLevel.build(1, reference, deformed, mask, half, params.min_texture, device.kind)
    zncc_i, status_i, iterations_i = level.match(centers[inside], trial, order, params)

    n = len(points)
    zncc = np.full(n, np.nan)
    status = np.full(n, int(Status.OUT_OF_BOUNDS), np.int64)
    iterations = np.zeros(n, np.int64)
    zncc[inside], status[inside], iterations[inside] = zncc_i, status_i, iterations_i
    low = np.isin(status, GOOD_CODES) & ~(zncc >= params.min_zncc)
    status[low] = int(Status.LOW_ZNCC)
    displacement = np.full((n, 3), np.nan)
    gradient = np.full((n, 3, 3), np.nan)
    d_i, g_i = shape_function.params_to_displacement(trial, order)
    offset = points[inside] - centers[inside]
    displacement[inside] = d_i + np.einsum("nij,nj->ni", g_i, offset)
    gradient[inside] = g_i
    failed = ~np.isin(status, np.r_[GOOD_CODES, [int(Status.LOW_ZNCC)]])
    displacement[failed] = np.nan
    gradient[failed] = np.nan
    provenance = np.full(n, int(Provenance.MEASURED), np.uint8)
    provenance[status == int(Status.MASKED)] = int(Provenance.MASKED)
    return ScatteredField(
        points=points.copy(),
        u=displacement,
        zncc=zncc.astype(np.float32),
        status=status.astype(np.uint8),
        iterations=iterations.astype(np.int32),
        provenance=provenance,
        gradient=gradient,
        params=params.to_dict(),
        metadata={
            "volume_shape": list(reference.shape),
            "guide_grid": {
                "origin": list(guide.origin),
                "step": list(guide.step),
                "shape": list(guide.shape),
            },
            "device": device.description,
            "timings": {"total_s": time.perf_counter() - started},
        },
    )
