"""The self-correcting strategy of the DVC displacement field (paper Fig. 3).

Steps, with the DVC parameters of the first run reused unchanged (no new user parameter):

a) ``D = DVC(G, F)`` (or a field the user already has);
b) clean ``D`` (:func:`.cleaning.clean`: median test, failed and low-ZNCC nodes, inpainting);
c) densify ``D`` by cubic splines (:mod:`.warp`);
d) bring the pair together with ``D``, in one of two frames:

   * ``frame="loaded"`` (the paper's, default): warp the reference to the loaded state,
     ``G'(X + D(X)) = G(X)`` (inverse map by fixed-point iteration);
   * ``frame="reference"``: pull the deformed volume back, ``F~(X) = F(X + D(X))`` (no
     inversion needed);

e) ``ΔD = DVC(G, F~)`` or ``DVC(G', F)`` on the same grid, starting from zero;
f) update the field:

   * ``update="exact"`` (default): the composition of the two motions,
     ``D'(X) = ΔD(X) + D(X + ΔD(X))`` in the reference frame and
     ``D'(X) = D(X) + ΔD(X + D(X))`` in the loaded frame (``ΔD`` is then measured at the
     deformed positions);
   * ``update="sum"``: the paper's ``D' = D + ΔD`` at the same node.

Beyond the paper:

* every pass is judged **locally and against the imaging noise**: the residual
  ``|F(X + D(X)) - G(X)|`` is averaged over each node's cell; a node keeps its corrected value
  unless that local residual rose by more than resampling the noise can explain (the noise floor
  ``r0`` of eq. 1, or the lower quartile of the local residuals where eq. 1 is spoilt), else it
  keeps its previous value. A pass cannot make a node measurably worse;
* passes repeat (``max_passes``) while some region (a node's subvolume) improves by more than
  the noise allows, not while the global mean falls (under noise it barely moves), and only
  while enough nodes moved by enough to improve in another pass (:mod:`.rematch_region`; a pass
  that could only confirm is not run); the reason the loop stopped is recorded;
* the first pass matches only near the nodes it can correct (not their own converged match, or
  bent), a later pass only near the nodes the previous one changed (the subvolume's half-width
  plus the spline's reach), and each judges only the nodes whose update can differ; the other
  matches are "no motion" or the previous pass's less what it applied, and the other nodes keep
  their value (``selective=False`` matches and judges every node);
* the correcting matches use the second-order shape function when the field bends inside a
  subvolume (:func:`pass_order`, chosen from the data, no user parameter);
* nodes whose local residual only an error of more than a voxel explains are flagged
  ``OUTLIER_REPLACED`` (refilled before the passes, flagged after them);
* every pass is recorded as a :class:`CorrectionPass` in ``field.metadata["correction_passes"]``
  (as dicts, for JSON; :func:`correction_table` reads them back).

One loop, two volume back-ends: :func:`correct_volumes_iter` is the loop; every volume
operation goes through a :class:`.volumes.CorrectionVolumes`, in memory for
:func:`correct_iter` (:class:`.volumes.InMemoryVolumes`) or block by block from lazily
read volumes for ``napari_dvc_correct.tiled.correction.correct_tiled_iter``.

See ``docs/method.md`` for the measurements behind the defaults.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Generator

import numpy as np

from ..correlation.params import CorrelationParams
from ..fields.absurd_nodes import flag_absurd_nodes
from ..fields.field import DisplacementField, Provenance, Status
from ..pair_checks import check_pair_and_fields
from ..progress import Progress, forward_progress, run_to_completion
from .acceptance import (
    Judge,
    accept_locally,
    crack_shield,
    flag_and_refill,
    mix_fields,
    noise_only_corrections,
    shrink_to_support,
    unsupported_updates,
)
from .cleaning import clean, masked_nodes
from .noise_fit import regularise
from .options import CorrectionOptions
from .oriented import oriented_step
from .pass_method import correction_grid, node_bend, nothing_to_correct, pass_method
from .pass_update import (
    correction_sigma,
    finish_pass,
    good_nodes,
    update_read_points,
    updated_field,
    zero_start,
)
from .record import (
    CHANGE_THRESHOLD,
    CorrectionPass,
    add_stages,
    correction_table,
    distinct_values,
    failed_pass,
)
from .rematch_region import (
    applied_change,
    first_selection,
    only_confirms,
    remeasurement,
    reuse,
    select,
)
from .volumes import CorrectionVolumes, InMemoryVolumes

__all__ = ["CorrectionPass", "correct", "correct_iter", "correct_volumes_iter", "correction_table"]

#: Another pass runs only while at least this fraction of the nodes improved above the noise.
MIN_IMPROVED_FRACTION = 0.01

#: ... and while at least this fraction moved by enough to improve in another pass
#: (:func:`.rematch_region.changed_nodes`): the same share, predicted before the pass instead of
#: found after it.
MIN_CHANGED_FRACTION = MIN_IMPROVED_FRACTION


def correct_iter(
    reference: np.ndarray,
    deformed: np.ndarray,
    field: DisplacementField | None = None,
    params: CorrelationParams | None = None,
    *,
    frame: str = CorrectionOptions.frame,
    update: str = CorrectionOptions.update,
    max_passes: int = CorrectionOptions.max_passes,
    min_improvement: float = CorrectionOptions.min_improvement,
    mask: np.ndarray | None = None,
    clean_options: dict | None = None,
    selective: bool = True,
    noise_fit: bool = CorrectionOptions.noise_fit,
) -> Generator[Progress, None, DisplacementField]:
    """Self-correct a DVC displacement field, yielding progress; returns the corrected field.

    Parameters
    ----------
    reference, deformed : ndarray, shape (nz, ny, nx)
        ``G`` and ``F``, same shape, any real dtype (processed as float32).
    field : DisplacementField, optional
        ``D`` from a previous DVC of this pair. None runs the DVC first (step a).
    params : CorrelationParams, optional
        DVC parameters; default: those that produced ``field`` (``field.params``), else the
        defaults. The correction reuses them unchanged.
    frame : {"loaded", "reference"}
        Warp ``G`` forward to the loaded state as in the paper (default), or pull ``F`` back to
        the reference (no inversion, but the correcting match then sees the error multiplied by
        the inverse deformation gradient, and fill values near the borders; see docs/method.md).
    update : {"exact", "sum"}
        Compose ``D`` with ``ΔD`` (default) or add them node by node as in the paper.
    max_passes : int
        Most correction passes (each is one DVC run), >= 1.
    min_improvement : float
        Another pass runs only if the last one removed more than this fraction of the local
        residual in excess of the noise floor (mean over the nodes; 0: as long as it falls), and
        only while at least :data:`MIN_IMPROVED_FRACTION` of the nodes improved by more than the
        noise allows.
    mask : ndarray of bool, shape (nz, ny, nx), optional
        Reference-space material mask, passed to every DVC run.
    clean_options : dict, optional
        Keyword arguments for :func:`.cleaning.clean` (threshold, radius, epsilon, smoothing...),
        used on ``D`` and on every ``ΔD``.
    selective : bool
        Match only near the nodes a pass can correct (the first) or the previous pass changed,
        and judge only the nodes that can change (:mod:`.rematch_region`; default). False: every pass
        matches and judges every node (the reference the selective passes are tested against).
        Either way a pass runs only if some node's change can still matter.
    noise_fit : bool
        After the passes, take the GLS affine fit over a node's neighbourhood where that holds
        only matching noise (:mod:`.noise_fit`, ``metadata["correction"]["noise_fit"]``).

    Yields
    ------
    Progress
        Stages ``"clean"``, ``"correction pass k: <DVC stage>"``, ``"residual"``, ``"done"``.

    Returns
    -------
    DisplacementField
        The corrected field on ``D``'s grid. After an applied pass, nodes carry the ZNCC /
        status / iterations of the correcting match and ``Provenance.CORRECTED`` (or
        ``REPLACED`` where that match failed and its correction was interpolated from the
        neighbours); nodes whose correction was refused keep their previous value and quality
        arrays; masked nodes keep their input values; nodes whose local residual no small error
        explains get ``Status.OUTLIER_REPLACED``. ``metadata["correction_passes"]`` holds one
        :class:`CorrectionPass` per pass as a dict (pass 0 = the cleaned input; read them with
        :func:`correction_table`).
        ``metadata["correction"]`` holds the options, the residual before and after, the noise
        floor, the order, subvolume and grid shape (of the last pass) of the correcting matches,
        the flagged node counts, ``stop_reason`` (why the loop stopped, also the last record's
        ``stop``) and ``stages`` (wall seconds of the set-up, warps, correcting DVC with its
        IC-GN and statistics, and local acceptance).
    """
    check_options(frame, update, max_passes, min_improvement)
    reference = np.asanyarray(reference)
    deformed = np.asanyarray(deformed)
    if reference.shape != deformed.shape:
        raise ValueError(
            f"reference {reference.shape} and deformed {deformed.shape} volumes must have the "
            "same shape"
        )
    # both frames: an empty or NaN mask, a field of other volumes or with absurd |u|
    check_pair_and_fields(reference, deformed, {} if field is None else field, mask)
    if field is not None:  # a few |u| > the volume: failed matches, cleaned
        field, _ = flag_absurd_nodes(field, reference.shape)
    volumes = InMemoryVolumes(reference, deformed, frame, mask)
    options = dict(update=update, max_passes=max_passes, min_improvement=min_improvement)
    options.update(clean_options=clean_options, selective=selective, noise_fit=noise_fit)
    return (yield from correct_volumes_iter(volumes, field, params, **options))


def check_options(frame, update, max_passes, min_improvement) -> None:
    """Raise ``ValueError`` for a correction option out of range (see :func:`correct_iter`)."""
    CorrectionOptions(frame, update, max_passes, min_improvement)


def params_of(field: DisplacementField | None, params: CorrelationParams | None):
    """The DVC parameters of a correction: ``params``, else the field's, else the defaults."""
    if params is not None:
        return params
    if field is not None and field.params:
        return CorrelationParams.from_dict(field.params)
    return CorrelationParams()


