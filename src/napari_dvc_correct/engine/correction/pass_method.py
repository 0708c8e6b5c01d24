"""How the correcting DVC runs of the self-correction match, chosen from the data.

The paper reuses the first run's parameters (no new user parameter). We keep that rule and choose,
from the input field alone, the shape function of the correcting matches: where the field bends
inside a subvolume more than an affine shape function can follow, the correcting matches are
second order on a smaller subvolume (measured in docs/method.md); elsewhere the first run's
parameters are reused unchanged. Displacements in voxels, axes (z, y, x).
"""

from __future__ import annotations

import functools

import numpy as np
from scipy import ndimage

from ..correlation.params import WINDOW_TRUNCATE, CorrelationParams, gaussian_window
from ..fields.field import DisplacementField, Provenance, Status
from .acceptance import MIN_USEFUL_CHANGE

#: A first-order field whose curvature bends a subvolume by more than this (voxels, see
#: :func:`field_curvature`) is corrected with second-order matches.
CURVATURE_VOXELS = 0.1

#: Subvolume of the second-order correcting matches, as a fraction of the first run's.
PASS_SUBVOLUME_FRACTION = 2.0 / 3.0

#: Scatter of a second-order match over a first-order one on the same subvolume (the
#: translation terms share the subvolume's information with 27 other parameters instead of 9).
SECOND_ORDER_NOISE_GAIN = 1.5

#: Another order or subvolume than the first run's is used only where its predicted error is
#: under this fraction of the first run's (the paper's rule is "the same parameters"; on the
#: narrow band under heavy noise second order on 21³ predicted 0.23 against 0.24 and did worse,
#: 0.32 against 0.30).
CHANGE_MARGIN = 0.8

#: Share of a first-order bend that a second-order match on the same subvolume still leaves
#: (:func:`predicted_error`; measured 0.14 / 0.29 on the narrow band of docs/method.md).
SECOND_ORDER_BIAS = 0.5

#: Smallest subvolume edge of a correcting match (voxels).
MIN_PASS_SUBVOLUME = 11

#: Standard deviations (voxels) of the Gaussian windows weighed for the second-order correcting
#: matches on their subvolume (:func:`pass_window`); the uniform subvolume is weighed with them.
WINDOW_STDS = (2.5, 3.0, 3.5, 4.0, 4.5, 5.0, 5.5, 6.0, 7.0, 8.0)


@functools.lru_cache(maxsize=64)
def window_geometry(half: int, std: float | None, order: int = 2) -> tuple[float, float]:
    """What a window does to a match of ``order`` on ``(2·half + 1)³``: ``(m2, noise)``.

    ``m2 = Σ w ξz² / Σ w``, the window's second moment along an axis (voxels²): the bias a field
    that bends inside the subvolume leaves grows with it (for the uniform box it is
    ``M (M + 1) / 3``, the ``M²`` of :func:`predicted_error`). ``noise = ‖k‖``, the norm of the
    equivalent kernel ``k = W X (Xᵀ W X)⁻¹ e₀`` of a weighted least-squares fit of the shape
    function's monomials ``X`` (``W = diag w``): the translation's scatter per unit of per-voxel
    noise where the texture is even (the noise through ``Σ w²`` and the fit). ``std`` None: the
    uniform subvolume; else the window the matches use (truncated at
    :data:`.params.WINDOW_TRUNCATE` std, :meth:`.CorrelationParams.subvolume_weights`).
    """
    r = np.arange(-half, half + 1, dtype=np.float64)
    z, y, x = (a.ravel() for a in np.meshgrid(r, r, r, indexing="ij"))
    columns = [np.ones_like(z), z, y, x]
    if order == 2:
        columns += [z * z, y * y, x * x, z * y, y * x, z * x]
    design = np.stack(columns, 1)
    w = np.ones_like(z) if std is None else gaussian_window(half, std, WINDOW_TRUNCATE).ravel()
    normal = design.T @ (w[:, None] * design)
    kernel = w * (design @ np.linalg.solve(normal, np.eye(len(normal))[0]))
    return float(np.sum(w * z * z) / np.sum(w)), float(np.sqrt(np.sum(kernel * kernel)))


