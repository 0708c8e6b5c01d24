"""How each correcting match matches, node by node, from its predicted error.

:func:`.pass_method.pass_method` chooses one order and subvolume for a whole pass from the
field's curvature (its 90th percentile) and the first run's median uncertainty. A field that
bends in a narrow band is curved at a few nodes only; elsewhere the small second-order subvolume
chosen for the band adds matching noise and removes no bias. Here the same prediction is made at
each node, from that node's bend (:func:`.pass_method.node_bend`) and its first-run uncertainty
``σ``: for each way to match (first order on the first run's subvolume ``S``, second order on
``S``, second order on the pass's smaller ``s``) the bias the bend leaves and the scatter
``σ (S / n)^(3/2)`` (times the second-order gain) a subvolume of edge ``n`` has, added in
quadrature (:func:`.pass_method.predicted_error`). The smallest wins, and another way than the
first run's only where its error is under :data:`.pass_method.CHANGE_MARGIN` of the first run's
(the paper's rule, as for the whole pass). A subvolume is never shrunk below what the noise
allows: a smaller one is chosen only where its predicted error, noise included, is smaller.

Each correcting node is matched once per pass: one DVC run per way to match, over disjoint sets
of the pass grid's nodes (:func:`correlate_regions`), merged into one correcting field that the
acceptance judges as a whole. Displacements in voxels, axes (z, y, x).
"""

from __future__ import annotations

from collections.abc import Callable, Generator
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from ..correlation.params import CorrelationParams
from ..fields.field import DisplacementField
from .pass_method import (
    CHANGE_MARGIN,
    SECOND_ORDER_BIAS,
    SECOND_ORDER_NOISE_GAIN,
    node_bend,
    node_second_differences,
)


@dataclass(frozen=True)
class PassRegions:
    """The ways the correcting matches of a pass match, and which node takes which.

    Attributes
    ----------
    methods : tuple of CorrelationParams
        The ways to match; ``methods[0]`` is the pass's own (:func:`.pass_method.pass_method`).
    choice : ndarray of int, the field's grid shape
        Index into ``methods`` of each node's predicted-best way to match.
    predicted : ndarray, the field's grid shape + (len(methods),)
        Each node's predicted error of each way (voxels).
    """

    methods: tuple
    choice: np.ndarray
    predicted: np.ndarray

    @property
    def half(self) -> np.ndarray:
        """Half-size of each node's correcting subvolume (voxels, the field's grid shape)."""
        halves = np.array([m.half for m in self.methods])
        return halves[self.choice]

    @property
    def largest_half(self) -> int:
        """The largest half-size in use (voxels): the reach of a selective pass."""
        return int(max(self.methods[int(k)].half for k in np.unique(self.choice)))

    def counts(self) -> dict:
        """Nodes per way to match, keyed ``"order <o>, <n>³"`` (for the record)."""
        counts = np.bincount(self.choice.reshape(-1), minlength=len(self.methods))
        return {
            f"order {m.order}, {m.subvolume}³": int(c) for m, c in zip(self.methods, counts) if c
        }

    def describe(self) -> str:
        """One line for the user: how many nodes match which way, and why."""
        parts = ", ".join(f"{n} nodes {k}" for k, n in self.counts().items())
        return f"per node by predicted error (the node's bend against its noise): {parts}"

    def bend(self, field: DisplacementField) -> np.ndarray:
        """:func:`.pass_method.node_bend` of ``field`` over each node's own correcting
        subvolume (voxels, the field's grid shape; the bend grows as the half-size squared)."""
        return node_bend(field, 1) * self.half.astype(np.float64) ** 2


