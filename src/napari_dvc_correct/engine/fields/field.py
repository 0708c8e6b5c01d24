"""The one data model: a displacement field on a regular grid of points of interest.

Conventions: axis order ``(z, y, x)`` everywhere, vectors stored ``(..., 3)`` in the
same order, units are voxels of the reference volume. The displacement is Lagrangian: material at
reference position ``X`` moves to ``x = X + u(X)``, so ``F(X + u(X)) ≈ G(X)``.

Node ``(i, j, k)`` of the grid sits at ``origin + (i, j, k) * step`` (voxels). In napari a grid
quantity is an Image layer with ``scale = step`` and ``translate = origin``.

A field on scattered points (another tool's, or a list of points of interest) is a
:class:`.scattered.ScatteredField`; :func:`.scattered.to_grid` and :func:`.scattered.sample_field`
go between the two (node provenance ``INTERPOLATED``).
"""

from __future__ import annotations

import copy
import dataclasses
from dataclasses import dataclass, field
from enum import IntEnum
from typing import Any

import numpy as np


class Status(IntEnum):
    """Per-POI outcome of the matching, stored as ``uint8`` codes.

    The codes are part of the file format: never renumber, only append.
    """

    CONVERGED = 0
    MAX_ITERATIONS = 1
    DIVERGED = 2
    OUT_OF_BOUNDS = 3
    MASKED = 4
    LOW_TEXTURE = 5
    SINGULAR = 6
    LOW_ZNCC = 7
    OUTLIER_REPLACED = 8
    NOT_COMPUTED = 9
    #: The node's subvolume straddles a discontinuity of the material (a crack that opened or
    #: closed): its residual shows material that changed phase, which no continuous shape
    #: function explains (:func:`.acceptance.Judge.discontinuous`).
    DISCONTINUITY = 10

    @property
    def label(self) -> str:
        """Readable name for the UI and reports, e.g. ``"max iterations"``."""
        return self.name.lower().replace("_", " ")


class Provenance(IntEnum):
    """Where the value at a node comes from, stored as ``uint8`` codes (append only)."""

    MEASURED = 0
    REPLACED = 1
    CORRECTED = 2
    MASKED = 3
    NOT_COMPUTED = 4
    #: Interpolated onto this node from a field on other points (an imported scattered field).
    INTERPOLATED = 5

    @property
    def label(self) -> str:
        return self.name.lower().replace("_", " ")


#: Statuses whose displacement was measured by a match and can be trusted as such.
GOOD_STATUSES = (Status.CONVERGED, Status.MAX_ITERATIONS)


