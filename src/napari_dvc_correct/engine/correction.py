"""The self-correcting strategy of the DVC displacement field (SPEC §3, paper Fig. 3).

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

Beyond the paper (issue 10):

* every pass is judged **locally and against the imaging noise**: the residual
  ``|F(X + D(X)) - G(X)|`` is averaged over each node's cell; a node keeps its corrected value
  unless that local residual rose by more than resampling the noise can explain (the noise floor
  ``r0`` of eq. 1, or the lower quartile of the local residuals where eq. 1 is spoilt), else it
  keeps its previous value. A pass cannot make a node measurably worse;
* passes repeat (``max_passes``) while some region (a node's subvolume) improves by more than
  the noise allows, not while the global mean falls (under noise it barely moves);
* the correcting matches use the second-order shape function when the field bends inside a
  subvolume (:func:`pass_order`, chosen from the data, no user parameter);
* nodes whose local residual only an error of more than a voxel explains are flagged
  ``OUTLIER_REPLACED`` (refilled before the passes, flagged after them);
* every pass is recorded as a :class:`CorrectionPass` in ``field.metadata["correction_passes"]``
  (as dicts, for JSON; :func:`correction_table` reads them back).

One loop, two volume back-ends (issue 13): :func:`correct_volumes_iter` is the loop; every volume
operation goes through a :class:`.correction_volumes.CorrectionVolumes`, in memory for
:func:`correct_iter` (:class:`.correction_volumes.InMemoryVolumes`) or block by block from lazily
read volumes for ``napari_dvc_correct.tiled.correction.correct_tiled_iter``.

See ``docs/method.md`` for the measurements behind the defaults.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Generator
from dataclasses import dataclass

import numpy as np

from .cleaning import clean, masked_nodes
from .compose import compose
from .correction_volumes import CorrectionVolumes, InMemoryVolumes
from .field import DisplacementField, Provenance, Status
from .local_acceptance import Judge, accept_locally, flag_and_refill, unsupported_updates
from .options import CorrectionOptions
from .pair_checks import check_pair_and_fields
from .params import CorrelationParams
from .pass_params import correction_grid, correction_params
from .progress import Progress, run_to_completion

#: A node counts as "changed" by a pass when its displacement moves by more than this (voxels).
CHANGE_THRESHOLD = 0.1

#: Another pass runs only while at least this fraction of the nodes improved above the noise.
MIN_IMPROVED_FRACTION = 0.01


@dataclass(frozen=True)
class CorrectionPass:
    """The record of one correction pass (pass 0 = the cleaned input field).

    Attributes
    ----------
    number : int
        Pass number, 0 for the cleaned input.
    mean_gray_residual : float
        Mean gray residual of the field after the pass, in the pass's frame (gray levels).
    noise_floor : float
        The imaging-noise floor the pass is judged against (gray levels): eq. 1's background
        residual ``r0`` or the lower quartile of the nodes' cell residuals, whichever is smaller,
        the smallest seen so far (:class:`.local_acceptance.Judge`).
    residual_before : float
        Mean gray residual before the pass (gray levels; pass 0: same as after).
    local_residual_before, local_residual_after : float
        Mean over the nodes of the local residual (reference frame, over each node's cell)
        before and after the pass (gray levels).
    accepted : bool
        Whether the pass changed the field at all (some node accepted).
    accepted_nodes, rejected_nodes : int
        Nodes whose correction was kept / refused (local residual rose by more than the noise
        allows; they keep their previous value).
    improved_nodes : int
        Accepted nodes whose residual over their subvolume fell by more than the noise allows
        (and more than a 0.01-voxel change explains): the regions that "improve above the
        floor", which decide whether another pass runs.
    fraction_changed : float
        Fraction of the (unmasked) nodes moved by more than :data:`CHANGE_THRESHOLD` voxels.
    mean_change, max_change : float
        Node displacement change of the pass (voxels).
    converged_fraction : float
        Fraction of good matches of the pass's DVC.
    seconds : float
        Wall time of the pass.
    unsupported_nodes : int
        Of the refused nodes, those refused because their update would read ``ΔD`` more than a
        step beyond the good correcting matches (:func:`.local_acceptance.unsupported_updates`).
    """

    number: int
    mean_gray_residual: float
    noise_floor: float
    residual_before: float
    local_residual_before: float
    local_residual_after: float
    accepted: bool
    accepted_nodes: int
    rejected_nodes: int
    improved_nodes: int
    fraction_changed: float
    mean_change: float
    max_change: float
    converged_fraction: float
    seconds: float
    unsupported_nodes: int = 0

    def to_dict(self) -> dict:
        """Plain dict for the field's JSON metadata (``number`` stored as ``"pass"``, the key
        older files and readers use)."""
        values = dataclasses.asdict(self)
        return {"pass": values.pop("number"), **values}

    @classmethod
    def from_dict(cls, values: dict) -> CorrectionPass:
        """Read a record back from metadata (also the string-keyed records of older files)."""
        values = dict(values)
        if "pass" in values and "number" not in values:
            values["number"] = values.pop("pass")
        nan = float("nan")
        defaults = {
            "noise_floor": nan,
            "residual_before": values.get("mean_gray_residual", nan),
            "local_residual_before": nan,
            "local_residual_after": nan,
            "accepted_nodes": 0,
            "rejected_nodes": 0,
            "improved_nodes": 0,
            "unsupported_nodes": 0,
        }
        names = {f.name for f in dataclasses.fields(cls)}
        merged = {**defaults, **{k: v for k, v in values.items() if k in names}}
        return cls(**merged)


def _relabel(progress: Progress, prefix: str) -> Progress:
    return Progress(f"{prefix}: {progress.stage}", progress.done, progress.total, progress.message)


def forward_progress(generator, prefix: str):
    """Re-yield an engine generator's progress with stages prefixed by ``prefix``; return its
    result (use as ``result = yield from forward_progress(gen, "pass 1")``)."""
    try:
        while True:
            try:
                progress = next(generator)
            except StopIteration as stop:
                return stop.value
            yield _relabel(progress, prefix)
    finally:
        generator.close()  # a cancelled caller stops the inner run too (its Dask work, its files)


def _update(current: DisplacementField, delta: DisplacementField, frame: str, update: str):
    if update == "sum":
        return compose(current, delta, mode="sum")
    if frame == "reference":
        return compose(delta, current)
    return compose(current, delta)


def _zeros(grid) -> DisplacementField:
    """The zero start of a correcting DVC on ``grid`` (origin, step, shape)."""
    zero = DisplacementField.zeros(*grid)
    zero.gradient = np.zeros((*grid[2], 3, 3))
    return zero


def _read_points(current: DisplacementField, frame: str, update: str) -> np.ndarray:
    """Where each node's update reads ``ΔD``: ``X + D(X)`` (loaded frame, exact), else ``X``."""
    if frame == "loaded" and update == "exact":
        return current.points + current.u.reshape(-1, 3)
    return current.points


