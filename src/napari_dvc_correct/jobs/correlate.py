"""The correlation of a pair on a POI grid, or at points, in memory or out of core."""

from __future__ import annotations

from collections.abc import Generator

import numpy as np

from ..engine.correlation.params import CorrelationParams
from ..engine.fields.field import DisplacementField
from ..engine.progress import Progress
from ..engine.run_options import RunOptions


def correlate_job(
    reference,
    deformed,
    params: CorrelationParams | None = None,
    *,
    mask=None,
    grid: tuple | None = None,
    run: RunOptions | None = None,
) -> Generator[Progress, None, DisplacementField]:
    """Local DVC of ``reference`` (G) and ``deformed`` (F) on a POI grid; yields progress.

    Parameters
    ----------
    reference, deformed : ndarray or lazy volume, shape (nz, ny, nx)
        ``G`` and ``F`` (lazily read volumes, or paths, out of core).
    params : CorrelationParams, optional
        The DVC parameters (default: their defaults).
    mask : ndarray of bool or lazy volume, optional
        Reference-space material mask.
    grid : (origin, step, shape), optional
        POI grid in reference voxels (default: the whole volume's); in memory only.
    run : RunOptions, optional
        In memory (default: :func:`..engine.correlation.correlate.correlate_iter`) or out of
        core (:func:`..tiled.correlate.correlate_tiled_iter`: batch by batch, each reading only
        its region); ``run.device`` says where IC-GN runs.

    Returns
    -------
    DisplacementField

    Raises
    ------
    ValueError
        For a ``grid`` out of core (a tiled run covers the whole volume's grid).
    """
    params = CorrelationParams() if params is None else params
    run = RunOptions() if run is None else run
    if run.out_of_core:
        if grid is not None:
            raise ValueError(
                "a region or a grid origin does not apply to a run out of core yet: the tiled "
                "run covers the whole volume's grid"
            )
        from ..tiled.correlate import correlate_tiled_iter

        return (
            yield from correlate_tiled_iter(
                reference, deformed, params, mask=mask, **run.tiled_keywords()
            )
        )
    from ..engine.correlation.correlate import correlate_iter

    return (
        yield from correlate_iter(
            reference, deformed, params, mask=mask, grid=grid, device=run.device
        )
    )


def points_job(
    reference,
    deformed,
    points,
    params: CorrelationParams | None = None,
    *,
    mask=None,
    run: RunOptions | None = None,
):
    """DVC at ``points`` (N, 3) (z, y, x reference voxels, fractional allowed); yields progress.

    A guide field (every point's initial guess) is correlated first on a grid of
    ``params.step`` over the points' bounding box, with progress; then IC-GN runs at each point
    (:func:`..engine.correlation.correlate_points.correlate_points`). Out of core
    (``run.out_of_core``) the guide runs in batches and the points in groups, each reading only
    its region (:func:`..tiled.points.correlate_points_tiled_iter`). Returns the
    ``ScatteredField``.
    """
    params = CorrelationParams() if params is None else params
    run = RunOptions() if run is None else run
    points = np.asarray(points, dtype=np.float64)
    if run.out_of_core:
        from ..tiled.points import correlate_points_tiled_iter

        return (
            yield from correlate_points_tiled_iter(
                reference, deformed, points, params, mask=mask, **run.tiled_keywords()
            )
        )
    from ..engine.correlation.correlate import correlate_iter
    from ..engine.correlation.correlate_points import correlate_points, guide_grid

    grid = guide_grid(reference.shape, points, params)  # as correlate_points' own guide
    guide = yield from correlate_iter(
        reference, deformed, params, mask=mask, grid=grid, device=run.device
    )
    yield Progress("IC-GN at the points", 0, len(points), f"{len(points)} points")
    return correlate_points(
        reference, deformed, points, params, mask=mask, guide=guide, device=run.device
    )