def pass_window(
    field: DisplacementField, bend: float, subvolume: int, pass_subvolume: int
) -> tuple[float | None, float, float]:
    """Gaussian window of the second-order correcting matches on ``pass_subvolume``³, chosen by
    predicted error: ``(std or None, its predicted error, the uniform subvolume's)``.

    For the uniform subvolume and each window of :data:`WINDOW_STDS`: the bias
    (:data:`SECOND_ORDER_BIAS` × the bend, falling as the square of the subvolume, as in
    :func:`predicted_error`) in proportion to the window's second moment, and the scatter from
    the first run's median uncertainty carried through the fits' equivalent kernels
    (:func:`window_geometry`: the second-order fit under the window against the first run's
    first-order one on ``subvolume``³); the predicted error is the root of the sum of squares.
    A window narrows the match to less bias at more scatter, so it is used only where the
    uniform subvolume's predicted bias is the larger part of its error (never where the noise
    already dominates: on the noisy concrete of docs/method.md every window measured worse; nor
    for a field that carries no uncertainty to weigh the noise by), and
    then the one of least predicted error wins (None where that is the uniform subvolume). The
    box is not enlarged: larger boxes under a window measured worse (their far voxels read the
    misfit of the densified field between the nodes, docs/method.md).
    """
    half = pass_subvolume // 2
    bias = SECOND_ORDER_BIAS * bend * (pass_subvolume / subvolume) ** 2
    sigma = predicted_scatter(field, subvolume, subvolume) / SECOND_ORDER_NOISE_GAIN
    m2_box, noise_box = window_geometry(half, None)
    _, noise_first = window_geometry(subvolume // 2, None, 1)
    scatter = sigma * noise_box / noise_first
    uniform = float(np.hypot(bias, scatter))
    best, best_error = None, uniform
    if not (bias > scatter > 0.0):  # noise-dominated, or no uncertainty to weigh it by
        return best, best_error, uniform
    for std in WINDOW_STDS:
        m2, noise = window_geometry(half, float(std))
        error = float(np.hypot(bias * m2 / m2_box, scatter * noise / noise_box))
        if error < best_error:
            best, best_error = float(std), error
    return best, best_error, uniform


def field_curvature(
    field: DisplacementField, half: int, exclude: np.ndarray | None = None
) -> float:
    """How far a first-order subvolume is from following ``field``, in voxels.

    The second differences of the node displacements (smoothed over one node) give the field's
    curvature; over a
    subvolume of half-size ``M`` a quadratic term ``u'' M^2 / 2`` is what an affine shape function
    cannot follow. Returns the 90th percentile over the interior nodes of the largest such term
    (any component, any axis), 0 for grids too small to tell. ``exclude`` (bool, the grid's
    shape, optional): nodes whose differences do not count (a crack and the nodes it shields:
    its jump is no bend a pass could follow, and a pass does not change them).
    """
    u = _smoothed_departure(field)
    if u is None:
        return 0.0
    # nodes next to the grid's border are bent by the smoothing's border handling
    interior = tuple(slice(1, -1) if n >= 5 else slice(None) for n in u.shape[:3])
    u = u[interior]
    counted = np.ones(u.shape[:3], bool) if exclude is None else ~np.asarray(exclude)[interior]
    terms = []
    for axis in range(3):
        if u.shape[axis] < 3:
            continue
        second = np.diff(u, n=2, axis=axis) / float(field.step[axis]) ** 2
        n = u.shape[axis]
        # a difference counts where its three nodes (i - 1, i, i + 1 along the axis) all do
        inside = np.ones(second.shape[:3], bool)
        for start in range(3):
            inside &= np.take(counted, np.arange(start, n - 2 + start), axis=axis)
        terms.append(np.max(np.abs(second), axis=-1)[inside].reshape(-1))
    if not terms:
        return 0.0
    values = np.concatenate(terms)
    values = values[np.isfinite(values)]
    return float(0.5 * np.percentile(values, 90.0) * half**2) if values.size else 0.0


def _smoothed_departure(field: DisplacementField) -> np.ndarray | None:
    """The node displacements less their affine trend, smoothed over one node (None where some
    node is not finite): what :func:`field_curvature` and :func:`node_bend` take second
    differences of."""
    u = np.asarray(field.u, dtype=np.float64)
    if not np.all(np.isfinite(u)):
        return None
    # the affine trend has no curvature: remove it so the smoothing's border handling cannot
    # bend it
    points = field.points
    design = np.column_stack([np.ones(len(points)), points])
    coefficients, *_ = np.linalg.lstsq(design, u.reshape(-1, 3), rcond=None)
    u = u - (design @ coefficients).reshape(u.shape)
    # one node of Gaussian smoothing first: the matching noise of the nodes (a few hundredths of
    # a voxel, independent from node to node) would otherwise read as curvature
    return np.stack([ndimage.gaussian_filter(u[..., c], 1.0, mode="nearest") for c in range(3)], -1)


def node_bend(field: DisplacementField, half: int) -> np.ndarray:
    """:func:`field_curvature` node by node: the bend ``|u''| M^2 / 2`` (voxels) that an affine
    shape function on a subvolume of half-size ``M`` leaves at each node, the largest over the
    components and axes, shape ``field.shape``.

    Second differences are centred; a face node takes its inner neighbour's along that axis,
    and an axis with fewer than 3 nodes counts no bend. NaN everywhere where some node is not
    finite (nothing to tell the bend from).
    """
    u = _smoothed_departure(field)
    if u is None:
        return np.full(field.shape, np.nan)
    bend = np.zeros(field.shape)
    for axis in range(3):
        n = u.shape[axis]
        if n < 3:
            continue
        second = np.diff(u, n=2, axis=axis) / float(field.step[axis]) ** 2
        # centred at nodes 1 .. n-2; the face nodes take their inner neighbour's
        index = np.clip(np.arange(n) - 1, 0, n - 3)
        second = np.take(second, index, axis=axis)
        bend = np.maximum(bend, np.max(np.abs(second), axis=-1))
    return 0.5 * bend * float(half) ** 2


def nothing_to_correct(
    field: DisplacementField, params: CorrelationParams, masked: np.ndarray
) -> str:
    """Why a correcting pass could only re-measure ``field`` (``""`` where it could correct).

    A correcting pass re-matches each node on the same images that gave its value, with the
    subvolume warped by the field densified between the nodes. It can correct a node only where
    the node's value is not its own converged match (the cleaning or the residual check replaced
    it, its match failed), or where the field bends across the subvolume by more than an affine
    shape function follows (:func:`node_bend`). Where neither holds at any measured node
    (``~masked``), that is every node its own converged match and no bend of
    :data:`.acceptance.MIN_USEFUL_CHANGE` (the matcher's own accuracy on clean scans) anywhere,
    a pass re-measures the first run's values and noise: it costs a whole correlation and
    :func:`.acceptance.noise_only_corrections` refuses what it finds. The bend is not weighed
    against the match's uncertainty: on a coarse grid (4³ nodes across a shear band) the
    smoothed bend reads far less than what a pass still corrects (measured: 0.023 voxel of bend
    against 0.064 of uncertainty, and a pass took the error from 0.117 to 0.106 voxel). Grids
    with fewer than 3 nodes along an axis show no bend along it: there a pass runs. So does a
    field that is not our own matcher's with ``params`` (no match uncertainty recorded, other
    parameters, another DVC program's field brought in: a pass is its first measurement here).
    Returns the reason in words for the stop record (``""``: run the passes).
    """
    measured = ~np.asarray(masked, bool).reshape(field.shape)
    if not measured.any() or correctable_nodes(field, params, masked).any():
        return ""
    bend = node_bend(field, params.half)
    return (
        f"no pass run: every one of the {int(measured.sum())} measured nodes is its own converged "
        f"match and the field bends no {params.subvolume}³ subvolume by more than "
        f"{MIN_USEFUL_CHANGE:g} voxel (largest bend {float(np.max(bend[measured])):.2g}): a pass "
        "could only re-measure the first run's values and noise"
    )


def correctable_nodes(
    field: DisplacementField, params: CorrelationParams, masked: np.ndarray
) -> np.ndarray:
    """The measured nodes a correcting pass can correct, not only re-measure (bool, the grid's
    shape): :func:`nothing_to_correct` node by node.

    A node (not ``masked``) whose value is not its own converged match, or where the field bends
    a subvolume of the first run (``params.half``) by more than
    :data:`.acceptance.MIN_USEFUL_CHANGE` (:func:`node_bend`; NaN counts as bent). Every measured
    node where ``field`` is not our matcher's own with ``params``, or where the grid has fewer
    than 3 nodes along an axis (no bend can be told there).
    """
    measured = ~np.asarray(masked, bool).reshape(field.shape)
    if min(field.shape) < 3 or not _measured_with(field, params):
        return measured
    own = (field.status == Status.CONVERGED) & (field.provenance == Provenance.MEASURED)
    bent = ~(node_bend(field, params.half) <= MIN_USEFUL_CHANGE)  # NaN: unknown, counts as bent
    return measured & (~own | bent)


def _measured_with(field: DisplacementField, params: CorrelationParams) -> bool:
    """Whether ``field`` holds our matcher's own matches with ``params`` (it recorded them and
    each match's uncertainty)."""
    if field.uncertainty is None or not field.params:
        return False
    try:
        return CorrelationParams.from_dict(field.params) == params
    except (TypeError, ValueError):
        return False


def predicted_scatter(field: DisplacementField, subvolume: int, pass_subvolume: int) -> float:
    """Predicted random error (voxels, norm) of second-order matches on ``pass_subvolume``³.

    From the first run's measured uncertainties (median of the nodes' norms; 0 where the field
    carries none): the scatter grows as the number of voxels falls, ``(S / s)^(3/2)``, and a
    second-order shape function spends its subvolume's information on 30 parameters instead of
    12 (:data:`SECOND_ORDER_NOISE_GAIN`).
    """
    if field.uncertainty is None:
        return 0.0
    sigma = np.linalg.norm(field.uncertainty, axis=-1)
    sigma = sigma[np.isfinite(sigma)]
    if not sigma.size:
        return 0.0
    ratio = (float(subvolume) / float(pass_subvolume)) ** 1.5
    return float(np.median(sigma)) * ratio * SECOND_ORDER_NOISE_GAIN


def pass_order(field: DisplacementField, params: CorrelationParams) -> int:
    """Shape-function order of the correcting matches, chosen from the data (no user parameter).

    Second order where the input field bends inside a subvolume by more than
    :data:`CURVATURE_VOXELS` (:func:`field_curvature`): the first-order floor then dominates the
    error, and the correcting match only follows the error of ``D``, whose second-order part a
    quadratic subvolume can take. First order otherwise (translations, affine fields, gentle
    gradients), which is cheaper and no less accurate there. ``params.order == 2`` stays 2.
    """
    if params.order == 2:
        return 2
    return 2 if field_curvature(field, params.half) > CURVATURE_VOXELS else 1


def correction_params(field: DisplacementField, params: CorrelationParams) -> CorrelationParams:
    """Matching parameters of the correcting DVC runs, chosen from the data.

    Where the field bends inside a subvolume (:func:`pass_order` says second order), the
    correcting matches use the second-order shape function on a subvolume of about
    :data:`PASS_SUBVOLUME_FRACTION` of the first run's (odd, at least :data:`MIN_PASS_SUBVOLUME`):
    they only have to find the error of ``D``, a small motion that a smaller subvolume finds as
    well, and a smaller quadratic subvolume follows a narrow band that neither a large one nor a
    first-order one can (measured in docs/method.md). Elsewhere the first run's parameters are
    reused unchanged, as in the paper.
    """
    return pass_method(field, params)[0]


def pass_method(
    field: DisplacementField, params: CorrelationParams, exclude: np.ndarray | None = None
) -> tuple[CorrelationParams, str]:
    """:func:`correction_params` and, in words, why they differ from the first run's (or not).

    The reason is shown to the user (panel, command line, report): the paper promises "the same
    DVC parameters", so any change must be said. ``exclude``: nodes whose bend does not count
    (:func:`field_curvature`).
    """
    if params.order == 2:
        return params, f"the first run's parameters (second order, {params.subvolume}³)"
    bend = field_curvature(field, params.half, exclude)
    if bend <= CURVATURE_VOXELS:
        return params, (
            f"the first run's parameters (first order, {params.subvolume}³): the field bends a "
            f"subvolume by {bend:.2g} voxel, at most {CURVATURE_VOXELS:g}"
        )
    smaller = 2 * int(round(PASS_SUBVOLUME_FRACTION * params.half)) + 1
    smaller = min(params.subvolume, max(MIN_PASS_SUBVOLUME, smaller))
    # the predicted error of each way to match: the bias the bend leaves, the scatter the
    # noise adds (root of the sum of squares); the smallest wins
    errors = {
        (order, subvolume): predicted_error(field, bend, params.subvolume, order, subvolume)
        for order, subvolume in ((1, params.subvolume), (2, params.subvolume), (2, smaller))
    }
    (order, subvolume), best = min(errors.items(), key=lambda item: item[1])
    if best > CHANGE_MARGIN * errors[(1, params.subvolume)]:
        order = 1  # not clearly better: the paper's rule, the first run's parameters
    listed = ", ".join(
        f"{'first' if o == 1 else 'second'} order on {s}³ {e:.2g}" for (o, s), e in errors.items()
    )
    if order == 1:
        return params, (
            f"the first run's parameters (first order, {params.subvolume}³): the field bends a "
            f"subvolume by {bend:.2g} voxel, but on these scans' noise the predicted errors are "
            f"{listed} voxel"
        )
    window, window_error, _ = (None, 0.0, 0.0)
    if subvolume == smaller:
        window, window_error, _ = pass_window(field, bend, params.subvolume, subvolume)
    weighted = (
        ""
        if window is None
        else f", weighted by a Gaussian window of std {window:g} voxels (predicted {window_error:.2g})"
    )
    return params.replace(order=2, subvolume=subvolume, window=window), (
        f"second order on {subvolume}³{weighted} instead of first order on {params.subvolume}³: "
        f"the field bends a {params.subvolume}³ subvolume by {bend:.2g} voxel "
        f"(> {CURVATURE_VOXELS:g}), more than an affine shape function can follow (predicted "
        f"errors: {listed} voxel)"
    )


def predicted_error(
    field: DisplacementField, bend: float, subvolume: int, order: int, pass_subvolume: int
) -> float:
    """Predicted error (voxels) of correcting matches of ``order`` on ``pass_subvolume``³.

    Bias: a first-order match keeps the bend ``bend`` of the first run's ``subvolume``³; a
    second-order one about :data:`SECOND_ORDER_BIAS` of it, falling as the square of the
    subvolume (measured on the narrow band of docs/method.md: 0.29 first order on 21³, 0.14
    second order on 21³, 0.07 on 15³). Scatter: :func:`predicted_scatter` (second order), the
    first run's median uncertainty (first order on its subvolume). Root of the sum of squares.
    """
    if order == 1:
        sigma = predicted_scatter(field, subvolume, subvolume) / SECOND_ORDER_NOISE_GAIN
        return float(np.hypot(bend * (pass_subvolume / subvolume) ** 2, sigma))
    bias = SECOND_ORDER_BIAS * bend * (pass_subvolume / subvolume) ** 2
    return float(np.hypot(bias, predicted_scatter(field, subvolume, pass_subvolume)))


def correction_grid(
    field: DisplacementField, volume_shape, params: CorrelationParams, read_points: np.ndarray
) -> tuple[tuple, tuple, tuple]:
    """POI grid ``(origin, step, shape)`` of the correcting DVC runs.

    ``field``'s lattice (same origin and step), extended by whole steps towards the nodes'
    read points (where their updates read ``ΔD``: ``X + D(X)`` in the loaded frame) as far as the
    lattice node nearest to the outermost read point, and no further than the correcting
    subvolume (``params.half``) fits in the volume. Under a large displacement the faces' nodes
    are carried one or more steps beyond ``field``'s grid; without these nodes their update would
    be the spline's extrapolation of ``ΔD``, not a measurement. Never smaller than ``field``'s
    grid; unchanged where every read point lies within half a step of it.

    Parameters
    ----------
    field : DisplacementField
        The field being corrected (its grid is the lattice).
    volume_shape : tuple of 3 ints
        ``(nz, ny, nx)`` of the volumes.
    params : CorrelationParams
        Parameters of the correcting matches (:func:`correction_params`).
    read_points : ndarray, shape (n, 3)
        Positions ``(z, y, x)`` in voxels; non-finite rows are ignored.

    Returns
    -------
    origin, step, shape : tuples of 3
        Origin and step in voxels (whole voxels where ``field``'s are), node counts.
    """
    origin = np.asarray(field.origin, dtype=np.float64)
    step = np.asarray(field.step, dtype=np.float64)
    last = np.asarray(field.shape) - 1
    points = np.asarray(read_points, dtype=np.float64).reshape(-1, 3)
    points = points[np.all(np.isfinite(points), axis=1)]
    if not len(points):
        return field.origin, field.step, field.shape
    half = params.half
    fits_lo = np.ceil((half - origin) / step)
    fits_hi = np.floor((np.asarray(volume_shape, dtype=np.float64) - 1 - half - origin) / step)
    lo = np.minimum(0, np.maximum(np.rint((points.min(axis=0) - origin) / step), fits_lo))
    hi = np.maximum(last, np.minimum(np.rint((points.max(axis=0) - origin) / step), fits_hi))
    new_origin = origin + lo * step
    shape = (hi - lo + 1).astype(int)
    return tuple(float(o) for o in new_origin), field.step, tuple(int(n) for n in shape)