def _finish_pass(
    candidate: DisplacementField,
    delta: DisplacementField,
    input_field: DisplacementField,
    masked: np.ndarray,
    read_points: np.ndarray,
) -> DisplacementField:
    """Quality arrays of a corrected field: those of the correcting match; masked nodes kept.

    A node's correcting match is the node of ``delta`` nearest to where its update reads ``ΔD``
    (``read_points``: its displaced position in the loaded frame, itself otherwise). Nodes where
    that match failed or was masked (its value interpolated from the neighbours' by the
    cleaning) are ``REPLACED``, the others ``CORRECTED``.
    """
    index = np.rint((read_points - np.asarray(delta.origin)) / np.asarray(delta.step))
    index = np.nan_to_num(index, nan=0.0)
    nearest = tuple(
        np.clip(index[:, a], 0, delta.shape[a] - 1).astype(np.intp).reshape(candidate.shape)
        for a in range(3)
    )
    candidate.zncc = delta.zncc[nearest].copy()
    candidate.status = delta.status[nearest].copy()
    candidate.iterations = delta.iterations[nearest].copy()
    candidate.provenance = np.full(candidate.shape, Provenance.CORRECTED, np.uint8)
    interpolated = np.isin(delta.provenance[nearest], [Provenance.REPLACED, Provenance.MASKED])
    candidate.provenance[interpolated] = Provenance.REPLACED
    candidate.provenance[masked] = Provenance.MASKED
    candidate.status[masked] = input_field.status[masked]
    return candidate


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
        floor, the order, subvolume and grid shape (of the last pass) of the correcting matches
        and the flagged node counts.
    """
    check_options(frame, update, max_passes, min_improvement)
    reference = np.asanyarray(reference)
    deformed = np.asanyarray(deformed)
    if reference.shape != deformed.shape:
        raise ValueError(
            f"reference {reference.shape} and deformed {deformed.shape} volumes must have the "
            "same shape"
        )
    # both frames: an empty or NaN mask, a field of other volumes or with absurd |u| (issue 12)
    check_pair_and_fields(reference, deformed, {} if field is None else field, mask)
    volumes = InMemoryVolumes(reference, deformed, frame, mask)
    options = dict(update=update, max_passes=max_passes, min_improvement=min_improvement)
    return (
        yield from correct_volumes_iter(
            volumes, field, params, **options, clean_options=clean_options
        )
    )


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
) -> Generator[Progress, None, DisplacementField]:
    """The correction loop of :func:`correct_iter` on any volume back-end (issue 13).

    ``volumes`` does every volume operation (:class:`.correction_volumes.CorrectionVolumes`:
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
                clean_options,
            )
        )  # fmt: skip
    finally:
        volumes.close()


