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

Matches are judged by the grid's noise-aware ZNCC threshold (:func:`.noise.noise_aware_thresholds`:
``min_zncc · (1 − σ_n² / s²)`` per point, ``LOW_TEXTURE`` where ``1 − σ_n² / s²`` is below
:data:`.noise.MIN_PERFECT_ZNCC`), with the noise ``σ_n²`` estimated from the points' own matches
when at least :data:`MIN_NOISE_POINTS` matched, else from the guide's (its grid covers the points'
region), else (a given guide without a noise estimate) the fixed ``min_zncc``;
``metadata["noise"]`` says which.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from ..backend import select_device
from ..fields.field import GOOD_STATUSES, DisplacementField, Provenance, Status
from ..fields.scattered import ScatteredField, sample_field
from . import shape_function
from .correlate import correlate, validate_pair
from .noise import (
    MIN_PERFECT_ZNCC,
    noise_aware_thresholds,
    noise_estimates,
    noise_metadata,
    zncc_floor,
)
from .params import CorrelationParams
from .placement import Box, grid_for_region
from .pyramid import PyramidLevel

GOOD_CODES = np.array([int(s) for s in GOOD_STATUSES])

#: Fewest matched points whose median ``s² (1 − ZNCC)`` is taken as the noise estimate. The
#: median of ``n`` estimates scatters by about ``1.25 / sqrt(n)`` of their spread (23 % at 30),
#: and a few bad matches among a handful of points move it far; below this the guide's estimate
#: (median over its grid, the same region) is used, and the fixed ``min_zncc`` without one.
MIN_NOISE_POINTS = 30


def _guide_noise(guide: DisplacementField):
    """The guide's recorded noise variance and how many matched POIs it came from (or None)."""
    sigma = (guide.metadata or {}).get("noise", {}).get("sigma")
    count = int(np.isin(guide.status, GOOD_CODES).sum()) if guide.status is not None else 0
    if sigma is None or not np.isfinite(sigma) or count < MIN_NOISE_POINTS:
        return None, count
    return float(sigma) ** 2, count


def matched_variance(level, centers, trial, zncc, status, order) -> np.ndarray:
    """Gray variance of each point's reference subvolume (gray levels², NaN where not matched):
    the noise estimate's ingredient, measured while ``level`` (its volumes) is at hand."""
    n = len(centers)
    stats = (np.full(n, np.nan), np.full(n, np.nan), np.full((n, 3), np.nan))
    matched = np.flatnonzero(np.isin(status, GOOD_CODES))
    cheap = np.zeros(len(matched), bool)
    level.statistics(centers[matched], trial[matched], zncc[matched], order, cheap, stats, matched)
    return stats[0]


def _thresholds(variance, zncc, status, order, params, guide):
    """Each point's ZNCC threshold, the LOW_TEXTURE points and ``metadata["noise"]``."""
    n = len(status)
    own = len(noise_estimates(variance, zncc, status))
    given, source, count = None, "points", own
    if own < MIN_NOISE_POINTS:
        given, count = _guide_noise(guide)
        source = "guide" if given is not None else "fixed"
    textureless = np.zeros(n, bool)
    if source == "fixed":
        noise_variance, thresholds = 0.0, np.full(n, float(params.min_zncc))
    else:
        floor = zncc_floor(order, params.subvolume)
        noise_variance, perfect, thresholds = noise_aware_thresholds(
            variance, zncc, status, params.min_zncc, floor, noise_variance=given
        )
        textureless = np.isin(status, GOOD_CODES) & (perfect < MIN_PERFECT_ZNCC)
    metadata = {
        **noise_metadata(noise_variance, thresholds, status, params.min_zncc),
        "source": source,
        "estimates": int(count),
        "min_points": MIN_NOISE_POINTS,
    }
    if source == "fixed":
        metadata["zncc_threshold_rule"] = "min_zncc (too few matched points, no guide estimate)"
    return thresholds, textureless, metadata


def guide_grid(volume_shape, points: np.ndarray, params: CorrelationParams) -> tuple:
    """The guide field's grid: a step beyond the points' bounding box on every side."""
    lo = points.min(axis=0) - params.step
    hi = points.max(axis=0) + params.step + 1
    return grid_for_region(volume_shape, params.subvolume, params.step, Box(lo, hi))


def check_points(points, volume_shape, params: CorrelationParams):
    """``(points, centres, inside)``: the points as float64 (N, 3), their nearest voxels and
    which of them keep their subvolume inside the volume. ValueError when none can be used."""
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or len(points) == 0:
        raise ValueError(f"points must have shape (N, 3) with N >= 1, got {points.shape}")
    if not np.all(np.isfinite(points)):
        raise ValueError("point positions must be finite")
    half = params.half
    centers = np.rint(points).astype(np.int64)
    inside = np.all((centers >= half) & (centers <= np.array(volume_shape) - 1 - half), axis=1)
    if not inside.any():
        raise ValueError(
            f"no point keeps its subvolume ({params.subvolume} voxels) inside the volume "
            f"{tuple(volume_shape)}: move the points at least {half} voxels from the border"
        )
    return points, centers, inside


