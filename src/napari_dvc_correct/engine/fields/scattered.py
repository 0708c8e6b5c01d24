"""Fields on scattered points: the companion of :class:`.field.DisplacementField`.

Other DVC tools (and a user's own list of points of interest) give a displacement at points that
need not form a regular grid. :class:`ScatteredField` holds such a field as it came, in the order
it came; the grid model stays the one the correction and the evaluation work on, and two functions
go between them:

* :func:`to_grid` — onto a regular grid: exactly when the points already form one (any order),
  otherwise by piecewise-linear interpolation over a Delaunay triangulation of the usable points,
  with every node's :class:`.field.Provenance` saying whether it was measured there or
  ``INTERPOLATED`` (nodes outside the points' convex hull are ``NOT_COMPUTED``);
* :func:`sample_field` — a grid field read back at any points (trilinear, or exact at nodes), so a
  corrected field is reported at the user's original points too.

Conventions as everywhere: positions and displacements ``(z, y, x)`` in reference voxels.
Pure numpy/scipy.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .field import (
    DisplacementField,
    NodeCounts,
    Provenance,
    Status,
    node_counts,
    usable_nodes,
)


@dataclass
class ScatteredField:
    """A displacement field at ``N`` arbitrary points, with per-point quality.

    Parameters
    ----------
    points : ndarray, shape (N, 3), float64
        Positions ``(z, y, x)`` in reference voxels (0-based: voxel ``i`` is centred at ``i``).
    u : ndarray, shape (N, 3), float64
        Displacement ``(uz, uy, ux)`` in voxels; NaN where the point has no value.
    zncc : ndarray, shape (N,), float32, optional
        ZNCC of the match in [-1, 1], NaN where unknown.
    status : ndarray, shape (N,), uint8, optional
        :class:`.field.Status` codes (default ``CONVERGED`` where ``u`` is finite, else
        ``NOT_COMPUTED``).
    iterations : ndarray, shape (N,), int32, optional
    provenance : ndarray, shape (N,), uint8, optional
        :class:`.field.Provenance` codes.
    gradient : ndarray, shape (N, 3, 3), optional
        Displacement gradient ``du_i/dX_j`` (z, y, x order).
    uncertainty : ndarray, shape (N, 3), optional
        Each point's match uncertainty (standard deviation of ``(uz, uy, ux)``, voxels; NaN
        where unknown), as :class:`.field.DisplacementField` records it.
    params, metadata : dict
        As in :class:`.field.DisplacementField`; ``metadata["source"]`` names the file format
        a field was read from.
    """

    points: np.ndarray
    u: np.ndarray
    zncc: np.ndarray | None = None
    status: np.ndarray | None = None
    iterations: np.ndarray | None = None
    provenance: np.ndarray | None = None
    gradient: np.ndarray | None = None
    params: dict = field(default_factory=dict)
    metadata: dict = field(default_factory=dict)
    uncertainty: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.points = np.asarray(self.points, dtype=np.float64)
        if self.points.ndim != 2 or self.points.shape[1] != 3:
            raise ValueError(f"points must have shape (N, 3), got {self.points.shape}")
        if not np.all(np.isfinite(self.points)):
            bad = np.flatnonzero(~np.all(np.isfinite(self.points), axis=1))
            raise ValueError(
                f"point positions must be finite: {len(bad)} of {len(self.points)} are not (the "
                f"first is point {bad[0]} counted from 0 in the file's order, at "
                f"{self.points[bad[0]].tolist()})"
            )
        n = len(self.points)
        self.u = np.asarray(self.u, dtype=np.float64)
        if self.u.shape != (n, 3):
            raise ValueError(f"u must have shape ({n}, 3), got {self.u.shape}")
        finite = np.all(np.isfinite(self.u), axis=1)
        if self.zncc is None:
            self.zncc = np.full(n, np.nan, np.float32)
        if self.status is None:
            self.status = np.where(finite, Status.CONVERGED, Status.NOT_COMPUTED)
        if self.iterations is None:
            self.iterations = np.zeros(n, np.int32)
        if self.provenance is None:
            self.provenance = np.where(finite, Provenance.MEASURED, Provenance.NOT_COMPUTED)
        self.zncc = np.asarray(self.zncc, dtype=np.float32).reshape(-1)
        self.status = np.asarray(self.status, dtype=np.uint8).reshape(-1)
        self.iterations = np.asarray(self.iterations, dtype=np.int32).reshape(-1)
        self.provenance = np.asarray(self.provenance, dtype=np.uint8).reshape(-1)
        for name in ("zncc", "status", "iterations", "provenance"):
            if len(getattr(self, name)) != n:
                raise ValueError(f"{name} must have {n} entries, got {len(getattr(self, name))}")
        if self.uncertainty is not None:
            self.uncertainty = np.asarray(self.uncertainty, dtype=np.float64)
            if self.uncertainty.shape != (n, 3):
                raise ValueError(
                    f"uncertainty must have shape ({n}, 3), got {self.uncertainty.shape}"
                )
        if self.gradient is not None:
            self.gradient = np.asarray(self.gradient, dtype=np.float64)
            if self.gradient.shape != (n, 3, 3):
                raise ValueError(f"gradient must have shape ({n}, 3, 3), got {self.gradient.shape}")

    @property
    def n_points(self) -> int:
        return len(self.points)

    @property
    def valid(self) -> np.ndarray:
        """Points holding a usable displacement (same rule as :attr:`DisplacementField.valid`)."""
        return usable_nodes(self.status, self.provenance, self.u)

    def status_counts(self) -> dict[str, int]:
        """Number of points of each status, by readable name (only the statuses present)."""
        codes, counts = np.unique(self.status, return_counts=True)
        return {Status(int(c)).label: int(n) for c, n in zip(codes, counts)}

    def node_counts(self) -> NodeCounts:
        """Usable, matched and filled-in points, and the counts by status (:class:`NodeCounts`)."""
        return node_counts(self.status, self.provenance, self.u)

    def copy(self) -> ScatteredField:
        """Deep copy (arrays and dictionaries)."""
        return copy.deepcopy(self)

    def __repr__(self) -> str:
        return f"ScatteredField(n_points={self.n_points}, valid={int(self.valid.sum())})"


def from_grid(grid_field: DisplacementField) -> ScatteredField:
    """The nodes of a grid field as scattered points (C order of the grid), values unchanged."""
    n = grid_field.n_points
    return ScatteredField(
        points=grid_field.points,
        u=grid_field.displacement.copy(),
        zncc=grid_field.zncc.reshape(n).copy(),
        status=grid_field.status.reshape(n).copy(),
        iterations=grid_field.iterations.reshape(n).copy(),
        provenance=grid_field.provenance.reshape(n).copy(),
        gradient=None if grid_field.gradient is None else grid_field.gradient.reshape(n, 3, 3),
        params=copy.deepcopy(grid_field.params),
        metadata=copy.deepcopy(grid_field.metadata),
        uncertainty=None
        if grid_field.uncertainty is None
        else grid_field.uncertainty.reshape(n, 3).copy(),
    )


def regular_grid_of(points: np.ndarray, tolerance: float = 1e-6):
    """The regular grid the points form, if they form one exactly (each node once, any order).

    Parameters
    ----------
    points : ndarray, shape (N, 3)
        ``(z, y, x)`` positions, voxels.
    tolerance : float
        Largest distance (voxels) between a point and its node.

    Returns
    -------
    (origin, step, shape, index) or None
        ``index[n]`` is the flat C-order node of point ``n``; None when the points are not a full
        regular grid.
    """
    points = np.asarray(points, dtype=np.float64)
    origin, step, shape, ijk = [], [], [], []
    for axis in range(3):
        values = np.sort(points[:, axis])
        breaks = np.flatnonzero(np.diff(values) > tolerance)
        levels = np.r_[values[0], values[breaks + 1]]
        if len(levels) == 1:
            spacing = 1.0
        else:
            gaps = np.diff(levels)
            spacing = float(np.mean(gaps))
            if np.max(np.abs(gaps - spacing)) > tolerance:
                return None
        position = (points[:, axis] - levels[0]) / spacing
        index = np.rint(position)
        if np.max(np.abs(position - index) * spacing) > tolerance:
            return None
        origin.append(float(levels[0]))
        step.append(spacing)
        shape.append(len(levels))
        ijk.append(index.astype(np.int64))
    shape = tuple(shape)
    if int(np.prod(shape)) != len(points):
        return None
    flat = np.ravel_multi_index(tuple(ijk), shape)
    if len(np.unique(flat)) != len(points):
        return None
    return tuple(origin), tuple(step), shape, flat


def default_grid(points: np.ndarray, step=None) -> tuple[tuple, tuple, tuple]:
    """A whole-voxel grid ``(origin, step, shape)`` over the points' bounding box.

    ``step`` (voxels, int or 3 ints) defaults to the median distance from a point to its nearest
    neighbour, rounded to a whole voxel (at least 1).
    """
    points = np.asarray(points, dtype=np.float64)
    if step is None:
        if len(points) < 2:
            step = 1
        else:
            from scipy import spatial  # here: scipy.spatial is slow to import (CLI start-up)

            distance, _ = spatial.cKDTree(points).query(points, k=2)
            step = max(1, int(round(float(np.median(distance[:, 1])))))
    steps = np.broadcast_to(np.asarray(step, dtype=np.int64), (3,))
    if np.any(steps < 1):
        raise ValueError(f"grid step must be >= 1 voxel, got {step}")
    low = np.ceil(points.min(axis=0) - 1e-9)
    high = np.floor(points.max(axis=0) + 1e-9)
    shape = np.maximum(1, (high - low) // steps + 1).astype(int)
    return (
        tuple(float(v) for v in low),
        tuple(float(s) for s in steps),
        tuple(int(n) for n in shape),
    )


def to_grid(scattered: ScatteredField, grid=None, tolerance: float = 1e-6) -> DisplacementField:
    """The scattered field on a regular grid, with each node's provenance.

    Parameters
    ----------
    scattered : ScatteredField
    grid : (origin, step, shape), optional
        Target grid (voxels). Default: the points' own grid when they form one (then no value is
        interpolated), else :func:`default_grid`.
    tolerance : float
        Distance (voxels) under which a node counts as one of the points.

    Returns
    -------
    DisplacementField
        Nodes that coincide with a point carry its values and provenance; the others are
        interpolated piecewise-linearly from the usable points (``Provenance.INTERPOLATED``,
        status ``CONVERGED``, ZNCC interpolated too), or ``NOT_COMPUTED`` (NaN) outside their
        convex hull. ``metadata["scattered"]`` counts both.
    """
    metadata = copy.deepcopy(scattered.metadata)
    if grid is None:
        exact = regular_grid_of(scattered.points, tolerance)
        if exact is not None:
            origin, step, shape, index = exact
            order = np.argsort(index)
            g, sigma = scattered.gradient, scattered.uncertainty
            metadata["scattered"] = {"n_points": scattered.n_points, "interpolated": 0}
            return DisplacementField(
                origin=origin,
                step=step,
                u=scattered.u[order].reshape(*shape, 3),
                zncc=scattered.zncc[order].reshape(shape),
                status=scattered.status[order].reshape(shape),
                iterations=scattered.iterations[order].reshape(shape),
                provenance=scattered.provenance[order].reshape(shape),
                gradient=None if g is None else g[order].reshape(*shape, 3, 3),
                params=copy.deepcopy(scattered.params),
                metadata=metadata,
                uncertainty=None if sigma is None else sigma[order].reshape(*shape, 3),
            )
        grid = default_grid(scattered.points)
    origin, step, shape = grid
    target = DisplacementField.zeros(origin, step, shape)
    nodes = target.points
    n_nodes = len(nodes)
    u = np.full((n_nodes, 3), np.nan)
    zncc = np.full(n_nodes, np.nan, np.float32)
    status = np.full(n_nodes, int(Status.NOT_COMPUTED), np.uint8)
    iterations = np.zeros(n_nodes, np.int32)
    provenance = np.full(n_nodes, int(Provenance.NOT_COMPUTED), np.uint8)
    usable = scattered.valid
    # nodes sitting on one of the points keep that point's values
    from scipy import spatial  # here: scipy.spatial is slow to import (CLI start-up)

    distance, nearest = spatial.cKDTree(scattered.points).query(nodes)
    on_point = distance <= tolerance
    source = nearest[on_point]
    u[on_point] = scattered.u[source]
    zncc[on_point] = scattered.zncc[source]
    status[on_point] = scattered.status[source]
    iterations[on_point] = scattered.iterations[source]
    provenance[on_point] = scattered.provenance[source]
    # a node on a point keeps its match's uncertainty; an interpolated node has none (NaN)
    uncertainty = None
    if scattered.uncertainty is not None:
        uncertainty = np.full((n_nodes, 3), np.nan)
        uncertainty[on_point] = scattered.uncertainty[source]
    todo = ~on_point
    if todo.any() and usable.sum() >= 4:
        known = scattered.points[usable]
        values = np.column_stack([scattered.u[usable], scattered.zncc[usable].astype(np.float64)])
        try:
            triangulation = spatial.Delaunay(known)
        except spatial.QhullError as error:
            raise ValueError(
                "the field's usable points are all in one plane or line and not on a regular "
                "grid: they span no volume to interpolate in (a 2-D result, or columns read "
                "in the wrong order?); a 3-D field is needed"
            ) from error
        interpolated = np.full((n_nodes, 4), np.nan)
        interpolated[todo] = _linear(triangulation, values, nodes[todo])
        inside = todo & np.all(np.isfinite(interpolated[:, :3]), axis=1)
        u[inside] = interpolated[inside, :3]
        zncc[inside] = interpolated[inside, 3].astype(np.float32)
        status[inside] = int(Status.CONVERGED)
        provenance[inside] = int(Provenance.INTERPOLATED)
    else:
        inside = np.zeros(n_nodes, bool)
    metadata["scattered"] = {
        "n_points": scattered.n_points,
        "interpolated": int(inside.sum()),
        "outside_hull": int((todo & ~inside).sum()),
    }
    return DisplacementField(
        origin=origin,
        step=step,
        u=u.reshape(*shape, 3),
        zncc=zncc.reshape(shape),
        status=status.reshape(shape),
        iterations=iterations.reshape(shape),
        provenance=provenance.reshape(shape),
        params=copy.deepcopy(scattered.params),
        metadata=metadata,
        uncertainty=None if uncertainty is None else uncertainty.reshape(*shape, 3),
    )


def _linear(triangulation, values: np.ndarray, query: np.ndarray) -> np.ndarray:
    """Barycentric (piecewise-linear) interpolation; NaN outside the hull."""
    simplex = triangulation.find_simplex(query)
    out = np.full((len(query), values.shape[1]), np.nan)
    inside = simplex >= 0
    transform = triangulation.transform[simplex[inside]]
    delta = query[inside] - transform[:, 3]
    bary = np.einsum("nij,nj->ni", transform[:, :3], delta)
    weights = np.column_stack([bary, 1.0 - bary.sum(axis=1)])
    vertices = triangulation.simplices[simplex[inside]]
    out[inside] = np.einsum("nk,nkc->nc", weights, values[vertices])
    return out


def sample_field(
    grid_field: DisplacementField, points: np.ndarray, tolerance: float = 1e-6
) -> ScatteredField:
    """A grid field read at arbitrary points.

    Parameters
    ----------
    grid_field : DisplacementField
    points : ndarray, shape (N, 3)
        ``(z, y, x)`` positions, voxels.
    tolerance : float
        A point within this distance (voxels) of a node takes that node's values exactly.

    Returns
    -------
    ScatteredField
        Displacement (and gradient, if the field has one) trilinear between the 8 surrounding
        nodes; NaN and ``NOT_COMPUTED`` where a surrounding node is unusable or the point lies
        outside the grid. Status, ZNCC and iterations are those of the nearest node; provenance is
        the node's on a node and ``INTERPOLATED`` elsewhere.
    """
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must have shape (N, 3), got {points.shape}")
    shape = np.array(grid_field.shape)
    index = (points - np.asarray(grid_field.origin)) / np.asarray(grid_field.step)
    inside = np.all((index >= -tolerance) & (index <= shape - 1 + tolerance), axis=1)
    index = np.clip(index, 0, shape - 1)
    nearest = np.rint(index).astype(np.int64)
    on_node = inside & np.all(
        np.abs(index - nearest) * np.asarray(grid_field.step) <= tolerance, axis=1
    )
    flat = np.ravel_multi_index(tuple(nearest.T), grid_field.shape)
    from scipy import ndimage  # here: keeps importing this module (and the CLI) quick

    usable = grid_field.valid
    u = np.full((len(points), 3), np.nan)
    coords = index.T
    for c in range(3):
        component = np.where(usable, grid_field.u[..., c], np.nan)
        u[:, c] = ndimage.map_coordinates(component, coords, order=1, mode="nearest")
    gradient = None
    if grid_field.gradient is not None:
        gradient = np.full((len(points), 3, 3), np.nan)
        for i in range(3):
            for j in range(3):
                component = np.where(usable, grid_field.gradient[..., i, j], np.nan)
                gradient[:, i, j] = ndimage.map_coordinates(
                    component, coords, order=1, mode="nearest"
                )
    # exact values on nodes (no rounding through the interpolation)
    u[on_node] = grid_field.displacement[flat[on_node]]
    u[~inside] = np.nan
    status = grid_field.status.reshape(-1)[flat].copy()
    provenance = np.where(
        on_node, grid_field.provenance.reshape(-1)[flat], int(Provenance.INTERPOLATED)
    ).astype(np.uint8)
    missing = ~np.all(np.isfinite(u), axis=1)
    status[missing & (status == int(Status.CONVERGED))] = int(Status.NOT_COMPUTED)
    provenance[missing] = int(Provenance.NOT_COMPUTED)
    if gradient is not None:
        gradient[on_node] = grid_field.gradient.reshape(-1, 3, 3)[flat[on_node]]
        gradient[missing] = np.nan
    metadata: dict[str, Any] = copy.deepcopy(grid_field.metadata)
    uncertainty = None
    if grid_field.uncertainty is not None:  # a match's own where a point sits on its node
        uncertainty = np.full((len(points), 3), np.nan)
        uncertainty[on_node] = grid_field.uncertainty.reshape(-1, 3)[flat[on_node]]
        uncertainty[missing] = np.nan
    metadata["sampled_from_grid"] = {
        "origin": list(grid_field.origin),
        "step": list(grid_field.step),
        "shape": list(grid_field.shape),
    }
    return ScatteredField(
        points=points.copy(),
        u=u,
        zncc=grid_field.zncc.reshape(-1)[flat],
        status=status,
        iterations=grid_field.iterations.reshape(-1)[flat],
        provenance=provenance,
        gradient=gradient,
        params=copy.deepcopy(grid_field.params),
        metadata=metadata,
        uncertainty=uncertainty,
    )
