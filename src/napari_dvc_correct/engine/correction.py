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

Beyond the paper, the correction is repeated while the mean gray residual falls (``max_passes``),
and every pass is reported (residual, fraction of nodes changed) in
``field.metadata["correction_passes"]``. A pass that does not lower the residual is not applied.
See ``docs/method.md`` for the measurements behind the defaults.
"""

from __future__ import annotations

import time
from collections.abc import Generator

import numpy as np

from . import warp
from .cleaning import clean, masked_nodes
from .compose import compose
from .correlate import correlate_iter
from .field import DisplacementField, Provenance
from .field_spline import FieldSpline
from .interpolation import prefilter
from .pair_checks import check_pair_and_fields
from .params import CorrelationParams
from .progress import Progress, run_to_completion

FRAMES = ("reference", "loaded")
UPDATES = ("exact", "sum")

#: A node counts as "changed" by a pass when its displacement moves by more than this (voxels).
CHANGE_THRESHOLD = 0.1


def _relabel(progress: Progress, prefix: str) -> Progress:
    return Progress(f"{prefix}: {progress.stage}", progress.done, progress.total, progress.message)


def forward_progress(generator, prefix: str):
    """Re-yield an engine generator's progress with stages prefixed by ``prefix``; return its
    result (use as ``result = yield from forward_progress(gen, "pass 1")``)."""
    while True:
        try:
            progress = next(generator)
        except StopIteration as stop:
            return stop.value
        yield _relabel(progress, prefix)


def _finite_or_fill(volume: np.ndarray, fill: float) -> np.ndarray:
    volume = np.asarray(volume, dtype=np.float32)
    bad = ~np.isfinite(volume)
    if bad.any():
        volume = volume.copy()
        volume[bad] = fill
    return volume


def _hull_mean(difference: np.ndarray, hull) -> float:
    block = difference[hull]
    finite = np.isfinite(block)
    return float(np.mean(block[finite], dtype=np.float64)) if finite.any() else float("nan")


class _Pair:
    """The two volumes with their spline coefficients, prefiltered once for every pass."""

    def __init__(self, reference, deformed, frame: str, mask):
        self.reference = np.ascontiguousarray(reference, dtype=np.float32)
        self.deformed = np.ascontiguousarray(deformed, dtype=np.float32)
        self.frame = frame
        self.mask = None if mask is None else np.asarray(mask) != 0
        if frame == "reference":
            self.coefficients = prefilter(self.deformed)
            self.fill = float(np.mean(self.deformed))
        else:
            self.coefficients = prefilter(self.reference)
            self.fill = float(np.mean(self.reference))
            self.mask_coefficients = (
                None if self.mask is None else prefilter(self.mask.astype(np.float32))
            )

    def align(self, field: DisplacementField) -> tuple[np.ndarray, float]:
        """The moved volume for the next DVC, and the mean gray residual of ``field``."""
        spline = FieldSpline.from_field(field)
        if self.frame == "reference":
            moved = warp.pull_back(
                self.deformed, spline, coefficients=self.coefficients, cval=np.nan
            )
            residual = _hull_mean(
                np.abs(moved - self.reference), spline.hull_slices(self.reference.shape)
            )
        else:
            moved, residual = warp.warp_forward_with_residual(
                self.reference, self.deformed, spline, coefficients=self.coefficients
            )
        return _finite_or_fill(moved, self.fill), residual

    def matching_pair(self, moved: np.ndarray, field: DisplacementField):
        """``(reference, deformed, mask)`` for the DVC of step e."""
        if self.frame == "reference":
            return self.reference, moved, self.mask
        mask = None
        if self.mask is not None:
            warped = warp.warp_forward(
                self.mask, field, coefficients=self.mask_coefficients, cval=0.0
            )
            mask = warped > 0.5
            if not mask.any():
                mask = None
        return moved, self.deformed, mask


def _update(current: DisplacementField, delta: DisplacementField, frame: str, update: str):
    if update == "sum":
        return compose(current, delta, mode="sum")
    if frame == "reference":
        return compose(delta, current)
    return compose(current, delta)


def _finish_pass(
    candidate: DisplacementField,
    delta: DisplacementField,
    input_field: DisplacementField,
    masked: np.ndarray,
) -> DisplacementField:
    """Quality arrays of a corrected field: those of the correcting match; masked nodes kept.

    Nodes where the correcting match failed or was masked (its value interpolated from the
    neighbours' by the cleaning) are ``REPLACED``, the others ``CORRECTED``.
    """
    candidate.zncc = delta.zncc.copy()
    candidate.status = delta.status.copy()
    candidate.iterations = delta.iterations.copy()
    candidate.provenance = np.full(candidate.shape, Provenance.CORRECTED, np.uint8)
    interpolated = np.isin(delta.provenance, [Provenance.REPLACED, Provenance.MASKED])
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
    frame: str = "loaded",
    update: str = "exact",
    max_passes: int = 3,
    min_improvement: float = 0.01,
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
        Another pass runs only if the last one lowered the mean gray residual by more than this
        fraction (0 repeats as long as it falls at all).
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
        neighbours); masked nodes keep their input values. ``metadata["correction_passes"]`` is a list with
        one entry per pass (pass 0 = the cleaned input): ``mean_gray_residual`` (gray levels),
        ``accepted``, ``fraction_changed`` (nodes moved by more than
        :data:`CHANGE_THRESHOLD` voxels), ``mean_change`` and ``max_change`` (voxels),
        ``converged_fraction`` of the correcting DVC, ``seconds``.
        ``metadata["correction"]`` holds the options and the residual before and after.
    """
    if frame not in FRAMES:
        raise ValueError(f"frame must be one of {FRAMES}, got {frame!r}")
    if update not in UPDATES:
        raise ValueError(f"update must be one of {UPDATES}, got {update!r}")
    if int(max_passes) < 1:
        raise ValueError(f"max_passes must be >= 1, got {max_passes!r}")
    if not 0.0 <= min_improvement < 1.0:
        raise ValueError(f"min_improvement must be in [0, 1), got {min_improvement!r}")
    clean_options = dict(clean_options or {})
    clean_options["fill_masked"] = True
    reference = np.asanyarray(reference)
    deformed = np.asanyarray(deformed)
    if reference.shape != deformed.shape:
        raise ValueError(
            f"reference {reference.shape} and deformed {deformed.shape} volumes must have the "
            "same shape"
        )
    # both frames: an empty or NaN mask, a field of other volumes or with absurd |u| (issue 12)
    check_pair_and_fields(reference, deformed, {} if field is None else field, mask)
    if params is None:
        params = (
            CorrelationParams.from_dict(field.params)
            if field is not None and field.params
            else CorrelationParams()
        )
    started = time.perf_counter()
    if field is None:
        field = yield from forward_progress(
            correlate_iter(reference, deformed, params, mask=mask), "DVC"
        )

    yield Progress("clean", 0, 1, "cleaning the field")
    masked = masked_nodes(field)
    current = clean(field, **clean_options)
    yield Progress("clean", 1, 1, f"{current.metadata['cleaning']['rejected']} nodes replaced")

    pair = _Pair(reference, deformed, frame, mask)
    yield Progress("residual", 0, 1, "gray residual of the input field")
    moved, residual = pair.align(current)
    yield Progress("residual", 1, 1, f"mean gray residual {residual:.4g}")
    passes = [
        {
            "pass": 0,
            "mean_gray_residual": residual,
            "accepted": True,
            "fraction_changed": float(current.metadata["cleaning"]["rejected"])
            / max(1, current.n_points),
            "mean_change": 0.0,
            "max_change": 0.0,
            "converged_fraction": float(np.mean(field.valid)),
            "seconds": time.perf_counter() - started,
        }
    ]
    grid = (current.origin, current.step, current.shape)
    zero = DisplacementField.zeros(current.origin, current.step, current.shape)
    zero.gradient = np.zeros((*current.shape, 3, 3))
    residual_before = residual
    for number in range(1, int(max_passes) + 1):
        pass_started = time.perf_counter()
        g, f, pass_mask = pair.matching_pair(moved, current)
        delta = yield from forward_progress(
            correlate_iter(g, f, params, mask=pass_mask, grid=grid, initial=zero),
            f"correction pass {number}",
        )
        converged = float(np.mean(delta.valid))
        try:
            delta = clean(delta, **clean_options)
        except ValueError:
            passes.append(_failed_pass(number, converged, pass_started))
            break
        candidate = _finish_pass(_update(current, delta, frame, update), delta, field, masked)
        yield Progress("residual", 0, 1, f"gray residual after pass {number}")
        candidate_moved, candidate_residual = pair.align(candidate)
        change = np.linalg.norm(candidate.u - current.u, axis=-1)[~masked]
        accepted = bool(candidate_residual < residual)
        passes.append(
            {
                "pass": number,
                "mean_gray_residual": candidate_residual,
                "accepted": accepted,
                "fraction_changed": float(np.mean(change > CHANGE_THRESHOLD))
                if change.size
                else 0.0,
                "mean_change": float(np.mean(change)) if change.size else 0.0,
                "max_change": float(np.max(change)) if change.size else 0.0,
                "converged_fraction": converged,
                "seconds": time.perf_counter() - pass_started,
            }
        )
        yield Progress(
            "residual",
            1,
            1,
            f"pass {number}: mean gray residual {residual:.4g} -> {candidate_residual:.4g}"
            + ("" if accepted else " (not applied)"),
        )
        if not accepted:
            break
        improvement = (residual - candidate_residual) / residual if residual > 0 else 0.0
        current, moved, residual = candidate, candidate_moved, candidate_residual
        if improvement <= min_improvement:
            break

    result = current.copy()
    result.u[masked] = field.u[masked]
    if result.gradient is not None and field.gradient is not None:
        result.gradient[masked] = field.gradient[masked]
    result.metadata["correction_passes"] = passes
    result.metadata["correction"] = {
        "frame": frame,
        "update": update,
        "max_passes": int(max_passes),
        "min_improvement": float(min_improvement),
        "passes_applied": int(sum(p["accepted"] for p in passes[1:])),
        "mean_gray_residual_before": residual_before,
        "mean_gray_residual_after": residual,
        "seconds": time.perf_counter() - started,
    }
    yield Progress("done", 1, 1, f"mean gray residual {residual_before:.4g} -> {residual:.4g}")
    return result


def _failed_pass(number: int, converged: float, started: float) -> dict:
    return {
        "pass": number,
        "mean_gray_residual": float("nan"),
        "accepted": False,
        "fraction_changed": 0.0,
        "mean_change": 0.0,
        "max_change": 0.0,
        "converged_fraction": converged,
        "seconds": time.perf_counter() - started,
    }


def correct(
    reference: np.ndarray,
    deformed: np.ndarray,
    field: DisplacementField | None = None,
    params: CorrelationParams | None = None,
    **options,
) -> DisplacementField:
    """Blocking form of :func:`correct_iter` (same parameters, no progress)."""
    return run_to_completion(correct_iter(reference, deformed, field, params, **options))


def correction_table(field: DisplacementField) -> list[dict]:
    """The per-pass report of a corrected field (``metadata["correction_passes"]``), or []."""
    return list(field.metadata.get("correction_passes", []))
