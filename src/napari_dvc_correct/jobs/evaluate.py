"""The accuracy evaluation of fields on a pair (paper eqs. 1–3), in memory or out of core."""

from __future__ import annotations

from ..engine.evaluation.options import EvaluationOptions
from ..engine.run_options import RunOptions


def evaluate_job(
    reference,
    deformed,
    fields,
    options: EvaluationOptions | None = None,
    *,
    background_fields=None,
    region=None,
    outputs: dict | None = None,
    run: RunOptions | None = None,
):
    """Evaluate ``fields`` on ``reference`` (G) and ``deformed`` (F); yields progress and
    returns the ``Evaluation``.

    Parameters
    ----------
    reference, deformed : ndarray or lazy volume, shape (nz, ny, nx)
        ``G`` and ``F`` (lazily read volumes, or paths, out of core).
    fields : DisplacementField, dict of name -> DisplacementField, or list
        The fields to compare (finite nodes: clean them first).
    options : EvaluationOptions, optional
        Phases, residual mode, strain and bins (default: its defaults).
    background_fields, region
        As :func:`..engine.evaluation.accuracy.evaluate_iter`.
    outputs : dict, optional
        Out of core: where the volumes go as they are made (the keys of
        :func:`..tiled.evaluation.evaluate_tiled_iter`); in memory the volumes are kept in the
        result instead.
    run : RunOptions, optional
        In memory (default) or out of core (block by block, ``run.block_shape`` voxels within
        ``run.max_memory``, on ``run.workers`` threads or ``run.scheduler``'s cluster).
    """
    options = EvaluationOptions() if options is None else options
    run = RunOptions() if run is None else run
    keywords = dict(options.keywords(), background_fields=background_fields, region=region)
    if run.out_of_core:
        from ..tiled.evaluation import evaluate_tiled_iter

        return (
            yield from evaluate_tiled_iter(
                reference,
                deformed,
                fields,
                outputs=outputs,
                block_shape=run.block_shape,
                max_memory=run.max_memory,
                workers=run.workers,
                scheduler=run.scheduler,
                **keywords,
            )
        )
    from ..engine.evaluation.accuracy import evaluate_iter

    return (yield from evaluate_iter(reference, deformed, fields, keep_volumes=True, **keywords))