def curvature_change(field: DisplacementField, half: int) -> np.ndarray:
    """What a second-order shape function on a subvolume of half-size ``half`` cannot follow at
    each node (voxels, ``field.shape``; NaN where some node is not finite).

    A quadratic shape function follows a constant curvature exactly (the bending of a beam, a
    uniform strain gradient); it leaves what the curvature changes across the subvolume. Over
    the nodes whose positions lie inside the subvolume (``floor(half / step)`` steps per axis,
    at least one) that is half the range of each second derivative
    (:func:`.pass_method.node_second_differences`: the best constant curvature misses it by
    that much), as a bend ``range / 2 · half² / 2``, the largest over components and axes.
    """
    second = node_second_differences(field)
    if second is None:
        return np.full(field.shape, np.nan)
    reach = np.maximum(1, np.floor(half / np.asarray(field.step, np.float64))).astype(int)
    size = tuple(2 * int(r) + 1 for r in reach) + (1,)
    change = np.zeros(field.shape)
    for values in second:
        spread = ndimage.maximum_filter(values, size=size, mode="nearest")
        spread = spread - ndimage.minimum_filter(values, size=size, mode="nearest")
        change = np.maximum(change, 0.5 * np.max(spread, axis=-1))
    return 0.5 * change * float(half) ** 2


def node_predicted_error(
    field: DisplacementField, sigma: np.ndarray, params: CorrelationParams, method
) -> np.ndarray:
    """Predicted error (voxels, ``field.shape``) at each node of correcting matches made
    ``method``'s way (order and subvolume), the first run having used ``params``.

    Bias: first order leaves the bend :func:`.pass_method.node_bend` over ``method``'s
    subvolume; second order :data:`.pass_method.SECOND_ORDER_BIAS` of what the curvature changes
    across it (:func:`curvature_change`; the share a second-order match still leaves, measured
    on a narrow band in docs/method.md). Scatter: the node's first-run uncertainty ``sigma``
    (norm) times ``(S / n)^(3/2)`` for a subvolume of edge ``n`` instead of ``S``, and
    :data:`.pass_method.SECOND_ORDER_NOISE_GAIN` for second order. Root of the sum of squares.
    """
    scatter = sigma * (float(params.subvolume) / float(method.subvolume)) ** 1.5
    if method.order == 1:
        bias = node_bend(field, method.half)
    else:
        scatter = scatter * SECOND_ORDER_NOISE_GAIN
        bias = SECOND_ORDER_BIAS * curvature_change(field, method.half)
    return np.hypot(bias, scatter)


def pass_regions(
    field: DisplacementField, params: CorrelationParams, pass_params: CorrelationParams
) -> PassRegions | None:
    """Each node's way to match in the correcting passes, by its own predicted error.

    Only where the pass itself changes the first run's way to match (``pass_params`` differs
    from ``params``, first order on the first run's subvolume): a pass that keeps the first
    run's parameters keeps them everywhere. The ways weighed are first order on
    ``params.subvolume``, second order on it, and ``pass_params`` (see the module); a node
    without a finite bend or uncertainty takes ``pass_params``'s (no prediction). ``None`` where
    nothing is chosen per node (the pass's parameters, or every node takes ``pass_params``).

    Parameters
    ----------
    field : DisplacementField
        The cleaned input field, with the first run's match uncertainties.
    params : CorrelationParams
        The first run's parameters.
    pass_params : CorrelationParams
        The pass's own way to match (:func:`.pass_method.pass_method`).
    """
    if pass_params == params or params.order != 1 or field.uncertainty is None:
        return None
    sigma = np.linalg.norm(np.asarray(field.uncertainty, np.float64), axis=-1)
    known = np.isfinite(sigma) & np.isfinite(node_bend(field, params.half))
    if not known.any():
        return None
    methods = [pass_params]
    for candidate in (params.replace(order=2),):
        if candidate not in methods:
            methods.append(candidate)
    predicted = np.stack([node_predicted_error(field, sigma, params, m) for m in methods], -1)
    # the faces' curvature is bent by the smoothing's border handling (as in
    # :func:`.pass_method.field_curvature`): a face node takes its inner neighbour's bias
    inner = np.ix_(*[np.clip(np.arange(n), 1, n - 2) if n >= 5 else np.arange(n) for n in field.shape])
    bias_free = np.stack(
        [node_predicted_error(field, 0 * sigma, params, m) for m in methods], -1
    )[inner]
    scatter = np.sqrt(np.maximum(predicted**2 - np.stack([node_predicted_error(field, 0 * sigma, params, m) for m in methods], -1) ** 2, 0))
    predicted = np.hypot(bias_free, scatter)
    best = np.argmin(np.where(np.isfinite(predicted), predicted, np.inf), axis=-1)
    choice = np.where(known, best, 0).astype(np.int64)
    if not np.any(choice):
        return None
    return PassRegions(tuple(methods), choice, predicted)