def starting_warps(guide: DisplacementField, centers: np.ndarray, order: int) -> np.ndarray:
    """Shape-function parameters (n, 3·nb) at voxels ``centers`` from the guide's warp there
    (nodes without a value filled from the nearest good one)."""
    at = centers.astype(np.float64)
    guess = sample_field(guide, at)
    good = np.all(np.isfinite(guess.u), axis=1)
    if not good.any():
        raise ValueError("the guide field has no usable node near the points")
    u0 = _fill_from_nearest(guess.u, good, at)
    g0 = None
    if guess.gradient is not None:
        g0 = _fill_from_nearest(guess.gradient.reshape(-1, 9), good, at).reshape(-1, 3, 3)
        g0 = np.nan_to_num(g0)
    return np.ascontiguousarray(shape_function.displacement_to_params(u0, g0, order))


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
        point, ZNCC, status, iterations; ``metadata["guide_grid"]`` describes the guide,
        ``metadata["noise"]`` the ZNCC thresholds (``"source"``: ``"points"``, ``"guide"`` or
        ``"fixed"``, and ``"estimates"``, the matched POIs the noise estimate came from).
    """
    params = CorrelationParams() if params is None else params
    started = time.perf_counter()
    device = select_device(device)
    reference, deformed, mask = validate_pair(reference, deformed, params, mask)
    points, centers, inside = check_points(points, reference.shape, params)
    if guide is None:
        grid = guide_grid(reference.shape, points[inside], params)
        guide = correlate(reference, deformed, params, mask=mask, grid=grid, device=device)
    order = params.order
    trial = starting_warps(guide, centers[inside], order)
    level = PyramidLevel.build(
        1, reference, deformed, mask, params.half, params.min_texture, device.kind,
        weights=params.subvolume_weights(),
    )  # fmt: skip
    zncc_i, status_i, iterations_i = level.match(centers[inside], trial, order, params)
    variance = matched_variance(level, centers[inside], trial, zncc_i, status_i, order)
    matches = PointMatches(trial, zncc_i, status_i, iterations_i, variance)
    result = points_field(points, centers, inside, matches, params, guide)
    result.metadata.update(volume_shape=list(reference.shape), device=device.description)
    result.metadata["timings"] = {"total_s": time.perf_counter() - started}
    return result


@dataclass
class PointMatches:
    """IC-GN results at the points that keep their subvolume inside the volume (``n`` of them,
    in input order): shape-function parameters ``trial`` (n, 3·nb), ``zncc``, ``status``,
    ``iterations`` and the reference subvolumes' gray ``variance`` (gray levels²)."""

    trial: np.ndarray
    zncc: np.ndarray
    status: np.ndarray
    iterations: np.ndarray
    variance: np.ndarray


def points_field(points, centers, inside, matches: PointMatches, params, guide) -> ScatteredField:
    """The :class:`ScatteredField` of matched points, judged at the points' noise (or the
    guide's): thresholds, ``LOW_TEXTURE``/``LOW_ZNCC``, the warp carried to each exact point.

    ``matches`` may come from one run or from several regions (:mod:`..tiled`): the noise
    estimate is the median over all the points either way.
    """
    order = params.order
    zncc_i, status_i, iterations_i = matches.zncc, matches.status, matches.iterations
    n = len(points)
    zncc = np.full(n, np.nan)
    status = np.full(n, int(Status.OUT_OF_BOUNDS), np.int64)
    iterations = np.zeros(n, np.int64)
    zncc[inside], status[inside], iterations[inside] = zncc_i, status_i, iterations_i
    thresholds, textureless, noise = _thresholds(
        matches.variance, zncc_i, status_i, order, params, guide
    )
    status[np.flatnonzero(inside)[textureless]] = int(Status.LOW_TEXTURE)
    low = np.isin(status, GOOD_CODES)
    low[inside] &= ~(zncc_i >= thresholds)
    status[low] = int(Status.LOW_ZNCC)
    displacement = np.full((n, 3), np.nan)
    gradient = np.full((n, 3, 3), np.nan)
    d_i, g_i = shape_function.params_to_displacement(matches.trial, order)
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
            "guide_grid": {
                "origin": list(guide.origin),
                "step": list(guide.step),
                "shape": list(guide.shape),
            },
            "noise": noise,
        },
    )
