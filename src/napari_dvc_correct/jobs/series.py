"""A scan series (every state against the first, or state by state), in memory or out of core."""

from __future__ import annotations

from collections.abc import Sequence

from ..engine.correlation.params import CorrelationParams
from ..engine.run_options import RunOptions


def series_job(
    volumes: Sequence,
    params: CorrelationParams | None = None,
    *,
    strategy: str = "incremental",
    correct_increments: bool = False,
    correct_total: bool = False,
    correction_options: dict | None = None,
    mask=None,
    grid: tuple | None = None,
    points=None,
    run: RunOptions | None = None,
):
    """Displacement fields of a scan series; yields progress, returns the ``SeriesResult``.

    Parameters
    ----------
    volumes : sequence of ndarray or lazy volumes, each shape (nz, ny, nx)
        The states in order (lazily read volumes, or paths, out of core).
    params, strategy, correct_increments, correct_total, correction_options, mask, grid, points
        As :func:`..engine.series.strategies.series_iter` (``points``: in memory only).
    run : RunOptions, optional
        In memory (default) or out of core (:func:`..tiled.series.series_tiled_iter`: every
        pair batch by batch, every correction and residual block by block, temporary volumes
        in ``run.temp_dir``).

    Raises
    ------
    ValueError
        For ``points`` out of core.
    """
    run = RunOptions() if run is None else run
    keywords = dict(
        strategy=strategy,
        correct_increments=correct_increments,
        correct_total=correct_total,
        correction_options=correction_options,
        mask=mask,
        grid=grid,
    )
    if run.out_of_core:
        if points is not None:
            raise ValueError("a series at points runs in memory only: use a grid out of core")
        from ..tiled.series import series_tiled_iter

        return (
            yield from series_tiled_iter(
                volumes, params, temp_dir=run.temp_dir, **run.tiled_keywords(), **keywords
            )
        )
    from ..engine.series.strategies import series_iter

    return (yield from series_iter(volumes, params, points=points, **keywords))