def usable_nodes(status: np.ndarray, provenance: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Nodes (or points) holding a usable displacement: measured with a good status, or filled
    in (replaced, corrected, interpolated) by post-processing, and finite. ``u`` is ``(..., 3)``."""
    measured_ok = np.isin(status, [int(s) for s in GOOD_STATUSES])
    filled = np.isin(
        provenance, [Provenance.REPLACED, Provenance.CORRECTED, Provenance.INTERPOLATED]
    )
    return (measured_ok | filled) & np.all(np.isfinite(u), axis=-1)


@dataclass(frozen=True)
class NodeCounts:
    """How many nodes (or points) hold a usable displacement, and why: the one definition of
    the "usable fraction" every summary prints next to the counts by status.

    A node is usable (:func:`usable_nodes`) when its match succeeded (status converged or max
    iterations) or when post-processing filled it in (replaced, corrected, interpolated); a
    filled node keeps the status of its failed match, so "diverged 5" and a usable fraction of
    1.000 agree when those 5 were filled in.

    Attributes
    ----------
    total : int
        Every node of the field (masked and not computed ones included).
    matched : int
        Usable nodes whose own match succeeded (status converged or max iterations).
    filled : int
        Usable nodes whose match failed (or never ran) and that post-processing filled in.
    statuses : dict of str -> int
        Nodes per status, by readable name (:attr:`Status.label`), the statuses present only.
    """

    total: int
    matched: int
    filled: int
    statuses: dict

    @property
    def usable(self) -> int:
        return self.matched + self.filled

    @property
    def usable_fraction(self) -> float:
        """Usable nodes / all nodes (NaN for an empty field)."""
        return self.usable / self.total if self.total else float("nan")

    def text(self) -> str:
        """One phrase, e.g. ``"usable 997 of 997 nodes (1.000): 992 matched, 5 filled in;
        status: converged 992, diverged 5"``."""
        statuses = ", ".join(f"{name} {n}" for name, n in self.statuses.items())
        return (
            f"usable {self.usable} of {self.total} nodes ({self.usable_fraction:.3f}): "
            f"{self.matched} matched, {self.filled} filled in; status: {statuses}"
        )

    def region_hint(self, region_given: bool) -> str | None:
        """A sentence suggesting a specimen region where at least :data:`NO_TEXTURE_SHARE` of
        the nodes found no texture and the run had no region (``region_given`` False); else
        None. Such nodes are mostly air or background around a specimen: cleaning fills them
        from their neighbours, and the correction and the evaluation count them, where a region
        would have left them out."""
        none = self.statuses.get(Status.LOW_TEXTURE.label, 0)
        if region_given or not self.total or none < NO_TEXTURE_SHARE * self.total:
            return None
        return (
            f"{none} of {self.total} nodes ({100 * none / self.total:.0f} %) found no texture "
            "to match (air or background around the specimen?): a specimen region (a mask, "
            "cylinder or box) leaves them out instead of filling them from their neighbours"
        )


#: The share of nodes without texture above which a run without a region suggests one
#: (:meth:`NodeCounts.region_hint`); the cracked real-rock crop without a mask: 9 %.
NO_TEXTURE_SHARE = 0.05


def node_counts(status: np.ndarray, provenance: np.ndarray, u: np.ndarray) -> NodeCounts:
    """The :class:`NodeCounts` of a field's ``status``, ``provenance`` and ``u`` (``(..., 3)``)."""
    usable = usable_nodes(status, provenance, u)
    matched = usable & np.isin(status, [int(s) for s in GOOD_STATUSES])
    codes, counts = np.unique(status, return_counts=True)
    return NodeCounts(
        total=int(np.asarray(status).size),
        matched=int(matched.sum()),
        filled=int(usable.sum() - matched.sum()),
        statuses={Status(int(c)).label: int(n) for c, n in zip(codes, counts)},
    )


def _as_triple(value: Any, name: str, dtype=float) -> tuple:
    array = np.broadcast_to(np.asarray(value, dtype=np.float64), (3,))
    if not np.all(np.isfinite(array)):
        raise ValueError(f"{name} must be finite, got {value!r}")
    return tuple(dtype(v) for v in array)


@dataclass
class DisplacementField:
    """A displacement field on a regular POI grid, with per-node quality and provenance.

    Parameters
    ----------
    origin : tuple of 3 floats
        Position ``(z, y, x)`` of node ``(0, 0, 0)`` in reference voxels (the centre of the first
        subvolume).
    step : tuple of 3 floats
        Grid spacing ``(z, y, x)`` in voxels, each > 0.
    u : ndarray, shape (nz, ny, nx, 3), float64
        Displacement ``(uz, uy, ux)`` in voxels at each node.
    zncc : ndarray, shape (nz, ny, nx), float32, optional
        Zero-normalised cross-correlation of the final match, in [-1, 1]; NaN where not matched.
    status : ndarray, shape (nz, ny, nx), uint8, optional
        :class:`Status` codes.
    iterations : ndarray, shape (nz, ny, nx), int32, optional
        IC-GN iterations used.
    provenance : ndarray, shape (nz, ny, nx), uint8, optional
        :class:`Provenance` codes.
    gradient : ndarray, shape (nz, ny, nx, 3, 3), float64, optional
        Displacement gradient ``du_i/dX_j`` (i, j in z, y, x order) from the shape function, or
        None.
    params : dict
        Parameters that produced the field (JSON-serialisable).
    metadata : dict
        Provenance of the run: versions, timings, history of correction passes, voxel size...
        (JSON-serialisable).
    uncertainty : ndarray, shape (nz, ny, nx, 3), float64, optional
        Standard deviation of ``(uz, uy, ux)`` in voxels that the imaging noise leaves in each
        measured node, estimated from the images alone (:func:`.icgn_uncertainty.subvolume_statistics`); NaN
        where no match was measured (failed, masked, or a value filled in by cleaning), or None
        when unknown (fields from older files or other tools).
    """

    origin: tuple
    step: tuple
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
        self.origin = _as_triple(self.origin, "origin")
        self.step = _as_triple(self.step, "step")
        if min(self.step) <= 0:
            raise ValueError(f"step must be > 0 along every axis, got {self.step}")
        u = np.asarray(self.u, dtype=np.float64)
        if u.ndim != 4 or u.shape[-1] != 3:
            raise ValueError(f"u must have shape (nz, ny, nx, 3), got {u.shape}")
        self.u = u
        grid = u.shape[:3]
        if self.zncc is None:
            self.zncc = np.full(grid, np.nan, np.float32)
        if self.status is None:
            self.status = np.full(grid, Status.CONVERGED, np.uint8)
        if self.iterations is None:
            self.iterations = np.zeros(grid, np.int32)
        if self.provenance is None:
            self.provenance = np.full(grid, Provenance.MEASURED, np.uint8)
        self.zncc = np.asarray(self.zncc, dtype=np.float32)
        self.status = np.asarray(self.status, dtype=np.uint8)
        self.iterations = np.asarray(self.iterations, dtype=np.int32)
        self.provenance = np.asarray(self.provenance, dtype=np.uint8)
        for name in ("zncc", "status", "iterations", "provenance"):
            if getattr(self, name).shape != grid:
                raise ValueError(
                    f"{name} must have the grid shape {grid}, got {getattr(self, name).shape}"
                )
        if self.gradient is not None:
            self.gradient = np.asarray(self.gradient, dtype=np.float64)
            if self.gradient.shape != (*grid, 3, 3):
                raise ValueError(
                    f"gradient must have shape {(*grid, 3, 3)}, got {self.gradient.shape}"
                )
        if self.uncertainty is not None:
            self.uncertainty = np.asarray(self.uncertainty, dtype=np.float64)
            if self.uncertainty.shape != (*grid, 3):
                raise ValueError(
                    f"uncertainty must have shape {(*grid, 3)}, got {self.uncertainty.shape}"
                )

    # -- geometry -------------------------------------------------------------------------
    @property
    def shape(self) -> tuple[int, int, int]:
        """Grid shape ``(nz, ny, nx)``."""
        return tuple(int(n) for n in self.u.shape[:3])

    @property
    def n_points(self) -> int:
        return int(np.prod(self.shape))

    def axis_coordinates(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """1-D node positions along z, y and x, in reference voxels."""
        return tuple(
            self.origin[a] + self.step[a] * np.arange(self.shape[a], dtype=np.float64)
            for a in range(3)
        )

    @property
    def points(self) -> np.ndarray:
        """Node positions, shape (N, 3), (z, y, x) reference voxels, in C order of the grid."""
        zz, yy, xx = np.meshgrid(*self.axis_coordinates(), indexing="ij")
        return np.stack([zz.ravel(), yy.ravel(), xx.ravel()], axis=1)

    @property
    def displacement(self) -> np.ndarray:
        """Flat displacement, shape (N, 3), matching :attr:`points`."""
        return self.u.reshape(-1, 3)

    @property
    def measured_displacement(self) -> np.ndarray:
        """Flat displacement (N, 3) with NaN wherever the status is not good.

        Only nodes matched with a status in :data:`GOOD_STATUSES` keep their value; failed,
        low-ZNCC, masked and replaced nodes are NaN (the grid :attr:`u` keeps values filled in by
        cleaning, with their :attr:`provenance`). This is what the ``.npz`` file's flat
        ``displacement`` holds for tools that read it without the status.
        """
        good = np.isin(self.status, [int(s) for s in GOOD_STATUSES]).reshape(-1)
        flat = self.u.reshape(-1, 3).copy()
        flat[~good] = np.nan
        return flat

    @property
    def magnitude(self) -> np.ndarray:
        """Displacement magnitude on the grid, shape (nz, ny, nx), voxels."""
        return np.sqrt(np.sum(self.u**2, axis=-1))

    @property
    def valid(self) -> np.ndarray:
        """Boolean grid mask of nodes holding a usable displacement.

        A node is usable when it was measured with a good status or was filled in (replaced or
        corrected) by post-processing.
        """
        return usable_nodes(self.status, self.provenance, self.u)

    def status_counts(self) -> dict[str, int]:
        """Number of nodes of each status, by readable name (only the statuses present)."""
        codes, counts = np.unique(self.status, return_counts=True)
        return {Status(int(c)).label: int(n) for c, n in zip(codes, counts)}

    def node_counts(self) -> NodeCounts:
        """Usable, matched and filled-in nodes, and the counts by status (:class:`NodeCounts`)."""
        return node_counts(self.status, self.provenance, self.u)

    # -- copies ---------------------------------------------------------------------------
    def copy(self) -> DisplacementField:
        """Deep copy (arrays and dictionaries)."""
        return copy.deepcopy(self)

    def replace(self, **changes: Any) -> DisplacementField:
        """A new field with some attributes changed (like :func:`dataclasses.replace`)."""
        return dataclasses.replace(self, **changes)

    def same_grid(self, other: DisplacementField) -> bool:
        return (
            self.shape == other.shape
            and np.allclose(self.origin, other.origin)
            and np.allclose(self.step, other.step)
        )

    @classmethod
    def zeros(cls, origin, step, shape, **kwargs: Any) -> DisplacementField:
        """A zero field on the given grid (used for tests and as a starting point)."""
        shape = tuple(int(n) for n in shape)
        return cls(origin=origin, step=step, u=np.zeros((*shape, 3)), **kwargs)

    def __repr__(self) -> str:
        return (
            f"DisplacementField(shape={self.shape}, origin={self.origin}, step={self.step}, "
            f"valid={int(self.valid.sum())}/{self.n_points})"
        )


#: Voxels kept between a subvolume and the volume's border by the default grid: the cubic
#: B-spline interpolant is least accurate within about two voxels of the border (its prefilter
#: has to assume a mirrored continuation of the volume there).
BORDER_MARGIN = 2


def grid_for_volume(volume_shape, subvolume: int, step) -> tuple[tuple, tuple, tuple]:
    """POI grid ``(origin, step, shape)`` that keeps every subvolume inside the volume.

    Subvolumes stay :data:`BORDER_MARGIN` voxels away from the border when the volume is large
    enough, and touch it otherwise.

    Parameters
    ----------
    volume_shape : tuple of 3 ints
        ``(nz, ny, nx)`` of the reference volume.
    subvolume : int
        Odd subvolume edge ``2M + 1`` in voxels.
    step : int or tuple of 3 ints
        POI spacing in voxels.

    Returns
    -------
    origin, step, shape : tuples of 3
        The first node sits at ``M`` along each axis and the grid is centred in the volume.
    """
    volume_shape = tuple(int(n) for n in volume_shape)
    steps = tuple(int(s) for s in np.broadcast_to(np.asarray(step), (3,)))
    half = subvolume // 2
    origin, shape = [], []
    for n, s in zip(volume_shape, steps):
        span = n - 1 - 2 * half  # room for node positions
        margin = BORDER_MARGIN if span >= 2 * BORDER_MARGIN else 0
        span -= 2 * margin
        if span < 0:
            from ..pair_checks import largest_subvolume_advice

            raise ValueError(
                f"subvolume {subvolume} is larger than the volume ({volume_shape}): "
                + largest_subvolume_advice(volume_shape)
            )
        count = span // s + 1
        used = (count - 1) * s
        origin.append(half + margin + (span - used) // 2)
        shape.append(count)
    return tuple(float(o) for o in origin), tuple(float(s) for s in steps), tuple(shape)
