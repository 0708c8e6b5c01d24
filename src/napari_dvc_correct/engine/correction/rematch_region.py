"""What a further correction pass can change, and when it can only confirm.

Pass ``k + 1`` of the self-correction (:mod:`.self_correction`) matches the warped volume again. A
correcting match can differ from pass ``k``'s only where the warped volume changed, that is near
the nodes whose value pass ``k`` changed: the dense field is a cubic B-spline through the node
values, whose response to one node's change decays by about ``2 - sqrt(3) = 0.27`` per grid step
(:func:`spline_tail`). So:

* the **changed nodes** are those whose change in pass ``k`` is large enough, and whose region's
  residual still stands far enough above the noise floor, that the next pass could still
  improve their region above that floor (:func:`changed_nodes`); where fewer than the stop
  rule's share of the nodes could, the next pass can only confirm;
* the **spline's reach** ``S`` is the fewest grid steps beyond which the largest change, through
  the spline, moves the warped volume by less than that tolerance (:func:`spline_reach`);
* the correcting matches that can change (**matched**) are the pass-grid nodes within
  ``ceil(half / step) + S`` steps (per axis) of a changed node's read point (``X + D(X)`` in the
  loaded frame), and the nodes new to the pass grid;
* the nodes **judged** are those whose update reads ``ΔD`` within ``S`` steps of a matched node;
  every other node keeps its value and quality arrays, as a full re-match would give them within
  the tolerance (its correction was already applied or refused).

Where no node changed by enough, or too few to matter, the next pass can only confirm, and does
not run; after two passes, "enough" is what the next pass is expected to move a node at the rate
the last two passes contracted (:func:`expected_change`, :func:`only_confirms`).

The first pass has no previous one: it matches only near the nodes it can correct rather than
re-measure (:func:`first_selection`, from :func:`.pass_method.correctable_nodes`), and its other
matches find no motion (:func:`remeasurement`). Positions in voxels, axes (z, y, x).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from ..correlation.params import CorrelationParams
from ..fields.field import DisplacementField
from ..fields.field_spline import FieldSpline
from .acceptance import MIN_USEFUL_CHANGE
from .pass_method import correctable_nodes


def _cardinal_tail(max_steps: int = 12) -> np.ndarray:
    """``max |eta(x)|`` over ``|x| >= d`` for ``d = 0, 1, ...``: ``eta`` is the cubic B-spline's
    cardinal function (its interpolant of one node at 1, the others at 0)."""
    pole = np.sqrt(3.0) - 2.0
    nodes = np.arange(-40, 41)
    weights = np.sqrt(3.0) * pole ** np.abs(nodes)
    x = np.linspace(0.0, max_steps + 1.0, 100 * (max_steps + 1) + 1)
    t = np.abs(x[None, :] - nodes[:, None])
    basis = np.where(t < 1, 2 / 3 - t**2 + t**3 / 2, np.where(t < 2, (2 - t) ** 3 / 6, 0.0))
    eta = np.abs(weights @ basis)
    return np.array([eta[x >= d].max() for d in range(max_steps + 1)])


@functools.cache
def spline_tail() -> np.ndarray:
    """``spline_tail()[d]``: the largest response of the cubic-spline interpolant, ``d`` or more
    grid steps from a node, to a unit change of that node (1, 0.137, 0.037, 0.0098, 0.0026...).

    Computed on first use, not on import (about 15 ms of every process that imports the
    correction); read-only."""
    tail = _cardinal_tail()
    tail.flags.writeable = False
    return tail


def __getattr__(name: str):
    if name == "SPLINE_TAIL":  # the module constant of before, now computed on first use
        return spline_tail()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def spline_reach(max_change: float, tolerance: float) -> int:
    """Fewest grid steps ``S >= 1`` beyond which a node change of ``max_change`` voxels moves
    the dense field by at most ``tolerance`` voxels (:func:`spline_tail`)."""
    if not np.isfinite(max_change) or max_change <= 0:
        return 1
    tail = spline_tail()
    within = np.flatnonzero(max_change * tail <= tolerance)
    return int(max(1, within[0])) if within.size else len(tail) - 1


@dataclass(frozen=True)
class Selection:
    """The nodes of one selective pass (see the module).

    Attributes
    ----------
    matched : ndarray of bool, the pass grid's shape
        Correcting matches to run again; the others are the previous pass's.
    judged : ndarray of bool, the field's grid shape
        Nodes whose update is proposed and judged; the others keep their value.
    changed : int
        Nodes whose change in the previous pass can still matter.
    reach : int
        The spline's reach ``S`` in grid steps.
    tolerance : float
        The change a node must exceed to count as changed (voxels; median over the changed
        nodes, :func:`changed_nodes`).
    """

    matched: np.ndarray
    judged: np.ndarray
    changed: int
    reach: int
    tolerance: float


def changed_nodes(change: np.ndarray, useful: np.ndarray, region_tolerance: float, excess=None):
    """Nodes whose last change, and the residual left above the noise floor, are large enough
    that the next pass might improve them.

    A pass counts a node as improved when the residual over its subvolume falls by more than
    the noise allows (``region_tolerance``) plus what :data:`.acceptance.MIN_USEFUL_CHANGE`
    explains (``useful``, :meth:`.acceptance.Judge.useful`: ``½ |∇G| · 0.01`` per node).
    Removing an error ``e`` lowers that residual by at most ``½ |∇G| e`` (less under noise,
    where the residual is not linear in ``e``), and the error a pass leaves is below the change
    it made (the passes contract). So a node whose last change ``c`` has
    ``½ |∇G| c <= region_tolerance + useful``, that is
    ``c <= MIN_USEFUL_CHANGE (1 + region_tolerance / useful)``, cannot improve above the floor
    in the next pass. Nor can a node whose region's residual is already within
    ``region_tolerance + useful`` of the noise floor (``excess``, the region's mean residual less
    the floor, gray levels, the grid's shape; optional): to improve above the floor the residual
    would have to fall below the noise of the images (NaN: not known, the change decides).
    Returns that mask and the median of the change bound over the changed nodes (voxels;
    ``MIN_USEFUL_CHANGE`` if none).
    """
    useful = np.nan_to_num(np.asarray(useful, np.float64), nan=0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        bound = np.where(useful > 0, MIN_USEFUL_CHANGE * (1.0 + region_tolerance / useful), np.inf)
    changed = np.nan_to_num(change, nan=0.0) > bound
    if excess is not None:
        excess = np.asarray(excess, np.float64).reshape(changed.shape)
        changed &= ~(excess <= region_tolerance + useful)
    tolerance = float(np.median(bound[changed])) if changed.any() else MIN_USEFUL_CHANGE
    return changed, tolerance


def expected_change(change: np.ndarray, previous: np.ndarray | None, measured: np.ndarray):
    """The change the next pass is expected to make at each node (voxels, ``change``'s shape).

    :func:`changed_nodes` bounds the error a pass leaves by the change it made. The passes
    contract: where two passes ran, the next one moves the nodes by about the last pass's
    change times the ratio of the last two passes' changes (root-mean-square over the
    ``measured`` nodes, at most 1), so that is what it can still remove. After one pass (no
    ``previous``) or where the previous pass changed nothing, ``change`` itself.

    Parameters
    ----------
    change, previous : ndarray, the grid's shape
        The node changes of the last pass and of the one before it (voxels; NaN: none).
    measured : ndarray of bool, the grid's shape
        The nodes the ratio is taken over.
    """
    change = np.nan_to_num(np.asarray(change, np.float64), nan=0.0)
    if previous is None:
        return change
    previous = np.nan_to_num(np.asarray(previous, np.float64), nan=0.0)
    before = float(np.sum(previous[measured] ** 2))
    if before <= 0.0:
        return change
    ratio = np.sqrt(float(np.sum(change[measured] ** 2)) / before)
    return change * min(1.0, ratio)


def only_confirms(
    number: int,
    change: np.ndarray,
    previous: np.ndarray | None,
    useful: np.ndarray,
    region_tolerance: float,
    measured: np.ndarray,
    min_fraction: float,
    excess: np.ndarray | None = None,
) -> tuple[str, np.ndarray, float]:
    """Why pass ``number + 1`` could only confirm pass ``number`` (``""``: it could improve),
    and :func:`changed_nodes` of the ``measured`` nodes (mask and tolerance).

    Fewer than ``min_fraction`` of the ``measured`` nodes moved by enough to improve above the
    noise floor in another pass (:func:`changed_nodes` of ``change``, pass ``number``'s node
    changes in voxels), or would at the rate the passes contract (:func:`expected_change`, with
    ``previous``, the changes of pass ``number - 1``). ``useful``, ``region_tolerance`` and
    ``excess`` (the residual left above the noise floor in each node's region after pass
    ``number``) as :func:`changed_nodes` takes them.
    """
    measured = np.asarray(measured, bool)
    tolerance = region_tolerance
    least = min_fraction * max(1, int(measured.sum()))
    changed, bound = changed_nodes(change, useful, tolerance, excess)
    changed &= measured
    if changed.sum() < least:
        return (
            f"{_few_nodes(changed.sum())} moved in pass {number} by enough to improve "
            f"above the noise floor in another pass (about {bound:.3g} voxel): it could "
            "only confirm",
            changed,
            bound,
        )
    expected = expected_change(change, previous, measured)
    likely = changed_nodes(expected, useful, tolerance, excess)[0] & measured
    if likely.sum() < least:
        size = float(np.sum(np.nan_to_num(change[measured]) ** 2))
        ratio = np.sqrt(np.sum(expected[measured] ** 2) / size) if size > 0 else 0.0
        return (
            f"pass {number} moved the nodes {ratio:.2g} times as far as pass {number - 1}: "
            f"at that rate {_few_nodes(likely.sum())} would move by enough to improve "
            "above the noise floor in another pass",
            changed,
            bound,
        )
    return "", changed, bound


def _lattice_index(points: np.ndarray, grid) -> np.ndarray:
    origin, step, _ = grid
    index = (np.asarray(points, np.float64).reshape(-1, 3) - np.asarray(origin)) / np.asarray(step)
    return np.rint(np.nan_to_num(index, nan=-1e9)).astype(np.int64)


def _near(index: np.ndarray, shape, reach) -> np.ndarray:
    """Grid nodes within ``reach`` steps (per axis) of any of ``index`` (rows may lie outside)."""
    reach = np.asarray(reach, np.int64)
    pad = reach + 1
    marks = np.zeros(tuple(np.asarray(shape) + 2 * pad), bool)
    inside = np.all((index >= -pad) & (index < np.asarray(shape) + pad), axis=1)
    shifted = index[inside] + pad
    marks[tuple(shifted.T)] = True
    marks = ndimage.maximum_filter(marks, size=tuple(2 * reach + 1), mode="constant")
    return marks[tuple(slice(int(p), int(p) + int(n)) for p, n in zip(pad, shape))]


def select(
    changed: np.ndarray,
    change: np.ndarray,
    changed_points: np.ndarray,
    read_points: np.ndarray,
    pass_grid,
    previous_grid,
    half: int,
    tolerance: float,
) -> Selection:
    """The matched and judged nodes of the next pass (see the module).

    Parameters
    ----------
    changed : ndarray of bool, the field's grid shape
        Nodes whose change can still matter (:func:`changed_nodes`).
    change : ndarray, the field's grid shape
        The previous pass's node changes (voxels), for the spline's reach.
    changed_points : ndarray (n, 3)
        Where the pass grid sees each node of the field (its read point, ``X + D(X)`` in the
        loaded frame), after the previous pass.
    read_points : ndarray (n, 3)
        Where each node's update of the next pass reads ``ΔD`` (same as ``changed_points``).
    pass_grid, previous_grid : (origin, step, shape)
        The next pass's correcting grid and the previous pass's (same lattice).
    half : int
        Half-size of the correcting subvolume (voxels).
    tolerance : float
        Voxels (:func:`changed_nodes`).
    """
    _, step, shape = pass_grid
    moved = float(np.max(np.nan_to_num(change[changed], nan=0.0))) if changed.any() else 0.0
    reach = spline_reach(moved, tolerance)
    subvolume_steps = np.ceil(half / np.asarray(step, np.float64)).astype(np.int64)
    index = _lattice_index(
        np.asarray(changed_points).reshape(-1, 3)[changed.reshape(-1)], pass_grid
    )
    matched = _near(index, shape, subvolume_steps + reach)
    # nodes the previous pass's grid did not have are matched for the first time
    offset = np.rint(
        (np.asarray(previous_grid[0]) - np.asarray(pass_grid[0])) / np.asarray(step)
    ).astype(np.int64)
    known = np.zeros(shape, bool)
    lo = np.clip(offset, 0, shape)
    hi = np.clip(offset + np.asarray(previous_grid[2]), 0, shape)
    known[tuple(slice(int(a), int(b)) for a, b in zip(lo, hi))] = True
    matched |= ~known
    near_matched = _near(np.argwhere(matched), shape, np.full(3, reach))
    reads = np.clip(_lattice_index(read_points, pass_grid), 0, np.asarray(shape) - 1)
    judged = near_matched[tuple(reads.T)].reshape(changed.shape)
    return Selection(matched, judged, int(changed.sum()), int(reach), float(tolerance))


def first_selection(
    field: DisplacementField,
    params: CorrelationParams,
    masked: np.ndarray,
    read_points: np.ndarray,
    pass_grid,
    half: int,
) -> Selection | None:
    """The matched and judged nodes of the first pass: near the nodes it can correct.

    Where a node's value is its own converged match and the field does not bend its subvolume
    (:func:`.pass_method.correctable_nodes` is False), a correcting match re-measures it on the
    same images and finds no motion but their noise, which the acceptance refuses
    (:func:`.acceptance.noise_only_corrections`). Its subvolume is warped by the field
    densified around it, so a match can find more only where its subvolume reaches a correctable
    node: the matched nodes are the pass-grid nodes within ``ceil(half / step) + 1`` steps (per
    axis) of a correctable node's read point, as :func:`select` finds them for a change; the
    judged nodes are those whose nearest correcting match (where their update reads ``ΔD``) is
    one of them. The other nodes keep their value; the other matches are
    :func:`remeasurement`'s. ``None`` where every pass-grid node is matched (or none is
    correctable: the caller runs no pass then).

    Parameters
    ----------
    field : DisplacementField
        The field the pass corrects.
    params : CorrelationParams
        The first run's parameters (:func:`.pass_method.correctable_nodes`).
    masked : ndarray of bool, the field's grid shape
        Nodes outside the user's mask.
    read_points : ndarray (n, 3)
        Where each node's update reads ``ΔD`` (voxels, C order of the field's grid).
    pass_grid : (origin, step, shape)
        The pass's correcting grid.
    half : int
        Half-size of the correcting subvolume (voxels).
    """
    correctable = correctable_nodes(field, params, masked)
    if not correctable.any():
        return None
    no_change = np.zeros(correctable.shape)
    selection = select(
        correctable, no_change, read_points, read_points, pass_grid, pass_grid, half, 1.0
    )
    if selection.matched.all():
        return None
    _, _, shape = pass_grid
    reads = np.clip(_lattice_index(read_points, pass_grid), 0, np.asarray(shape) - 1)
    judged = selection.judged & selection.matched[tuple(reads.T)].reshape(correctable.shape)
    return Selection(selection.matched, judged, selection.changed, selection.reach, 0.0)


def remeasurement(
    delta: DisplacementField, field: DisplacementField, read_points: np.ndarray
) -> DisplacementField:
    """What the first pass's correcting matches find where they cannot correct
    (:func:`first_selection`): no motion.

    On ``delta``'s grid: zero displacement and gradient, unknown uncertainty (NaN: the
    acceptance neither shrinks nor pools by it), and at each correcting node that some node of
    ``field`` reads its update at (``read_points``, (n, 3) voxels), that node's own match quality
    (ZNCC, status, iterations): a re-measurement of a node is its own match.
    """
    zero = DisplacementField.zeros(delta.origin, delta.step, delta.shape)
    zero.gradient = np.zeros((*delta.shape, 3, 3))
    zero.uncertainty = np.full((*delta.shape, 3), np.nan)
    reads = _lattice_index(read_points, (delta.origin, delta.step, delta.shape))
    inside = np.all((reads >= 0) & (reads < np.asarray(delta.shape)), axis=1)
    target = tuple(reads[inside].T)
    for name in ("zncc", "status", "iterations"):
        getattr(zero, name)[target] = getattr(field, name).reshape(-1)[inside]
    return zero


def applied_change(
    field: DisplacementField, change: np.ndarray, points: np.ndarray, loaded: bool
) -> np.ndarray:
    """The last pass's change of ``field`` seen from the next correcting grid's ``points``.

    ``field`` is the field after that pass and ``change`` (its grid shape + (3,)) what the pass
    added. A correcting node at ``y`` measures the motion left between the warped volume and
    ``F`` there: the previous pass's match minus what the pass applied at the reference position
    ``X`` of ``y`` (``X + D(X) = y`` in the loaded frame with the exact update, ``X = y``
    otherwise), to first order in the change. Returns (n, 3) voxels.
    """
    points = np.asarray(points, np.float64).reshape(-1, 3)
    if loaded:
        points = FieldSpline.from_field(field).invert(points)[0]
    values = np.nan_to_num(np.asarray(change, np.float64), nan=0.0)
    return FieldSpline(field.origin, field.step, values)(points)


def reuse(
    delta: DisplacementField,
    previous: DisplacementField,
    matched: np.ndarray,
    applied: np.ndarray | None = None,
):
    """``delta`` (matched at ``matched`` only) completed with ``previous``'s matches elsewhere.

    Both are raw correcting fields (before cleaning) on the same lattice; ``previous``'s grid
    covers every node of ``delta`` not in ``matched`` (:func:`select` matches the new ones).
    ``applied`` ((n, 3), for the nodes not matched in C order, :func:`applied_change`) is
    subtracted from the reused displacements: what the previous pass's update already took.
    """
    merged = delta.copy()
    offset = np.rint(
        (np.asarray(previous.origin) - np.asarray(delta.origin)) / np.asarray(delta.step)
    ).astype(np.int64)
    index = np.argwhere(~matched)
    source = tuple((index - offset).T)
    target = tuple(index.T)
    for name in ("u", "zncc", "status", "iterations", "provenance", "gradient", "uncertainty"):
        into, values = getattr(merged, name), getattr(previous, name)
        if into is not None and values is not None:
            into[target] = values[source]
    if applied is not None:
        merged.u[target] -= np.asarray(applied, np.float64).reshape(-1, 3)
    return merged


def _few_nodes(count) -> str:
    """``"no node"``, ``"only 1 node"``, ``"only N nodes"``: the stop reasons' counts in words."""
    count = int(count)
    return "no node" if count == 0 else f"only {count} node{'s' if count > 1 else ''}"
