"""Scan series: the total and incremental strategies (paper Fig. 2).

* ``strategy="total"``: every state ``k`` is correlated with the first, ``U_0→k = DVC(V0, Vk)``.
  Robust against error accumulation, but decorrelates when the deformation grows large.
* ``strategy="incremental"``: adjacent states are correlated, ``u_k−1→k = DVC(Vk−1, Vk)``, and
  the increments are merged by displacement superposition, i.e. composition
  (:func:`.compose.compose`): ``U_0→k(X) = U_0→k−1(X) + u_k−1→k(X + U_0→k−1(X))``, with the
  increment interpolated at the displaced positions by cubic splines.

The self-correction (:mod:`.self_correction`) can be applied to every increment
(``correct_increments``, against ``Vk−1`` and ``Vk``) and/or to every merged total
(``correct_total``, against ``V0`` and ``Vk``; the corrected total is the one the next increment
is composed onto). With the total strategy both options mean "correct each total".

The POIs are a grid (``grid``, default the whole volume's) or a list of points (``points``,
:func:`.correlate_points.correlate_points`; results at exactly those points of the first state).
At points the incremental strategy follows each point: the increment ``k−1→k`` is measured at
``X + U_0→k−1(X)`` and added, ``U_0→k(X) = U_0→k−1(X) + u_k−1→k(X + U_0→k−1(X))``, with no
interpolation; a point lost in one state stays lost in the later ones.

On a grid, one loop (:func:`series_volumes_iter`) runs every strategy and option; what it does to
the volumes (correlate a pair, correct a field of a pair, move the mask, the mean gray residual)
goes through a :class:`.volumes.SeriesVolumes`: in memory for :func:`series_iter`, batch
by batch from lazily read volumes for ``napari_dvc_correct.tiled.series.series_tiled_iter``.
"""

from __future__ import annotations

import time
from collections.abc import Generator, Sequence
from dataclasses import dataclass, field

import numpy as np

from ..correction.cleaning import clean
from ..correlation.correlate_points import correlate_points
from ..correlation.params import CorrelationParams
from ..fields.compose import compose
from ..fields.field import DisplacementField, Provenance, Status, grid_for_volume
from ..fields.scattered import ScatteredField
from ..progress import Progress, forward_progress, run_to_completion, state_of
from .volumes import InMemorySeries, SeriesVolumes

STRATEGIES = ("total", "incremental")


@dataclass
class SeriesResult:
    """Fields of a scan series.

    Attributes
    ----------
    totals : list of DisplacementField
        ``U_0→k`` for ``k = 1 .. n-1`` on the grid of the first state (reference voxels of V0),
        self-corrected where the run corrects.
    increments : list of DisplacementField
        ``u_k−1→k`` for the incremental strategy (each in the voxels of state ``k-1``, corrected
        where the run corrects increments, and the first one where it corrects the first
        total); empty for the total strategy.
    uncorrected : list of DisplacementField
        The uncorrected total ``U_0→k`` of each state, the series as if no self-correction had
        run, on the same grid (first state's nodes, reference voxels of V0):

        * total strategy: the DVC of ``(V0, Vk)``, before its correction;
        * incremental strategy: the composition of the *measured* increments only,
          ``Ũ_0→k(X) = Ũ_0→k−1(X) + ũ_k−1→k(X + Ũ_0→k−1(X))``, with ``ũ_k−1→k`` the DVC of
          ``(Vk−1, Vk)`` before any correction (grid in state ``k-1``'s voxels) and
          ``Ũ_0→1 = ũ_0→1``. (The increments were measured in a self-corrected run: the only
          trace of the corrections in ``Ũ`` is the mask carried to state ``k-1``, which moves
          with the corrected total.)

        Each one is evaluated on its own pair ``(V0, Vk)``, as the corrected total is. Without
        self-correction these are the totals themselves (the same objects).
    strategy : str
    self_corrected : bool
        Whether the run self-corrected (increments, totals or both).
    """

    totals: list = field(default_factory=list)
    increments: list = field(default_factory=list)
    uncorrected: list = field(default_factory=list)
    strategy: str = "incremental"
    self_corrected: bool = False

    def summary(self) -> list[dict]:
        """One row per state (the first state included, with zero displacement).

        ``mean_gray_residual`` is that of the total, ``mean_gray_residual_uncorrected`` that of
        the uncorrected total (:attr:`uncorrected`; the same number without self-correction).
        """
        rows = [
            {
                "state": 0,
                "strategy": self.strategy,
                "valid_fraction": 1.0,
                "mean_displacement": 0.0,
                "max_displacement": 0.0,
                "mean_zncc": float("nan"),
                "mean_gray_residual": float("nan"),
                "mean_gray_residual_uncorrected": float("nan"),
                "correction_passes": 0,
            }
        ]
        for state, total in enumerate(self.totals, start=1):
            valid = total.valid
            magnitude = np.linalg.norm(total.u, axis=-1)[valid]
            zncc = total.zncc[valid]
            info = total.metadata.get("series", {})
            rows.append(
                {
                    "state": state,
                    "strategy": self.strategy,
                    "valid_fraction": float(valid.mean()),
                    "mean_displacement": float(magnitude.mean()) if magnitude.size else np.nan,
                    "max_displacement": float(magnitude.max()) if magnitude.size else np.nan,
                    "mean_zncc": float(np.nanmean(zncc)) if np.isfinite(zncc).any() else np.nan,
                    "mean_gray_residual": info.get("mean_gray_residual", float("nan")),
                    "mean_gray_residual_uncorrected": info.get(
                        "mean_gray_residual_uncorrected", float("nan")
                    ),
                    "correction_passes": info.get("correction_passes", 0),
                }
            )
        return rows