def _correction_loop(
    volumes, field, params, update, max_passes, min_improvement, clean_options
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

    residuals = yield from volumes.residuals()
    judge = Judge(None, None, None, current.step, params.half, residuals=residuals)
    yield Progress("residual", 0, 1, "gray residual of the input field")
    local_current = judge.local(current)
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
    pass_params = correction_params(current, params)
    residual_before = residual
    unmasked = max(1, int(np.count_nonzero(~masked)))
    for number in range(1, int(max_passes) + 1):
        pass_started = time.perf_counter()
        pair = yield from volumes.matching_pair(moved, current)
        read_points = _read_points(current, frame, update)
        pass_grid = (
            grid
            if update == "sum"
            else correction_grid(current, volumes.shape, pass_params, read_points)
        )
        delta = yield from forward_progress(
            volumes.correlate(pass_params, pair, grid=pass_grid, initial=_zeros(pass_grid)),
            f"correction pass {number}",
        )
        volumes.release(pair[2])
        converged = float(np.mean(delta.valid))
        try:
            delta = clean(delta, **clean_options)
        except ValueError:
            passes.append(_failed_pass(number, converged, pass_started, passes[-1]))
            break
        candidate = _finish_pass(
            _update(current, delta, frame, update), delta, field, masked, read_points
        )
        yield Progress("residual", 0, 1, f"local acceptance of pass {number}")
        floor_before = judge.floor
        refuse = unsupported_updates(delta, read_points)
        mixed, local_mixed, accept, improved = accept_locally(
            judge, current, local_current, candidate, refuse=refuse
        )
        accept[masked] = False
        improved[masked] = False
        n_accepted = int(np.count_nonzero(accept))
        applied = n_accepted > 0
        if applied:
            mixed_moved, mixed_residual = yield from volumes.align(mixed)
        else:
            mixed, mixed_moved, mixed_residual, local_mixed = (
                current,
                moved,
                residual,
                local_current,
            )
        change = np.linalg.norm(mixed.u - current.u, axis=-1)[~masked]
        record = CorrectionPass(
            number=number,
            mean_gray_residual=mixed_residual,
            noise_floor=judge.floor,
            residual_before=residual,
            local_residual_before=_mean(local_current),
            local_residual_after=_mean(local_mixed),
            accepted=applied,
            accepted_nodes=n_accepted,
            rejected_nodes=int(np.count_nonzero(~accept & ~masked)),
            improved_nodes=int(np.count_nonzero(improved)),
            fraction_changed=float(np.mean(change > CHANGE_THRESHOLD)) if change.size else 0.0,
            mean_change=float(np.mean(change)) if change.size else 0.0,
            max_change=float(np.max(change)) if change.size else 0.0,
            converged_fraction=converged,
            seconds=time.perf_counter() - pass_started,
            unsupported_nodes=int(np.count_nonzero(refuse.reshape(accept.shape) & ~masked)),
        )
        passes.append(record)
        yield Progress(
            "residual",
            1,
            1,
            f"pass {number}: {n_accepted} nodes accepted, {record.rejected_nodes} refused, "
            f"{record.improved_nodes} improved above the noise floor {judge.floor:.4g}; "
            f"mean gray residual {residual:.4g} -> {mixed_residual:.4g}",
        )
        if not applied:
            break
        excess = record.local_residual_before - min(floor_before, judge.floor)
        removed = record.local_residual_before - record.local_residual_after
        volumes.release(moved)
        current, moved, residual, local_current = mixed, mixed_moved, mixed_residual, local_mixed
        if record.improved_nodes < MIN_IMPROVED_FRACTION * unmasked:
            break  # no region improves above the noise floor any more
        if excess > 0 and removed <= min_improvement * excess:
            break

    # after the passes, unexplained nodes are flagged but keep their value: refilling them from
    # neighbours that the same fault may have spoiled does not make them any more right
    unexplained = judge.unexplained(current, local_current) & ~masked
    current = current.copy()
    current.status[unexplained] = Status.OUTLIER_REPLACED
    flagged_after = int(unexplained.sum())
    result = current.copy()
    result.u[masked] = field.u[masked]
    if result.gradient is not None and field.gradient is not None:
        result.gradient[masked] = field.gradient[masked]
    result.metadata["correction_passes"] = [p.to_dict() for p in passes]
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
        "pass_grid_shape": [int(n) for n in pass_grid[2]],
        "flagged_before": int(flagged),
        "flagged_after": int(flagged_after),
        "seconds": time.perf_counter() - started,
    }
    yield Progress("done", 1, 1, f"mean gray residual {residual_before:.4g} -> {residual:.4g}")
    return result


