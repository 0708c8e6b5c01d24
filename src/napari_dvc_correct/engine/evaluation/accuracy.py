"""Accuracy of a displacement field without ground truth (paper section 2.2, eqs. 1–2, Table 1).

The pieces, in the order the paper uses them:

1. **Phases** (:mod:`.phases`). Each volume is split into ``N`` phases by ``N - 1`` increasing
   gray thresholds (multi-Otsu by default; any ``N >= 2``); the per-phase gray range and mean gray
   of each state make the paper's Table 1.
2. **Background residual (eq. 1).** The gray residual ``r(X) = |F(X + u(X)) - G(X)|`` is computed
   by :func:`napari_dvc_correct.engine.evaluation.residual.gray_residual`. At voxels where the phase of ``G`` and
   the phase of ``F`` mapped by the field agree, the residual is (ideally) imaging noise only; its
   mean over those voxels is the background residual ``r0`` (:func:`background_residual`), and
   ``r' = r - r0`` is the corrected residual.
3. **Accuracy index (eq. 2).** ``p = 1 - mean(r') / |g1 - g2|`` with ``g1, g2`` the mean grays of
   the two phases (:func:`accuracy_index`, :func:`phase_contrast`). For ``N > 2`` phases the two
   *most abundant* phases of the reference are used by default (they make most of the texture the
   matcher sees and most of the phase boundaries a misplaced voxel lands on); any pair can be
   chosen.
4. **Curves against equivalent strain** (paper Figs. 10–11, :mod:`.binning`): the residual of
   each voxel is pooled with the strain of its nearest grid node.

All functions take plain arrays (residual volume, label volumes) so they can be used with any
residual; :func:`evaluate_fields` runs the whole chain for one or several fields.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from ..fields.field import DisplacementField
from ..progress import Progress, run_to_completion
from .accuracy_blocks import (  # noqa: F401 (part of this module's interface)
    BackgroundResidual,
    background_residual,
    corrected_residual,
)
from .accuracy_pair import PairStatistics
from .gray_levels import GrayLevelMap
from .local_accuracy import (  # noqa: F401 (part of this module's interface)
    honest_accuracy,
    local_accuracy_map,
    local_mean_residual,
    region_half,
)
from .options import EvaluationOptions
from .phases import PhaseStats, phase_table, phase_thresholds, segment_phases
from .results import Evaluation, FieldEvaluation


# --- grid quantities ready to display -------------------------------------------------------------
def check_field_fits(field: DisplacementField, volume_shape, name: str = "field") -> None:
    """Raise ``ValueError`` unless every node of ``field`` lies inside a volume of ``volume_shape``.

    A field computed on another volume (other size, other crop) would silently produce residuals
    of the wrong material; this catches it before any work is done.
    """
    volume_shape = tuple(int(n) for n in volume_shape)
    for axis, (coords, n) in enumerate(zip(field.axis_coordinates(), volume_shape)):
        if coords[0] < -0.5 or coords[-1] > n - 0.5:
            raise ValueError(
                f"{name}: its grid does not fit the volume: along axis {'zyx'[axis]} its nodes span "
                f"{coords[0]:g}..{coords[-1]:g} voxels but the volume has {n} voxels "
                f"(0..{n - 1}); was the field computed on another volume?"
            )


# --- background residual, eq. 1, and accuracy index, eq. 2 ----------------------------------------
def default_phase_pair(stats: Sequence[PhaseStats]) -> tuple[int, int]:
    """The two most abundant phases, in label order (the pair eq. 2 uses for ``N > 2``)."""
    if len(stats) < 2:
        raise ValueError("the accuracy index needs at least two phases")
    order = sorted(stats, key=lambda s: (-s.voxels, s.phase))
    return tuple(sorted((order[0].phase, order[1].phase)))


def phase_contrast(
    reference_stats: Sequence[PhaseStats],
    deformed_stats: Sequence[PhaseStats] | None = None,
    pair: tuple[int, int] | None = None,
) -> tuple[float, tuple[int, int]]:
    """Gray contrast ``|g1 - g2|`` between two phases, the denominator of eq. 2.

    Parameters
    ----------
    reference_stats, deformed_stats : list of PhaseStats
        :func:`phase_table` of the reference and of the deformed state. With both, the contrast
        is the mean of the two states' contrasts (the paper's Table 1 lists both states; gray
        levels drift a little between scans); with only the first, that state's contrast.
    pair : (int, int), optional
        Phases to use; default :func:`default_phase_pair` of the reference.

    Returns
    -------
    contrast : float
        Gray levels, > 0.
    pair : (int, int)
    """
    pair = default_phase_pair(reference_stats) if pair is None else tuple(int(p) for p in pair)
    if len(pair) != 2 or pair[0] == pair[1]:
        raise ValueError(f"the phase pair must name two different phases, got {pair}")
    contrasts = []
    for stats in (reference_stats, deformed_stats):
        if stats is None:
            continue
        means = {s.phase: s.mean_gray for s in stats}
        missing = [p for p in pair if p not in means]
        if missing:
            raise ValueError(f"phase {missing[0]} does not exist (phases: {sorted(means)})")
        contrasts.append(abs(means[pair[0]] - means[pair[1]]))
    contrast = float(np.mean(contrasts))
    if not np.isfinite(contrast) or contrast <= 0:
        raise ValueError(f"phases {pair} have the same mean gray: the accuracy index is undefined")
    return contrast, pair


def accuracy_index(mean_residual, background: BackgroundResidual | float, contrast: float):
    """Accuracy index, eq. 2: ``p = 1 - (mean(r) - r0) / |g1 - g2|``.

    Parameters
    ----------
    mean_residual : float or ndarray
        Mean gray residual ``mean(r)`` over a region (the whole volume, or each strain bin).
    background : BackgroundResidual or float
        ``r0`` (eq. 1).
    contrast : float
        ``|g1 - g2|`` from :func:`phase_contrast`.

    Returns
    -------
    float or ndarray
        1 for a residual at the noise level; it falls by 0.1 for every tenth of the phase
        contrast the mean residual rises above the noise. It can exceed 1 slightly where a region's
        residual is below the volume's average noise (it is not clipped).
    """
    r0 = background.mean if isinstance(background, BackgroundResidual) else float(background)
    if not contrast > 0:
        raise ValueError(f"the phase contrast must be > 0, got {contrast}")
    result = 1.0 - (np.asarray(mean_residual, dtype=np.float64) - r0) / float(contrast)
    return float(result) if result.ndim == 0 else result


def _named_fields(fields) -> list[tuple[str, DisplacementField]]:
    if isinstance(fields, DisplacementField):
        return [("field", fields)]
    if isinstance(fields, Mapping):
        items = [(str(k), v) for k, v in fields.items()]
    else:
        items = [(f"field {i + 1}", v) for i, v in enumerate(fields)]
    if not items:
        raise ValueError("give at least one displacement field to evaluate")
    names = [n for n, _ in items]
    if len(set(names)) != len(names):
        raise ValueError(f"field names must be unique, got {names}")
    for name, value in items:
        if not isinstance(value, DisplacementField):
            raise TypeError(f"{name!r} is a {type(value).__name__}, not a DisplacementField")
    return items


# --- the grid side of an evaluation, and its assembly (shared with tiled.evaluation) ---------
@dataclass
class EvaluationPlan:
    """The grid-side part of an evaluation: fields, their strains, the binning and its edges."""

    named: list  # [(name, DisplacementField)]
    strains: list  # equivalent strain on each field's grid
    bin_fields: list  # per field: the field whose grid bins its residual
    bin_strains: list  # per field: the strain that bins it
    edges: np.ndarray
    mode: str
    options: dict


def plan_evaluation(
    fields,
    volume_shape,
    *,
    mode: str = EvaluationOptions.mode,
    strain_measure: str = EvaluationOptions.strain_measure,
    strain_method: str = EvaluationOptions.strain_method,
    strain_window: int = EvaluationOptions.strain_window,
    n_bins: int = EvaluationOptions.n_bins,
    bin_edges=None,
    shared_background: bool = EvaluationOptions.shared_background,
    bin_by: str | None = EvaluationOptions.bin_by,
) -> EvaluationPlan:
    """Check the fields against the volume shape; strains and strain-bin edges (no volume read).

    See :func:`.accuracy.evaluate_iter` for the parameters.
    """
    from .binning import strain_bin_edges
    from .strain import equivalent_strain_field

    named = _named_fields(fields)
    EvaluationOptions(  # the options' checks, once
        mode=mode, strain_measure=strain_measure, strain_method=strain_method,
        strain_window=strain_window, n_bins=n_bins, bin_edges=bin_edges,
        shared_background=shared_background, bin_by=bin_by,
    )  # fmt: skip
    for name, item in named:
        check_field_fits(item, volume_shape, name=f"field {name!r}")
    strains = [
        equivalent_strain_field(
            item, measure=strain_measure, method=strain_method, window=strain_window
        )
        for _, item in named
    ]
    names = [name for name, _ in named]
    if bin_by is not None and bin_by not in names:
        raise ValueError(f"bin_by names no evaluated field: {bin_by!r} (fields: {names})")
    which = [k if bin_by is None else names.index(bin_by) for k in range(len(named))]
    bin_strains = [strains[k] for k in which]
    edges = (
        strain_bin_edges(bin_strains, n_bins)
        if bin_edges is None
        else np.asarray(bin_edges, dtype=np.float64)
    )
    options = {
        "strain_measure": strain_measure,
        "strain_method": strain_method,
        "strain_window": int(strain_window),
        "shared_background": bool(shared_background),
        "bin_by": bin_by,
    }
    return EvaluationPlan(
        named, strains, [named[k][1] for k in which], bin_strains, edges, mode, options
    )


def check_same_phase_count(thresholds_g, thresholds_f) -> None:
    if np.size(thresholds_g) != np.size(thresholds_f):
        raise ValueError(
            f"the reference has {np.size(thresholds_g) + 1} phases and the deformed volume "
            f"{np.size(thresholds_f) + 1}: give both states the same number of thresholds"
        )


def assemble_evaluation(plan, thresholds, tables, phase_pair, partial, labels, pair=None):
    """The :class:`.results.Evaluation`: the contrast, ``r0`` (the pair's or own), eq. 2
    everywhere, the error estimate.

    Parameters
    ----------
    plan : EvaluationPlan
    thresholds, tables, labels : pairs (reference, deformed)
        Phase thresholds, :func:`.phases.phase_table` rows and label volumes (or None).
    phase_pair : (int, int) or None
    partial : list of dict
        :func:`field_partial` of every field, in the plan's order.
    pair : PairStatistics, optional
        The pair's map and ``r0`` (:func:`.accuracy_pair.measure_pair`); without it, ``r0`` is
        the smallest of the fields' own.
    """
    from .error_estimate import error_estimate

    contrast, phases = phase_contrast(tables[0], tables[1], phase_pair)
    if pair is None:
        best = min(partial, key=lambda p: p["background"].mean)
        pair = PairStatistics(
            GrayLevelMap.identity(),
            best["background"],
            best["name"],
            {p["name"]: p["background"].mean for p in partial},
        )
    shared = pair.background.mean
    results = []
    for p in partial:
        r0 = shared if plan.options["shared_background"] else p["background"].mean
        local_accuracy = local_accuracy_map(p["local_residual"], r0, contrast)
        own = {k: v for k, v in p.items() if k != "error_moments"}
        estimate, resolution = error_estimate(
            p["field"], p["error_moments"], shared, correlation=pair.noise_correlation
        )
        results.append(
            FieldEvaluation(
                **own,
                error_estimate=estimate,
                error_resolution=resolution,
                local_accuracy=local_accuracy,
                local_accuracy_index=honest_accuracy(local_accuracy),
                background_used=r0,
                accuracy=accuracy_index(p["mean_residual"], r0, contrast),
                bin_accuracy=accuracy_index(p["bins"].mean_residual, r0, contrast),
            )
        )
    return Evaluation(
        mode=plan.mode,
        thresholds_reference=thresholds[0],
        thresholds_deformed=thresholds[1],
        phases_reference=tables[0],
        phases_deformed=tables[1],
        contrast=contrast,
        phase_pair=phases,
        edges=plan.edges,
        options=dict(plan.options),
        fields=results,
        labels_reference=labels[0],
        labels_deformed=labels[1],
        pair=pair,
    )


def check_region(region, shape) -> np.ndarray:
    """The specimen region as a boolean array of ``shape``, refused when empty or misshapen."""
    region = np.asarray(region) != 0
    if region.shape != tuple(shape):
        raise ValueError(
            f"the specimen region {region.shape} must have the reference volume's shape {shape}"
        )
    if not region.any():
        raise ValueError("the specimen region holds no voxel: draw or choose another one")
    return region


def specimen_mask(shape, region) -> np.ndarray:
    """Boolean volume of ``shape``: the voxels whose centres ``region`` (a
    :class:`.placement.Box` or :class:`.placement.Cylinder`, voxels z, y, x) contains."""
    shape = tuple(int(n) for n in shape)
    mask = np.empty(shape, bool)
    yy, xx = np.meshgrid(np.arange(shape[1]), np.arange(shape[2]), indexing="ij")
    plane = np.stack([np.zeros(yy.size), yy.ravel(), xx.ravel()], axis=1)
    for z in range(shape[0]):
        plane[:, 0] = z
        mask[z] = region.contains(plane).reshape(shape[1:])
    return mask


def region_phases(volume, choice, n_phases, region, name):
    """Thresholds (multi-Otsu over the region's voxels, or the user's), labels (NO_PHASE
    outside the region) and Table 1 of one state over a specimen region."""
    from .phases import label_phases, otsu_stride, otsu_thresholds, validate_thresholds

    inside = np.where(region, np.asarray(volume, np.float64), np.nan)
    if choice is None or (isinstance(choice, str) and choice == "auto"):
        stride = otsu_stride(volume.shape)
        thresholds = otsu_thresholds(inside[::stride, ::stride, ::stride], n_phases)
    elif isinstance(choice, str):
        raise ValueError(f"phases must be 'auto' or a list of thresholds, got {choice!r}")
    else:
        values = inside[np.isfinite(inside)]
        thresholds = validate_thresholds(choice, (values.min(), values.max()), name)
    labels = label_phases(inside, thresholds)  # NaN outside the region: NO_PHASE
    table = phase_table(inside, labels, thresholds)
    empty = [s.phase for s in table if s.voxels == 0]
    if empty:
        raise ValueError(
            f"phase {empty[0]} has no voxel inside the specimen region of the {name}: move the "
            "thresholds or ask for fewer phases"
        )
    return thresholds, labels, table


def evaluate_iter(
    reference: np.ndarray,
    deformed: np.ndarray,
    fields: DisplacementField | Mapping[str, DisplacementField] | Sequence[DisplacementField],
    *,
    phases=EvaluationOptions.phases,
    phases_deformed=EvaluationOptions.phases_deformed,
    n_phases: int = EvaluationOptions.n_phases,
    phase_pair: tuple[int, int] | None = EvaluationOptions.phase_pair,
    mode: str = EvaluationOptions.mode,
    strain_measure: str = EvaluationOptions.strain_measure,
    strain_method: str = EvaluationOptions.strain_method,
    strain_window: int = EvaluationOptions.strain_window,
    n_bins: int = EvaluationOptions.n_bins,
    bin_edges: Sequence[float] | None = None,
    shared_background: bool = EvaluationOptions.shared_background,
    bin_by: str | None = EvaluationOptions.bin_by,
    keep_volumes: bool = True,
    gray_levels: bool | GrayLevelMap = EvaluationOptions.gray_levels,
    background_fields: Mapping[str, DisplacementField] | None = None,
    pair: PairStatistics | None = None,
    region: np.ndarray | None = None,
) -> Iterator[Progress]:
    """Evaluate one or several fields on the same pair of volumes (generator).

    Yields :class:`~.progress.Progress` per stage and returns an :class:`Evaluation`
    (``run_to_completion`` or :func:`evaluate_fields` drive it).

    Parameters
    ----------
    reference, deformed : ndarray, shape (nz, ny, nx)
        ``G`` and ``F``, any real dtype.
    fields : DisplacementField, dict of name -> DisplacementField, or list
        The fields to compare (e.g. ``{"uncorrected": d, "corrected": d2}``). Their nodes must
        lie inside the reference volume and hold finite displacements (clean them first).
    phases : "auto" or sequence of float
        Thresholds for both states (``"auto"``: multi-Otsu with ``n_phases`` per state).
    phases_deformed : "auto", sequence of float, or None
        Thresholds of the deformed state when they differ (default: as ``phases``).
    n_phases : int
        Number of phases for ``"auto"``.
    phase_pair : (int, int), optional
        Phases whose contrast is used in eq. 2 (default: the two most abundant).
    mode : {"reference", "loaded"}
        Where the residual lives (see :func:`~.residual.gray_residual`).
    strain_measure, strain_method, strain_window
        Equivalent strain options (:func:`~.strain.strain_tensor`).
    n_bins : int
        Number of equivalent-strain bins (ignored with ``bin_edges``).
    bin_edges : sequence of float, optional
        Explicit bin edges.
    shared_background : bool
        Use the scan pair's ``r0`` for every field (:mod:`.accuracy_pair`: the smallest
        same-phase residual of the fields known on the pair). Imaging noise belongs to the scans,
        not to a field, and a field's errors can only add misplaced texture to its same-phase
        residual, so the smallest is the best noise estimate and the fields are compared against
        the same baseline. False: each field uses its own ``r0`` for ``p`` (the error estimate
        always uses the pair's).
    bin_by : str, optional
        Name of the field whose equivalent strain bins *every* field's residual, so that all
        curves compare the same material regions (e.g. bin the uncorrected and the corrected
        residuals by the corrected field's strain). Default: each field by its own strain.
    keep_volumes : bool
        Keep the residual and label volumes in the result (for display and export).
    gray_levels : bool or GrayLevelMap
        True (default): fit the pair's gray-level map (:mod:`.gray_levels`) with the best field
        and judge every residual as ``|map(F~) - G|`` in the reference's gray levels, phased by
        the reference's thresholds; a map: use it; False: the raw residual ``|F~ - G|``, the
        moved scan phased by its own thresholds.
    background_fields : dict of name -> DisplacementField, optional
        Every field known on this pair (finite nodes), evaluated or not: the pair's map and
        ``r0`` are measured with the best of them. Default: the evaluated fields.
    pair : PairStatistics, optional
        The pair's map and ``r0`` measured already (then ``gray_levels`` and
        ``background_fields`` are not used).
    region : ndarray of bool, shape (nz, ny, nx), optional
        The specimen region in the reference (True inside; :func:`specimen_mask` makes one from
        a box or a cylinder): the phase thresholds, Table 1 of both states, the gray-level map,
        ``r0`` and every residual statistic use only its voxels (in loaded mode, the loaded
        voxels at the same indices: the displacements are a few voxels).

    Raises
    ------
    ValueError
        Bad thresholds, an empty phase, a field that does not fit the volume or holds NaN.
    """
    from ..correlation.interpolation import prefilter
    from ..fields.field_spline import FieldSpline
    from ..fields.warp import slab_boxes, spline_sampler
    from ..pair_checks import check_pair_and_fields
    from .accuracy_blocks import FieldAccumulator, field_block, field_partial, halo_gradient
    from .binning import node_voxels
    from .error_estimate import error_region_half
    from .error_scales import window_ladder

    reference = np.asanyarray(reference)
    deformed = np.asanyarray(deformed)
    plan = plan_evaluation(
        fields, reference.shape, mode=mode, strain_measure=strain_measure,
        strain_method=strain_method, strain_window=strain_window, n_bins=n_bins,
        bin_edges=bin_edges, shared_background=shared_background, bin_by=bin_by,
    )  # fmt: skip
    check_pair_and_fields(reference, deformed, dict(plan.named))  # finite volumes, shape

    yield Progress("phases", 0, 2, "segmenting the phases")
    phases_f = phases if phases_deformed is None else phases_deformed
    if region is None:
        thresholds_g = phase_thresholds(reference, phases, n_phases, "reference volume")
        thresholds_f = phase_thresholds(deformed, phases_f, n_phases, "deformed volume")
        check_same_phase_count(thresholds_g, thresholds_f)
        labels_g = segment_phases(reference, thresholds_g, "reference volume")
        labels_f = segment_phases(deformed, thresholds_f, "deformed volume")
        tables = (
            phase_table(reference, labels_g, thresholds_g),
            phase_table(deformed, labels_f, thresholds_f),
        )
    else:
        region = check_region(region, reference.shape)
        (thresholds_g, labels_g, table_g), (thresholds_f, labels_f, table_f) = (
            region_phases(volume, choice, n_phases, region, name)
            for volume, choice, name in (
                (reference, phases, "reference volume"),
                (deformed, phases_f, "deformed volume"),
            )
        )
        check_same_phase_count(thresholds_g, thresholds_f)
        tables = (table_g, table_f)
    phase_contrast(*tables, phase_pair)  # an undefined contrast fails before the residuals
    yield Progress("phases", 2, 2, "phases segmented")

    mapped_levels = gray_levels is not False
    coefficients_f = prefilter(deformed)
    if pair is None:
        from .accuracy_pair import measure_pair

        yield Progress("pair", 0, 1, "gray-level map and background residual of the pair")
        candidates = dict(plan.named) if not background_fields else dict(background_fields)
        for name, item in candidates.items():  # (a NaN node: FieldSpline says so)
            check_field_fits(item, reference.shape, name=f"field {name!r}")
        pair = measure_pair(
            reference, deformed, candidates, thresholds_g if mapped_levels else thresholds_f,
            labels_g, fit_map=gray_levels is True,
            gray_levels=gray_levels if isinstance(gray_levels, GrayLevelMap) else None,
            deformed_coefficients=coefficients_f, region=region,
        )  # fmt: skip
        yield Progress("pair", 1, 1, pair.gray_levels.describe())
    mapping = None if pair.gray_levels.is_identity else pair.gray_levels
    if mode == "reference":
        own, own_labels = reference, labels_g
        other_thresholds = thresholds_g if mapped_levels else thresholds_f
        sampler = spline_sampler(coefficients_f)
    else:
        own = deformed
        own_labels = None if mapping is not None else labels_f
        other_thresholds = thresholds_g
        sampler = spline_sampler(prefilter(reference))

    partial = []
    for index, (name, item) in enumerate(plan.named):
        yield Progress("residual", index, len(plan.named), f"gray residual of {name}")
        spline = FieldSpline.from_field(item)
        halves = window_ladder(error_region_half(item))  # the error estimate's windows
        totals = FieldAccumulator(item, plan.bin_fields[index], halves)
        centers, half = node_voxels(item, own.shape), region_half(item)
        residual = np.empty(own.shape, np.float32) if keep_volumes else None
        mapped = np.empty(own.shape, np.uint8) if keep_volumes else None
        for z, box in slab_boxes(own.shape):
            gradient = halo_gradient(  # whole-volume central differences
                own.__getitem__,
                box,
                own.shape,
                None if mode == "reference" else mapping,
                instrument=True,
            )
            block, _, block_residual, block_mapped = field_block(
                own[z], sampler, spline, box, mode, other_thresholds,
                None if own_labels is None else own_labels[z], plan.bin_fields[index], centers,
                half, mapping, halves, gradient,
                None if region is None else region[z],
            )  # fmt: skip
            totals.add(block)
            if keep_volumes:
                residual[z], mapped[z] = block_residual, block_mapped
        partial.append(field_partial(plan, index, totals, residual, mapped))
    yield Progress("residual", len(plan.named), len(plan.named), "residuals done")
    return assemble_evaluation(
        plan, (thresholds_g, thresholds_f), tables, phase_pair, partial,
        (labels_g, labels_f) if keep_volumes else (None, None), pair,
    )  # fmt: skip


def evaluate_fields(reference, deformed, fields, **options) -> Evaluation:
    """Run :func:`evaluate_iter` to the end and return its :class:`Evaluation`."""
    return run_to_completion(evaluate_iter(reference, deformed, fields, **options))


def evaluate_field(reference, deformed, field: DisplacementField, **options) -> Evaluation:
    """Evaluate a single field (named ``"field"``); see :func:`evaluate_iter` for the options.

    Examples
    --------
    >>> result = evaluate_field(G, F, field)  # doctest: +SKIP
    >>> result["field"].accuracy, result["field"].bins.mean_residual  # doctest: +SKIP
    """
    return evaluate_fields(reference, deformed, {"field": field}, **options)