def _check_volumes(volumes) -> list:
    volumes = list(volumes)
    if len(volumes) < 2:
        raise ValueError(f"a series needs at least 2 volumes, got {len(volumes)}")
    shapes = {tuple(np.shape(v)) for v in volumes}
    if len(shapes) != 1:
        raise ValueError(f"all volumes of a series must have the same shape, got {sorted(shapes)}")
    if len(next(iter(shapes))) != 3:
        raise ValueError(f"volumes must be 3-D (z, y, x), got shape {next(iter(shapes))}")
    return volumes


def _passes_applied(corrected: DisplacementField) -> int:
    return int(corrected.metadata.get("correction", {}).get("passes_applied", 0))


def series_iter(
    volumes: Sequence[np.ndarray],
    params: CorrelationParams | None = None,
    *,
    strategy: str = "incremental",
    correct_increments: bool = False,
    correct_total: bool = False,
    correction_options: dict | None = None,
    mask: np.ndarray | None = None,
    grid: tuple | None = None,
    points: np.ndarray | None = None,
) -> Generator[Progress, None, SeriesResult]:
    """Displacement fields of a scan series, yielding progress; returns a :class:`SeriesResult`.

    Parameters
    ----------
    volumes : sequence of ndarray, each shape (nz, ny, nx)
        States ``V0, V1, ...`` in loading order (same shape; memory maps are fine).
    params : CorrelationParams, optional
        DVC parameters for every correlation (and every correction pass).
    strategy : {"incremental", "total"}
    correct_increments : bool
        Self-correct each increment (incremental) or each total (total strategy).
    correct_total : bool
        Self-correct each merged total against ``V0`` (incremental) or each total (total).
    correction_options : dict, optional
        Keyword arguments for :func:`.self_correction.correct_iter` (frame, update, max_passes...).
    mask : ndarray of bool, shape (nz, ny, nx), optional
        Material mask in the first state's voxels; for increments it is carried to state
        ``k-1`` by the merged field.
    grid : (origin, step, shape), optional
        POI grid in the first state's voxels (e.g. :func:`.placement.grid_for_region`); default
        :func:`.field.grid_for_volume`.
    points : array-like, shape (N, 3), optional
        Points of interest ``(z, y, x)`` in the first state's voxels instead of a grid: the
        totals (and increments) are :class:`.scattered.ScatteredField` at those points. Not
        with a self-correction, nor with a mask in the incremental strategy.

    Yields
    ------
    Progress
        Stages prefixed by ``"state k of n"`` (:func:`.progress.state_of`).
    """
    if strategy not in STRATEGIES:
        raise ValueError(f"strategy must be one of {STRATEGIES}, got {strategy!r}")
    volumes = _check_volumes(volumes)
    params = CorrelationParams() if params is None else params
    options = dict(correction_options or {})
    if points is not None:
        if correct_increments or correct_total:
            raise ValueError("a series at points cannot be self-corrected (it needs a grid)")
        if grid is not None:
            raise ValueError("give a grid or points, not both")
        if mask is not None and strategy == "incremental":
            raise ValueError("a mask with points needs the total strategy")
        result = yield from _points_series(volumes, params, strategy, mask, points)
        return result
    if grid is None:
        grid = grid_for_volume(np.shape(volumes[0]), params.subvolume, params.step)
    backend = InMemorySeries(volumes, params, grid, mask, options)
    return (
        yield from series_volumes_iter(
            backend,
            strategy=strategy,
            correct_increments=correct_increments,
            correct_total=correct_total,
        )
    )