def _mean(values: np.ndarray) -> float:
    finite = np.isfinite(values)
    return float(np.mean(values[finite])) if finite.any() else float("nan")


def _failed_pass(
    number: int, converged: float, started: float, previous: CorrectionPass
) -> CorrectionPass:
    return CorrectionPass(
        number=number,
        mean_gray_residual=float("nan"),
        noise_floor=previous.noise_floor,
        residual_before=previous.mean_gray_residual,
        local_residual_before=previous.local_residual_after,
        local_residual_after=float("nan"),
        accepted=False,
        accepted_nodes=0,
        rejected_nodes=0,
        improved_nodes=0,
        fraction_changed=0.0,
        mean_change=0.0,
        max_change=0.0,
        converged_fraction=converged,
        seconds=time.perf_counter() - started,
    )


def correct(
    reference: np.ndarray,
    deformed: np.ndarray,
    field: DisplacementField | None = None,
    params: CorrelationParams | None = None,
    **options,
) -> DisplacementField:
    """Blocking form of :func:`correct_iter` (same parameters, no progress)."""
    return run_to_completion(correct_iter(reference, deformed, field, params, **options))


def correction_table(field: DisplacementField) -> list[CorrectionPass]:
    """The per-pass records of a corrected field (``metadata["correction_passes"]``), or []."""
    return [
        entry if isinstance(entry, CorrectionPass) else CorrectionPass.from_dict(entry)
        for entry in field.metadata.get("correction_passes", [])
    ]