def correct_volumes_iter(
    volumes: CorrectionVolumes,
    field: DisplacementField | None,
    params: CorrelationParams | None = None,
    *,
    update: str = CorrectionOptions.update,
    max_passes: int = CorrectionOptions.max_passes,
    min_improvement: float = CorrectionOptions.min_improvement,
    clean_options: dict | None = None,
    selective: bool = True,
    noise_fit: bool = CorrectionOptions.noise_fit,
) -> Generator[Progress, None, DisplacementField]:
    """The correction loop of :func:`correct_iter` on any volume back-end.

    ``volumes`` does every volume operation (:class:`.volumes.CorrectionVolumes`:
    in memory, or block by block from lazy volumes in ``napari_dvc_correct.tiled.correction``);
    the fields stay in memory. Options and result as :func:`correct_iter` (the frame is
    ``volumes.frame``); the input volumes and field are checked by the caller. ``volumes`` is
    closed at the end, also on error or when the generator is closed (cancelled).
    """
    check_options(volumes.frame, update, max_passes, min_improvement)
    try:
        return (
            yield from _correction_loop(
                volumes, field, params_of(field, params), update, max_passes, min_improvement,
                clean_options, selective, noise_fit,
            )
        )  # fmt: skip
    finally:
        volumes.close()


def _correction_loop(
    volumes, field, params, update, max_passes, min_improvement, clean_options, selective,
    noise_fit,
):  # fmt: skip
    frame = volumes.frame
    clean_options = dict(clean_options or {})
    clean_options["fill_masked"] = True
    started = time.perf_counter()
    if field is None:
        field = yield from forward_progress(volumes.correlate(params), "DVC")

    yield Progress("clean", 0, 1, "cleaning the field")
    masked = masked_nodes(field)
    current = clean(field, **clean_options)
    yield Progress("clean", 1, 1, f"{current.metadata['cleaning']['rejected']} nodes replaced")

    yield Progress("gray levels", 0, 1, "fitting the gray-level change between the scans")
    gray_levels = yield from volumes.fit_gray_levels(current)
    yield Progress("gray levels", 1, 1, gray_levels.describe())
    residuals = yield from volumes.residuals()
    judge = Judge(None, None, None, current.step, params.half, residuals=residuals)
    yield Progress("residual", 0, 1, "gray residual of the input field")
    local_current = judge.local(current)
    # a discontinuity (a crack) breaks the continuous warp the passes rest on: its nodes are
    # not corrected, and the good measured nodes around it keep their values (the splines
    # through the crack's refilled nodes would otherwise pull them across it)
    flagged_input = judge.unexplained(current, local_current) & ~masked
    crack = judge.discontinuous(current, local_current, flagged_input)
    shielded = crack_shield(current, crack)
    current, local_current, flagged = flag_and_refill(
        judge, current, local_current, masked, clean_options
    )
    moved, residual = yield from volumes.align(current)
    yield Progress("residual", 1, 1, f"mean gray residual {residual:.4g}")
    passes = [
        CorrectionPass(
            number=0,
            mean_gray_residual=residual,
            noise_floor=judge.floor,
            residual_before=residual,
            local_residual_before=_mean(local_current),
            local_residual_after=_mean(local_current),
            accepted=True,
            accepted_nodes=int(current.n_points),
            rejected_nodes=0,
            improved_nodes=0,
            fraction_changed=float(current.metadata["cleaning"]["rejected"])
            / max(1, current.n_points),
            mean_change=0.0,
            max_change=0.0,
            converged_fraction=float(np.mean(field.valid)),
            seconds=time.perf_counter() - started,
        )
    ]
    grid = (current.origin, current.step, current.shape)
    # the bend a pass follows, not a crack's jump (docs/heldout.md)
    pass_params, method = pass_method(current, params, crack | shielded)
    residual_before = residual
    unmasked = max(1, int(np.count_nonzero(~masked)))
    stop = f"max_passes ({int(max_passes)}) reached"
    nothing = nothing_to_correct(current, params, masked)
    stop = nothing or stop
    pass_grid = grid
    previous_raw, next_pass = None, None
    stages = {"setup_s": passes[0].seconds}
    for number in range(1, 1 if nothing else int(max_passes) + 1):
        pass_started = time.perf_counter()
        read_points = update_read_points(current, frame, update)
        pass_grid = (
            grid
            if update == "sum"
            else correction_grid(current, volumes.shape, pass_params, read_points)
        )
        selection = None
        if next_pass is not None and selective:
            changed, last_change, tolerance, change_vectors = next_pass
            selection = select(
                changed, last_change, read_points, read_points, pass_grid,
                (previous_raw.origin, previous_raw.step, previous_raw.shape),
                pass_params.half, tolerance,
            )  # fmt: skip
            selection = selection if not selection.matched.all() else None
        elif selective:  # the first pass matches only near the nodes it can correct
            selection = first_selection(
                current, params, masked, read_points, pass_grid, pass_params.half
            )
        active = None if selection is None else selection.matched
        t0 = time.perf_counter()
        pair = yield from volumes.matching_pair(moved, current)
        t1 = time.perf_counter()
        delta = yield from forward_progress(
            volumes.correlate(
                pass_params, pair, grid=pass_grid, initial=zero_start(pass_grid), active=active
            ),
            f"correction pass {number}",
        )
        volumes.release(pair[2])
        del pair  # its moved volume is `moved`, let go of below when the pass is applied
        add_stages(stages, delta, warp_s=t1 - t0, correcting_dvc_s=time.perf_counter() - t1)
        t0 = time.perf_counter()
        if selection is not None and previous_raw is None:
            delta = reuse(delta, remeasurement(delta, current, read_points), selection.matched)
        elif selection is not None:
            reused = delta.points.reshape(*delta.shape, 3)[~selection.matched]
            loaded = frame == "loaded" and update == "exact"
            taken = applied_change(current, change_vectors, reused, loaded)
            delta = reuse(delta, previous_raw, selection.matched, taken)
        previous_raw = delta
        judged = np.ones(current.shape, bool) if selection is None else selection.judged
        converged = float(np.mean(delta.valid))
        try:
            delta = clean(delta, **clean_options)
        except ValueError:
            passes.append(failed_pass(number, converged, pass_started, passes[-1]))
            stop = "the correcting field could not be cleaned"
            break
        candidate = finish_pass(
            updated_field(current, delta, frame, update), delta, field, masked, read_points
        )
        yield Progress("residual", 0, 1, f"local acceptance of pass {number}")
        floor_before = judge.floor
        # a correction is applied in proportion to its support above the correcting match's
        # own noise; one the noise alone explains is not applied (the node keeps its value)
        sigma = correction_sigma(delta, read_points, current.shape)
        # ... and not at all where the node's whole neighbourhood holds nothing but noise: no
        # correction above its matches' noise, no bend a match could find (a pass there would
        # re-apply the noise of the images that gave the values)
        noise_only = noise_only_corrections(
            current, candidate, sigma, node_bend(current, pass_params.half)
        )
        candidate, unsupported_by_noise = shrink_to_support(current, candidate, sigma)
        unsupported_by_noise |= noise_only
        # a good node whose correcting match failed keeps its value and its status: a failed
        # (or smaller, noisier) correcting match says nothing about the node's own error. So
        # does a correcting match that came out MASKED at a node the first run measured with
        # the mask (the match read at X + D(X) next to the mask's edge): the node stays
        # measured (on the intact real rock 125 of 5 579 measured nodes turned MASKED this way).
        # A mask given to the correction only is news about the nodes: there MASKED stands
        failed_match = good_nodes(current) & ~good_nodes(candidate) & ~masked
        if not field.metadata.get("masked", False):
            failed_match &= candidate.status != Status.MASKED
        refuse = (
            unsupported_updates(delta, read_points)
            | unsupported_by_noise.reshape(-1)
            | failed_match.reshape(-1)
            | shielded.reshape(-1)
        )
        if selection is not None:  # the other nodes keep their value, unjudged
            candidate = mix_fields(current, candidate, judged)
        mixed, local_mixed, accept, improved = accept_locally(
            judge, current, local_current, candidate, refuse=refuse | ~judged.reshape(-1)
        )
        accept[masked] = False
        improved[masked] = False
        n_accepted = int(np.count_nonzero(accept))
        applied, raised = n_accepted > 0, None
        t1 = time.perf_counter()
        add_stages(stages, None, acceptance_s=t1 - t0)
        if applied:  # the pass's moved volume is not needed beside the mixed field's
            volumes.release(moved)
            moved = mixed_moved = None  # (the last pass's mixed_moved is this pass's moved)
            mixed_moved, mixed_residual = yield from volumes.align(mixed)
            if mixed_residual > residual:  # the nodes' local gains did not add up: not applied
                raised, applied = mixed_residual, False
                accept[:], improved[:] = False, False
                volumes.release(mixed_moved)
                # the loop ends here: the field keeps its residual (``residual``, the same number
                # an align of it gives again) and needs no moved volume (what follows only
                # releases it), so it is not aligned again (a warp saved)
                mixed_moved = None
            add_stages(stages, None, warp_s=time.perf_counter() - t1)
        if not applied:
            mixed, mixed_moved, mixed_residual, local_mixed = (
                current,
                moved,
                residual,
                local_current,
            )
        change_vectors = np.nan_to_num(mixed.u - current.u, nan=0.0)
        change_vectors[masked] = 0.0
        node_change = np.linalg.norm(change_vectors, axis=-1)
        change = node_change[~masked]
        record = CorrectionPass(
            number=number,
            mean_gray_residual=mixed_residual,
            noise_floor=judge.floor,
            residual_before=residual,
            local_residual_before=_mean(local_current),
            local_residual_after=_mean(local_mixed),
            accepted=applied,
            accepted_nodes=int(np.count_nonzero(accept)),
            rejected_nodes=int(np.count_nonzero(judged & ~accept & ~masked)),
            improved_nodes=int(np.count_nonzero(improved)),
            fraction_changed=float(np.mean(change > CHANGE_THRESHOLD)) if change.size else 0.0,
            mean_change=float(np.mean(change)) if change.size else 0.0,
            max_change=float(np.max(change)) if change.size else 0.0,
            converged_fraction=converged,
            seconds=time.perf_counter() - pass_started,
            unsupported_nodes=int(
                np.count_nonzero(refuse.reshape(accept.shape) & judged & ~masked)
            ),
            matched_nodes=int(np.prod(pass_grid[2]) if active is None else active.sum()),
            judged_nodes=int(np.count_nonzero(judged & ~masked)),
            failed_match_nodes=int(np.count_nonzero(failed_match & judged & ~masked)),
            noise_refused_nodes=int(np.count_nonzero(unsupported_by_noise & judged & ~masked)),
            order=int(pass_params.order),
            subvolume=int(pass_params.subvolume),
            method=method,
        )
        passes.append(record)
        if raised is None:
            before, after = distinct_values(residual, mixed_residual)
            text = (
                f"pass {number}: {n_accepted} nodes accepted, {record.rejected_nodes} refused, "
                f"{record.improved_nodes} improved above the noise floor {judge.floor:.4g}; "
                f"mean gray residual {before} -> {after}"
            )
        else:
            before, after = distinct_values(residual, raised)
            text = (
                f"pass {number}: {n_accepted} nodes accepted one by one, but together they "
                f"raise the mean gray residual {before} -> {after}: no node changed"
            )
        yield Progress("residual", 1, 1, text)
        if raised is not None:
            stop = (
                f"pass {number} would raise the mean gray residual {before} -> {after}: not applied"
            )
            break
        if not applied:
            stop = f"pass {number} kept no node"
            break
        excess = record.local_residual_before - min(floor_before, judge.floor)
        removed = record.local_residual_before - record.local_residual_after
        current, moved, residual, local_current = mixed, mixed_moved, mixed_residual, local_mixed
        # a further pass can change only what this one moved by enough (pass_reach)
        # ... and only what it moved by enough, at the rate the passes contract
        confirm, changed, tolerance = only_confirms(
            number, node_change, None if next_pass is None else next_pass[1],
            judge.useful(current), judge.region_tolerance, ~masked, MIN_CHANGED_FRACTION,
            judge.last_region - judge.floor,  # each region's residual left above the floor
        )  # fmt: skip
        if number < max_passes and confirm:
            stop = confirm
            break
        if record.improved_nodes < MIN_IMPROVED_FRACTION * unmasked:
            stop = (
                f"pass {number} improved {record.improved_nodes} nodes above the noise floor "
                f"(fewer than {MIN_IMPROVED_FRACTION:.0%})"
            )
            break  # no region improves above the noise floor any more
        if excess > 0 and removed <= min_improvement * excess:
            stop = (
                f"pass {number} removed {removed / excess:.1%} of the local residual above the floor "
                f"(at most min_improvement {min_improvement:.0%})"
            )
            break
        next_pass = (changed, node_change, tolerance, change_vectors)

    mixed_moved = None  # the same volume as moved, which goes on to the oriented step
    # where a band still bends the first run's cubes after the passes: the original pair
    # re-matched under windows along the field's own plane, through the same acceptance
    oriented = yield from oriented_step(
        volumes, judge, current, local_current, params, masked | shielded | crack,
        moved, residual,
    )  # fmt: skip
    current, local_current, moved, residual = (
        oriented.field, oriented.local, oriented.moved, oriented.residual,
    )  # fmt: skip
    oriented.moved = moved = None  # the last field's moved volume is not needed (close() frees it)
    # after the passes, unexplained nodes are flagged but keep their value: refilling them from
    # neighbours that the same fault may have spoiled does not make them any more right
    # flagged nodes whose residual is one-signed straddle a discontinuity (a crack): their own
    # status, so that a user sees the crack rather than "outliers"
    unexplained = judge.unexplained(current, local_current) & ~masked
    cracked = judge.discontinuous(current, local_current, unexplained) | (crack & unexplained)
    current = current.copy()
    current.status[unexplained] = Status.OUTLIER_REPLACED
    current.status[cracked] = Status.DISCONTINUITY
    flagged_after = int(unexplained.sum())
    passes[-1] = dataclasses.replace(passes[-1], stop=stop)
    result = current.copy()
    # a crack's nodes keep their own measurement where they had one (the motion of the side
    # their centre is on), flagged: refilled from both sides it would smear the jump
    measured_crack = cracked & good_nodes(field) & (field.provenance == Provenance.MEASURED)
    kept = masked | measured_crack
    result.u[kept] = field.u[kept]
    if result.gradient is not None and field.gradient is not None:
        result.gradient[kept] = field.gradient[kept]
    result.provenance[measured_crack] = Provenance.MEASURED
    fitted = None
    if noise_fit:  # where the data say "noise": a GLS fit
        usable, t0 = ~(masked | shielded | cracked | unexplained), time.perf_counter()
        fitted = regularise(result, params.subvolume, pass_params.subvolume, usable, current)
        result = fitted.field
        add_stages(stages, None, noise_fit_s=time.perf_counter() - t0)
    result.metadata["correction_passes"] = [p.to_dict() for p in passes]
    result.metadata["gray_levels"] = gray_levels.to_dict()
    result.metadata["correction"] = {
        "frame": frame,
        "update": update,
        "max_passes": int(max_passes),
        "min_improvement": float(min_improvement),
        "passes_applied": int(sum(p.accepted for p in passes[1:])),
        "mean_gray_residual_before": residual_before,
        "mean_gray_residual_after": residual,
        "noise_floor": judge.floor,
        "pass_order": int(pass_params.order),
        "pass_subvolume": int(pass_params.subvolume),
        "pass_method": method,
        "oriented": oriented.summary,
        "pass_grid_shape": [int(n) for n in pass_grid[2]],
        "flagged_before": int(flagged),
        "flagged_after": int(flagged_after),
        # the nodes the user asked to measure (inside their mask): flagged fractions count these
        "measured_nodes": int(np.count_nonzero(~masked)),
        "discontinuity_nodes": int(cracked.sum()),
        "shielded_nodes": int(shielded.sum()),
        "stop_reason": stop,
        "noise_fit": None if fitted is None else fitted.summary(),
        "selective": bool(selective),
        "stages": stages,
        "seconds": time.perf_counter() - started,
    }
    yield Progress("done", 1, 1, f"mean gray residual {residual_before:.4g} -> {residual:.4g}")
    return result


def _mean(values: np.ndarray) -> float:
    finite = np.isfinite(values)
    return float(np.mean(values[finite])) if finite.any() else float("nan")


def correct(
    reference: np.ndarray,
    deformed: np.ndarray,
    field: DisplacementField | None = None,
    params: CorrelationParams | None = None,
    **options,
) -> DisplacementField:
    """Blocking form of :func:`correct_iter` (same parameters, no progress)."""
    return run_to_completion(correct_iter(reference, deformed, field, params, **options))