def series_volumes_iter(
    volumes: SeriesVolumes,
    *,
    strategy: str = "incremental",
    correct_increments: bool = False,
    correct_total: bool = False,
) -> Generator[Progress, None, SeriesResult]:
    """The series loop of :func:`series_iter` on a grid, on any volume back-end.

    ``volumes`` does every volume operation (:class:`.volumes.SeriesVolumes`: in memory,
    or batch by batch from lazy volumes in ``napari_dvc_correct.tiled.series``); the fields stay
    in memory. Options and result as :func:`series_iter` (the POI grid, the mask and the
    correction options are the back-end's); the inputs are checked by the caller. ``volumes`` is
    closed at the end, also on error or when the generator is closed (cancelled).
    """
    if strategy not in STRATEGIES:
        raise ValueError(f"strategy must be one of {STRATEGIES}, got {strategy!r}")
    try:
        return (yield from _series_loop(volumes, strategy, correct_increments, correct_total))
    finally:
        volumes.close()


def _series_loop(volumes, strategy, correct_increments, correct_total):
    result = SeriesResult(strategy=strategy)
    n = volumes.n_states
    started = time.perf_counter()
    corrects = correct_increments or correct_total
    result.self_corrected = bool(corrects)
    for k in range(1, n):
        label = state_of(k, n - 1)
        state_started = time.perf_counter()
        if strategy == "total" or k == 1:
            total = yield from forward_progress(volumes.correlate(0, k, volumes.mask), label)
            if strategy == "incremental":
                result.increments.append(total.copy())
            plain = total  # the uncorrected total: the measured one
            corrected_here = corrects
        else:
            previous = result.totals[-1]
            filled = clean(previous, fill_masked=True)
            state_mask = None
            if volumes.mask is not None:
                state_mask = yield from forward_progress(
                    volumes.carry_mask(filled), f"{label}: mask"
                )
            try:
                increment = yield from forward_progress(
                    volumes.correlate(k - 1, k, state_mask), f"{label}: increment"
                )
                measured = increment
                if correct_increments:
                    increment = yield from forward_progress(
                        volumes.correct(k - 1, k, increment, state_mask),
                        f"{label}: increment correction",
                    )
            finally:
                volumes.release(state_mask)
            result.increments.append(increment)
            increment_filled = clean(increment, fill_masked=True)
            total = compose(previous, increment_filled)
            corrected_here = correct_total
            # the uncorrected chain: the measured increments composed onto each other only
            plain = _compose_filled(result.uncorrected[-1], measured, total) if corrects else total
        passes = 0
        if corrected_here:
            total = yield from forward_progress(
                volumes.correct(0, k, total, volumes.mask), f"{label}: correction"
            )
            passes = _passes_applied(total)
            if strategy == "incremental" and k == 1:
                result.increments[0] = total.copy()
        yield Progress(label, 0, 1, "gray residual")
        residual = yield from _residual(volumes, k, total, label)
        residual_uncorrected = (
            (yield from _residual(volumes, k, plain, f"{label}: uncorrected"))
            if plain is not total
            else residual
        )
        total.metadata["series"] = {
            "state": k,
            "strategy": strategy,
            "reference_state": 0,
            "corrected_increments": bool(correct_increments),
            "corrected_total": bool(corrected_here),
            "correction_passes": passes,
            "mean_gray_residual": residual,
            "mean_gray_residual_uncorrected": residual_uncorrected,
            "seconds": time.perf_counter() - state_started,
        }
        if plain is not total:  # its own dictionary (a corrected field may share one)
            plain.metadata = {
                **plain.metadata,
                "series": {
                    "state": k,
                    "strategy": strategy,
                    "reference_state": 0,
                    "uncorrected": True,
                    "mean_gray_residual": residual_uncorrected,
                },
            }
        result.totals.append(total)
        result.uncorrected.append(plain)
        yield Progress(label, 1, 1, f"mean gray residual {residual:.4g}")
    yield Progress("done", n - 1, n - 1, f"{n - 1} states in {time.perf_counter() - started:.1f} s")
    return result


