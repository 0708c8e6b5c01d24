"""Band-oriented re-matches: the original pair matched under windows that follow the field's plane.

Where a field varies across a plane (a shear band) and the imaging noise forbids the small
second-order boxes that would follow it, a first-order match whose subvolume is weighted by an
anisotropic Gaussian, narrow across that plane and wide along it, averages the noise over as many
voxels as a cube while reading the field's variation across the plane at the scale of a few
voxels. This module

* estimates the plane at every node from the field itself (:func:`plane_normals`): the
  structure tensor of the departures of the nodes' displacement gradients from their regional
  mean, smoothed over a neighbourhood of nodes; its first eigenvector is the normal of the plane
  across which the field varies, the share of its first eigenvalue says whether the variation is
  planar at all;
* quantises the normals to a fixed set of directions (:func:`direction_set`, worst angle a few
  degrees) so that one weighted run serves every node of one direction;
* re-matches the original pair at the chosen nodes, one run per direction
  (:func:`oriented_rematch`), from the field's own values, through a matcher of the volume
  back-end (:class:`ArrayMatcher` for arrays; the tiled back-end's reads them block by block).

The self-correction calls it as one step after its passes (:func:`oriented_step`); the new values
go through its usual local acceptance. See ``docs/method.md`` (the heavy-noise narrow band).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Generator

import numpy as np
from scipy import ndimage

from ..correlation.correlate import correlate_iter
from ..correlation.icgn_reference import gradient_volume
from ..correlation.interpolation import prefilter
from ..correlation.params import WINDOW_TRUNCATE, CorrelationParams
from ..correlation.pyramid import GRADIENT_ON_DEMAND_FROM, Prefiltered
from ..fields.field import GOOD_STATUSES, DisplacementField
from ..progress import Progress
from .acceptance import accept_locally
from .oriented_deblur import deblur_across, window_moments
from .pass_method import CURVATURE_VOXELS, field_curvature

#: The oriented window's standard deviation across the plane, in units of the first run's
#: subvolume half-width (2.0 voxels for 21³): narrow enough to read a band of half-width 4; the
#: blur it leaves (its second moment times the band's curvature) is taken out afterwards
#: (:mod:`.oriented_deblur`), so the narrower window's smaller higher-order blur wins over its
#: larger noise (2.5 voxels before the deblur, measured in docs/method.md).
ACROSS_FRACTION = 0.2

#: ... along the plane, in the same units (12 voxels for 21³): the voxels of a 21³ cube spread
#: over the plane (and more: the bending it blurs along the plane is taken out with the rest).
ALONG_FRACTION = 1.2

#: The oriented match's box edge over the first run's subvolume (31³ for 21³): holds the window
#: to beyond two standard deviations along the plane.
BOX_FRACTION = 1.5

#: Worst angle (degrees) between a node's normal and the direction it is matched with.
DIRECTION_TOLERANCE = 4.0

#: A node's variation is planar when the first eigenvalue of its structure tensor holds at least
#: this share of the trace (1: one direction only; 1/3: isotropic).
PLANARITY = 0.6

#: Smoothing of the structure tensor (Gaussian std, in grid steps).
TENSOR_SMOOTHING = 2.0

#: The regional mean the gradients are measured from (Gaussian std, in grid steps): a rotation,
#: a uniform strain and slow bending are not a plane's variation.
REGIONAL_SCALE = 3.0


def oriented_window(
    half: int, normal, across: float, along: float, truncate: float | None = WINDOW_TRUNCATE
) -> np.ndarray:
    """Weights of an anisotropic Gaussian on a ``(2·half + 1)³`` box.

    Parameters
    ----------
    half : int
        The box's half-width (voxels), >= 1.
    normal : array-like, shape (3,)
        The plane's normal ``(z, y, x)`` (any length > 0).
    across, along : float
        Standard deviations (voxels, > 0) along ``normal`` and in the plane normal to it.
    truncate : float or None
        The window's radius in standard deviations: voxels with
        ``t²/across² + p²/along² > truncate²`` weigh 0 (the matcher skips them), as
        :meth:`.CorrelationParams.subvolume_weights`' Gaussian; None: the whole box is weighted.

    Returns
    -------
    ndarray, shape (2·half + 1,)*3, float64
        ``exp(-t²/(2 across²) - p²/(2 along²))``, ``t`` the offset along the normal, ``p`` in
        the plane; 1 at the centre.
    """
    normal = np.asarray(normal, np.float64).reshape(3)
    length = float(np.linalg.norm(normal))
    if not np.isfinite(length) or length == 0.0:
        raise ValueError(f"the plane's normal must be a finite non-zero vector, got {normal}")
    if int(half) < 1:
        raise ValueError(f"the box's half-width must be >= 1 voxel, got {half!r}")
    if not (np.isfinite(across) and np.isfinite(along) and across > 0 and along > 0):
        raise ValueError(
            f"the window's standard deviations must be > 0 voxels, got {across!r} / {along!r}"
        )
    normal = normal / length
    r = np.arange(-int(half), int(half) + 1, dtype=np.float64)
    z, y, x = np.meshgrid(r, r, r, indexing="ij")
    t = z * normal[0] + y * normal[1] + x * normal[2]
    plane = z * z + y * y + x * x - t * t
    if truncate is not None and not (np.isfinite(truncate) and truncate > 0):
        raise ValueError(f"the window's radius must be > 0 standard deviations, got {truncate!r}")
    r2 = t * t / across**2 + plane / along**2
    weights = np.exp(-0.5 * r2)
    if truncate is not None:
        weights[r2 > float(truncate) ** 2] = 0.0
    return weights


def direction_set(tolerance: float = DIRECTION_TOLERANCE) -> np.ndarray:
    """Unit vectors on the upper hemisphere (``z >= 0``, a Fibonacci lattice) such that every
    direction lies within ``tolerance`` degrees of one of them (up to sign).

    Returns
    -------
    ndarray, shape (K, 3)
        ``(z, y, x)`` unit vectors.
    """
    if not (0.5 <= tolerance <= 45.0):
        raise ValueError(f"the direction tolerance must be 0.5–45 degrees, got {tolerance!r}")
    # a Fibonacci lattice of n points on the sphere covers it within about 1.1 × the mean
    # spacing sqrt(4π / n); the number is set so that the measured worst angle is below tolerance
    n = int(np.ceil(4.0 * np.pi / np.radians(tolerance / 1.25) ** 2))
    index = np.arange(n) + 0.5
    z = 1.0 - 2.0 * index / n
    azimuth = np.pi * (1.0 + 5.0**0.5) * index
    radius = np.sqrt(1.0 - z * z)
    points = np.stack([z, radius * np.sin(azimuth), radius * np.cos(azimuth)], -1)
    return points[z >= 0.0]


#: Normals quantised at a time by :func:`quantise` (bounds its working memory).
QUANTISE_ROWS = 2048


def quantise(normals: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """Index into ``directions`` of the direction nearest to each normal (up to sign).

    ``normals``: shape (..., 3); NaN normals get -1.
    """
    flat = np.asarray(normals, np.float64).reshape(-1, 3)
    finite = np.flatnonzero(np.all(np.isfinite(flat), axis=1))
    index = np.full(len(flat), -1, np.int64)
    # a few thousand normals at a time: the cosines of every node with every direction (~2000)
    # would take 16 kB per node at once (0.2 GB for 12 725 nodes, measured in a tiled run)
    for start in range(0, len(finite), QUANTISE_ROWS):
        rows = finite[start : start + QUANTISE_ROWS]
        index[rows] = np.argmax(np.abs(flat[rows] @ directions.T), axis=1)
    return index.reshape(np.shape(normals)[:-1])


def plane_normals(
    field: DisplacementField,
    usable: np.ndarray | None = None,
    smoothing: float = TENSOR_SMOOTHING,
    regional: float | None = REGIONAL_SCALE,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The plane across which the field varies, at every node, from the field alone.

    The displacement gradient ``∇u_k`` (central differences over the grid) less its regional
    mean (Gaussian of std ``regional`` steps: a rotation, a uniform strain, a slow bending are
    removed) gives per node ``T = Σ_k (∇u_k − ⟨∇u_k⟩)(∇u_k − ⟨∇u_k⟩)ᵀ``, smoothed over
    ``smoothing`` steps. For ``u = f(n·X)`` every row of the gradient is parallel to ``n``: ``T``'s
    first eigenvector is ``n`` and its eigenvalue is the whole trace.

    Parameters
    ----------
    field : DisplacementField
        ``u`` of shape (nz, ny, nx, 3), voxels; grid of at least 3 nodes per axis.
    usable : ndarray of bool, shape (nz, ny, nx), optional
        Nodes whose value may be read (default: every finite node); the others are filled from
        their neighbours' smoothed values before differencing and carry no weight in ``T``.

    Returns
    -------
    normal : ndarray, shape (nz, ny, nx, 3)
        Unit normal ``(z, y, x)`` per node (sign arbitrary).
    planarity : ndarray, shape (nz, ny, nx)
        First eigenvalue over the trace (1/3 isotropic … 1 planar); NaN where ``T`` is 0.
    strength : ndarray, shape (nz, ny, nx)
        ``sqrt`` of the first eigenvalue: the size of the planar gradient departure (voxel per
        voxel).
    """
    u = np.asarray(field.u, np.float64)
    if u.ndim != 4 or u.shape[-1] != 3:
        raise ValueError(f"the field's u must have shape (nz, ny, nx, 3), got {u.shape}")
    if min(u.shape[:3]) < 3:
        raise ValueError(f"the plane needs at least 3 nodes per axis, got grid {u.shape[:3]}")
    good = np.all(np.isfinite(u), axis=-1)
    if usable is not None:
        good &= np.asarray(usable, bool)
    if not good.any():
        raise ValueError("no usable node to estimate the field's plane from")
    weight = good.astype(np.float64)
    filled = np.where(good[..., None], u, 0.0)
    # holes: the normalised-convolution fill (their own neighbours' mean)
    norm = ndimage.gaussian_filter(weight, 1.0, mode="nearest")
    for c in range(3):
        mean = ndimage.gaussian_filter(filled[..., c], 1.0, mode="nearest") / np.maximum(
            norm, 1e-12
        )
        filled[..., c] = np.where(good, u[..., c], mean)
    step = np.asarray(field.step, np.float64)
    tensor = np.zeros(u.shape[:3] + (3, 3))
    for c in range(3):
        gradient = np.stack(np.gradient(filled[..., c], *step), -1)
        for a in range(3):
            if regional is None:
                gradient[..., a] -= np.mean(gradient[..., a][good])
            else:
                gradient[..., a] -= ndimage.gaussian_filter(
                    gradient[..., a], regional, mode="nearest"
                )
        tensor += gradient[..., :, None] * gradient[..., None, :] * weight[..., None, None]
    tensor = ndimage.gaussian_filter(tensor, (smoothing,) * 3 + (0, 0), mode="nearest")
    tensor /= np.maximum(ndimage.gaussian_filter(weight, smoothing, mode="nearest"), 1e-12)[
        ..., None, None
    ]
    values, vectors = np.linalg.eigh(tensor)
    trace = values.sum(-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        planarity = np.where(trace > 0, values[..., -1] / trace, np.nan)
    strength = np.sqrt(np.maximum(values[..., -1], 0.0))
    return vectors[..., -1], planarity, strength


def oriented_params(params: CorrelationParams) -> tuple[CorrelationParams, float, float]:
    """The oriented match's parameters from the first run's: first order on a box
    :data:`BOX_FRACTION` × its subvolume, window std across / along from its half-width."""
    half = int(round(BOX_FRACTION * params.half))
    across = ACROSS_FRACTION * params.half
    along = ALONG_FRACTION * params.half
    return params.replace(order=1, subvolume=2 * half + 1, window=None), across, along


def oriented_rematch(
    match,
    field: DisplacementField,
    nodes: np.ndarray,
    normals: np.ndarray,
    params: CorrelationParams,
    *,
    tolerance: float = DIRECTION_TOLERANCE,
) -> Generator[Progress, None, tuple[DisplacementField, OrientedRuns]]:
    """Match the original pair at ``nodes`` of ``field``'s grid under oriented windows.

    The normals are quantised to :func:`direction_set` (worst angle ``tolerance`` degrees); per
    direction one first-order weighted run (:func:`oriented_params`) matches that direction's
    nodes, started from ``field``'s values and gradients. This is the planning, shared by every
    volume back-end; ``match`` runs the matches.

    Parameters
    ----------
    match : matcher
        The original pair's matcher: ``match.shape`` is the volumes' ``(nz, ny, nx)``, and
        ``match(params, initial, active, weights)`` is a generator (progress) returning the
        DVC of the original pair ``(G, F)`` (and its mask) on ``initial``'s grid from its values,
        at the nodes of ``active`` only (the others ``Status.NOT_COMPUTED``), every subvolume
        weighted by ``weights`` (shape ``(subvolume,)*3``): :class:`ArrayMatcher` in memory,
        the tiled back-end's block by block.
    field : DisplacementField
        The field whose values start the matches (its grid is the matches' grid).
    nodes : ndarray of bool, shape of the grid
        The nodes to re-match.
    normals : ndarray, shape (nz, ny, nx, 3)
        The plane's normal per node (:func:`plane_normals`).
    params : CorrelationParams
        The first run's parameters.

    Returns
    -------
    matched : DisplacementField
        On ``field``'s grid: the oriented matches at ``nodes``, ``Status.NOT_COMPUTED`` elsewhere.
    runs : OrientedRuns
        The direction each node was matched with and each direction's window (what
        :func:`deblur_matches` takes the blur of).
    """
    nodes = np.asarray(nodes, bool)
    if nodes.shape != field.shape:
        raise ValueError(f"nodes {nodes.shape} must have the field's grid shape {field.shape}")
    directions = direction_set(tolerance)
    direction = np.where(nodes, quantise(normals, directions), -1)
    match_params, across, along = oriented_params(params)
    room = border_room(field, match.shape)
    result = None
    runs = OrientedRuns(direction, {}, {}, along)
    used = np.unique(direction[direction >= 0])
    for number, k in enumerate(used):
        yield Progress("oriented", number, len(used), f"direction {number + 1} of {len(used)}")
        group = direction == k
        half = group_half(room, group, params)
        weights = oriented_window(half, directions[k], across, along, WINDOW_TRUNCATE)
        runs.half[int(k)], runs.moments[int(k)] = half, window_moments(weights)
        run = yield from match(match_params.replace(subvolume=2 * half + 1), field, group, weights)
        result = run if result is None else _merge(result, run, group)
    if result is None:
        raise ValueError("no node to re-match with an oriented window")
    yield Progress("oriented", len(used), len(used), f"{int(nodes.sum())} nodes re-matched")
    return result, runs


@dataclasses.dataclass(frozen=True)
class OrientedRuns:
    """What :func:`oriented_rematch` ran, whatever the matcher: each node's direction and, per
    direction, the window of its run.

    Attributes
    ----------
    direction : ndarray of int, shape of the grid
        The direction index (into :func:`direction_set`) each node was matched with (-1: not
        matched).
    half : dict of int to int
        Per direction index, the run's box half-width (voxels; :func:`group_half`).
    moments : dict of int to ndarray, shape (3, 3)
        Per direction index, the second moments (voxel², z, y, x) of the run's window
        (:func:`.oriented_deblur.window_moments`).
    along : float
        The windows' standard deviation along the plane (voxels).
    """

    direction: np.ndarray
    half: dict
    moments: dict
    along: float

    def node_moments(self) -> np.ndarray:
        """Per node, the moments of the window it was matched with (0 where not matched);
        shape ``direction.shape + (3, 3)``."""
        moments = np.zeros(self.direction.shape + (3, 3))
        for k, value in self.moments.items():
            moments[self.direction == k] = value
        return moments


def group_half(room: np.ndarray, group: np.ndarray, params: CorrelationParams) -> int:
    """The box half-width of one direction's run: :func:`oriented_params`' box, shrunk to what
    the group's nodes have room for (``room``: :func:`border_room`), never below the first run's."""
    return int(np.clip(room[group].min(), params.half, oriented_params(params)[0].half))


def deblur_matches(matched: DisplacementField, took: np.ndarray, runs: OrientedRuns, normals):
    """The oriented matches at ``took`` less their windows' blur
    (:func:`.oriented_deblur.deblur_across`; each node with the moments of the window its
    direction's run used, from ``runs``: :func:`oriented_rematch`'s). Returns the
    displacements and the nodes deblurred."""
    points = matched.points.reshape(*matched.shape, 3)
    return deblur_across(
        matched.u, points, took, normals, runs.node_moments(), matched.step, runs.along
    )


class ArrayMatcher:
    """:func:`oriented_rematch`'s matcher of a pair of arrays: :func:`.correlate.correlate_iter`.

    ``F``'s coefficients (``coef_deformed``, or computed here) and, below the size where a level
    computes it on demand, ``∇G`` are computed once for every direction's run (the same
    volumes); they are let go with the matcher.

    Parameters
    ----------
    reference, deformed : ndarray, shape (nz, ny, nx)
        The original pair ``G``, ``F``.
    mask : ndarray, shape (nz, ny, nx), optional
        Reference-space material mask (non-zero = inside).
    coef_deformed : ndarray, float32, shape (nz, ny, nx), optional
        ``F``'s B-spline coefficients (:func:`.interpolation.prefilter`), when already held.
    noise_hint : float, optional
        As :func:`.correlate.correlate_iter`'s.
    """

    def __init__(self, reference, deformed, mask=None, *, coef_deformed=None, noise_hint=None):
        self.shape = tuple(int(n) for n in np.shape(reference))
        self._pair = (reference, deformed, mask)
        self._noise_hint = noise_hint
        gradient = None
        if np.size(reference) < GRADIENT_ON_DEMAND_FROM:
            gradient = gradient_volume(prefilter(np.asarray(reference, np.float32)))
        if coef_deformed is None:
            coef_deformed = prefilter(np.asarray(deformed, np.float32))
        self._shared = Prefiltered(gradient=gradient, coef_deformed=coef_deformed)

    def __call__(self, params, initial, active, weights):
        reference, deformed, mask = self._pair
        return correlate_iter(
            reference, deformed, params, mask=mask,
            grid=(initial.origin, initial.step, initial.shape), initial=initial, active=active,
            weights=weights, noise_hint=self._noise_hint, prefiltered=self._shared,
        )  # fmt: skip


def border_room(field: DisplacementField, shape) -> np.ndarray:
    """Per node, the largest box half-width (voxels) that fits in volumes of ``shape``."""
    points = field.points.reshape(*field.shape, 3)
    high = np.asarray(shape, np.float64) - 1.0 - points
    return np.floor(np.minimum(points, high).min(axis=-1)).astype(np.int64)


def _merge(into: DisplacementField, run: DisplacementField, take: np.ndarray):
    merged = into.copy()
    for name in ("u", "zncc", "status", "iterations", "gradient", "uncertainty"):
        target, source = getattr(merged, name, None), getattr(run, name, None)
        if target is not None and source is not None:
            target[take] = source[take]
    return merged


@dataclasses.dataclass
class OrientedStep:
    """What :func:`oriented_step` did: the field after it (the input where nothing changed) and
    a summary for ``metadata["correction"]["oriented"]``."""

    field: DisplacementField
    local: np.ndarray
    moved: object
    residual: float
    summary: dict

    @property
    def applied(self) -> bool:
        return bool(self.summary.get("accepted_nodes", 0))


def oriented_step(
    volumes, judge, current, local_current, params, excluded, moved, residual
) -> Generator[Progress, None, OrientedStep]:
    """The self-correction's oriented step, after its passes.

    It runs where the first run matched first-order cubes and the field after the passes still
    bends them by more than :data:`.pass_method.CURVATURE_VOXELS`, whatever the passes' own
    order (after second-order 15³ passes too, which leave a narrow band's bias
    and, on held-out bands, scatter of their own; docs/heldout.md), on the nodes whose variation
    is planar (:func:`plane_normals`, planarity >= :data:`PLANARITY`) and not ``excluded``
    (masked, cracked, shielded). Those nodes are re-matched on the original pair under oriented
    windows (:func:`oriented_rematch`) from the current values; the new values go through the
    correction's local acceptance (:func:`.acceptance.accept_locally`), failed matches refused.
    The planning (normals, directions, nodes, boxes, acceptance) is this one code path for every
    volume back-end; only the matches differ: ``volumes``' matcher of the original pair
    (:meth:`.volumes.CorrectionVolumes.original_matcher`: the whole arrays in memory, batch by
    batch with each box's margins in the tiled back-end, which then gives the in-memory step's
    nodes and counts, and its values but where a chain of repaired matches crosses a batch face,
    as in any tiled DVC; ``docs/method.md``). Where the step does not run, the summary says why.
    """
    started = time.perf_counter()
    unchanged = OrientedStep(current, local_current, moved, residual, {"ran": False})
    bend = field_curvature(current, params.half)
    if params.order != 1 or bend <= CURVATURE_VOXELS:
        unchanged.summary["reason"] = (
            "the first run's own boxes follow the field (second order, or no bend above "
            f"{CURVATURE_VOXELS:g} voxel)"
        )
        return unchanged
    good = np.isin(current.status, [int(s) for s in GOOD_STATUSES]) & ~excluded
    good &= np.all(np.isfinite(current.u), axis=-1)
    if min(current.shape) < 3 or not good.any():
        unchanged.summary["reason"] = "too few nodes to find a plane"
        return unchanged
    normals, planarity, _ = plane_normals(current, usable=good)
    nodes = good & (planarity >= PLANARITY)
    nodes &= border_room(current, volumes.shape) >= params.half
    if not nodes.any():
        unchanged.summary["reason"] = f"no node varies across a plane (planarity < {PLANARITY:g})"
        return unchanged
    # the matcher (and what it holds: F's coefficients, ∇G) lives as long as the re-match
    matched, runs = yield from oriented_rematch(
        volumes.original_matcher(), current, nodes, normals, params
    )
    candidate = current.copy()
    took = nodes & np.isin(matched.status, [int(s) for s in GOOD_STATUSES])
    deblurred, sharpened = deblur_matches(matched, took, runs, normals)
    candidate.u[took] = deblurred[took]
    if candidate.gradient is not None and matched.gradient is not None:
        candidate.gradient[took] = matched.gradient[took]
    mixed, local_mixed, accept, improved = accept_locally(
        judge, current, local_current, candidate, refuse=~took
    )
    match_params, across, along = oriented_params(params)
    summary = {
        "ran": True,
        "reason": (
            f"the field still bends a first-order {params.subvolume}³ subvolume by {bend:.2g} "
            "voxel after the passes: planar nodes re-matched on the original pair "
            f"under windows of std {across:g} voxels across the field's plane, {along:g} along "
            f"it, first order on {match_params.subvolume}³ boxes, less the windows' blur (from "
            "the matches' local quadratic)"
        ),
        "planar_nodes": int(nodes.sum()),
        "deblurred_nodes": int(sharpened.sum()),
        "matched_nodes": int(took.sum()),
        "accepted_nodes": int(accept.sum()),
        "improved_nodes": int(improved.sum()),
        "directions": len(runs.half),
        "across": float(across),
        "along": float(along),
        "subvolume": int(match_params.subvolume),
    }
    if not accept.any():
        unchanged.summary = summary
        return unchanged
    mixed = mixed.copy()
    for name in ("zncc", "status", "iterations"):
        getattr(mixed, name)[accept] = getattr(matched, name)[accept]
    volumes.release(moved)
    moved, residual = yield from volumes.align(mixed)
    summary["seconds"] = time.perf_counter() - started
    return OrientedStep(mixed, local_mixed, moved, residual, summary)