def grid_choice(
    regions: PassRegions, read_points: np.ndarray, pass_grid, volume_shape
) -> np.ndarray:
    """Which way each node of the pass grid matches (index into ``regions.methods``).

    A correcting node takes the choice of the field node that reads its update there (the node
    of the pass grid nearest to its read point ``X + D(X)``, or ``X``); where several do, the
    pass's own way wins; a node no field node reads takes the nearest read node's choice. A
    node whose subvolume would not fit in the volume keeps the pass's own way.

    Parameters
    ----------
    regions : PassRegions
        The field nodes' choices.
    read_points : ndarray (n, 3)
        Where each field node (C order) reads ``ΔD`` (voxels).
    pass_grid : (origin, step, shape)
        The correcting grid.
    volume_shape : tuple of 3 ints
        ``(nz, ny, nx)`` of the volumes.
    """
    origin, step, shape = pass_grid
    points = np.asarray(read_points, np.float64).reshape(-1, 3)
    index = np.rint((points - np.asarray(origin)) / np.asarray(step))
    inside = np.all(np.isfinite(index), axis=1)
    inside &= np.all((index >= 0) & (index < np.asarray(shape)), axis=1)
    index = index[inside].astype(np.intp)
    node_choice = regions.choice.reshape(-1)[inside]
    choice = np.full(shape, -1, np.int64)
    order = np.argsort(node_choice == 0, kind="stable")  # the pass's own way written last
    choice[tuple(index[order].T)] = node_choice[order]
    unread = choice < 0
    if unread.all():
        return np.zeros(shape, np.int64)
    if unread.any():
        nearest = ndimage.distance_transform_edt(
            unread, return_distances=False, return_indices=True
        )
        choice = choice[tuple(nearest)]
    # a subvolume that does not fit in the volume keeps the pass's own way
    centres = np.stack(
        np.meshgrid(*[o + s * np.arange(n) for o, s, n in zip(origin, step, shape)], indexing="ij"),
        axis=-1,
    )
    halves = np.array([m.half for m in regions.methods])[choice]
    upper = np.asarray(volume_shape, np.float64) - 1.0
    fits = np.all(
        (centres - halves[..., None] >= 0) & (centres + halves[..., None] <= upper), axis=-1
    )
    return np.where(fits, choice, 0)


def correlate_regions(
    run: Callable[[CorrelationParams, np.ndarray | None], Generator],
    regions: PassRegions | None,
    choice: np.ndarray | None,
    pass_params: CorrelationParams,
    active: np.ndarray | None,
) -> Generator:
    """One correcting field from one DVC run per way to match (a generator; returns it).

    ``run(params, active)`` is the pass's correcting DVC (a progress generator returning a
    :class:`DisplacementField` on the pass grid, ``Status.NOT_COMPUTED`` outside ``active``).
    Each way matches the nodes of ``active`` (all where None) that ``choice`` gives it; the
    results are merged node by node, each node from the run that matched it, so each node is
    matched once. Without ``regions`` this is ``run(pass_params, active)``.
    """
    if regions is None or choice is None:
        return (yield from run(pass_params, active))
    wanted = np.ones(choice.shape, bool) if active is None else np.asarray(active, bool)
    merged, timings = None, {}
    for k, method in enumerate(regions.methods):
        nodes = wanted & (choice == k)
        if not nodes.any() and not (k == 0 and merged is None and not wanted.any()):
            continue
        part = yield from run(method, nodes)
        for key, value in part.metadata.get("timings", {}).items():
            if isinstance(value, (int, float)):
                timings[key] = timings.get(key, 0) + value
        if merged is None:
            merged = part.copy()
            continue
        for name in ("u", "zncc", "status", "iterations", "provenance", "gradient", "uncertainty"):
            into, values = getattr(merged, name), getattr(part, name)
            if into is not None and values is not None:
                into[nodes] = values[nodes]
    if merged is None:  # nothing to match at all
        return (yield from run(pass_params, active))
    merged.metadata["timings"] = timings
    return merged