def _compose_filled(previous: DisplacementField, increment: DisplacementField, like):
    """``previous`` followed by ``increment`` (cleaned and filled, :func:`.compose.compose`);
    where ``increment`` cannot be cleaned (no valid node), ``like``'s grid with every node lost
    (NaN, ``NOT_COMPUTED``)."""
    try:
        return compose(previous, clean(increment, fill_masked=True))
    except ValueError:
        lost = like.copy()
        lost.u[...] = np.nan
        lost.status[...] = int(Status.NOT_COMPUTED)
        return lost


def _points_series(volumes, params, strategy, mask, points):
    """:func:`series_iter` at points (see the module's docstring)."""
    points = np.asarray(points, np.float64)
    result = SeriesResult(strategy=strategy)
    n = len(volumes)
    started = time.perf_counter()
    for k in range(1, n):
        label = state_of(k, n - 1)
        state_started = time.perf_counter()
        yield Progress(label, 0, 1, f"correlating at {len(points)} points")
        if strategy == "total" or k == 1:
            total = correlate_points(volumes[0], volumes[k], points, params, mask=mask)
            if strategy == "incremental":
                result.increments.append(total.copy())
        else:
            previous = result.totals[-1]
            here = previous.valid
            if not here.any():
                raise ValueError(f"state {k}: no point is left to follow (all lost before)")
            moved = points[here] + previous.u[here]
            step = correlate_points(volumes[k - 1], volumes[k], moved, params)
            at = points.copy()
            at[here] = moved  # the lost points keep their first-state position
            result.increments.append(_at_all_points(step, at, here))
            total = _at_all_points(step, points, here)
            total.u[here] = previous.u[here] + step.u
            # the deformation gradients multiply: I + ∇U_0→k = (I + ∇u_k−1→k)(I + ∇U_0→k−1)
            g_prev, g_step = previous.gradient[here], step.gradient
            total.gradient[here] = g_prev + g_step + g_step @ g_prev
        total.metadata["series"] = {
            "state": k,
            "strategy": strategy,
            "reference_state": 0,
            "points": len(points),
            "seconds": time.perf_counter() - state_started,
        }
        result.totals.append(total)
        result.uncorrected.append(total)  # never corrected at points
        yield Progress(label, 1, 1, f"{int(total.valid.sum())} of {len(points)} points matched")
    yield Progress("done", n - 1, n - 1, f"{n - 1} states in {time.perf_counter() - started:.1f} s")
    return result


def _at_all_points(step: ScatteredField, positions, here) -> ScatteredField:
    """``step`` (measured at the points ``here`` only) at all ``positions``: NaN and
    ``NOT_COMPUTED`` at the others."""
    n = len(positions)
    u = np.full((n, 3), np.nan)
    u[here] = step.u
    zncc = np.full(n, np.nan, np.float32)
    zncc[here] = step.zncc
    status = np.full(n, int(Status.NOT_COMPUTED), np.uint8)
    status[here] = step.status
    iterations = np.zeros(n, np.int32)
    iterations[here] = step.iterations
    gradient = np.full((n, 3, 3), np.nan)
    gradient[here] = step.gradient
    provenance = np.full(n, int(Provenance.NOT_COMPUTED), np.uint8)
    provenance[here] = step.provenance
    return ScatteredField(
        points=positions,
        u=u,
        zncc=zncc,
        status=status,
        iterations=iterations,
        provenance=provenance,
        gradient=gradient,
        params=dict(step.params),
        metadata=dict(step.metadata),
    )


def _residual(volumes: SeriesVolumes, k: int, total: DisplacementField, label: str):
    """The summary's mean gray residual of ``total`` (``U_0→k``), cleaned and filled; NaN where
    the field cannot be cleaned (no valid node)."""
    try:
        filled = clean(total, fill_masked=True)
    except ValueError:
        return float("nan")
    return (
        yield from forward_progress(volumes.mean_residual(k, filled), f"{label}: gray residual")
    )


def series(volumes: Sequence[np.ndarray], params: CorrelationParams | None = None, **options):
    """Blocking form of :func:`series_iter` (same parameters, no progress)."""
    return run_to_completion(series_iter(volumes, params, **options))
