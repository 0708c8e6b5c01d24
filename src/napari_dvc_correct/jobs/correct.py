"""The self-correction of a pair's field, in memory or out of core (paper Fig. 3)."""

from __future__ import annotations

from collections.abc import Generator

from ..engine.correction.options import CleaningOptions, CorrectionOptions
from ..engine.correlation.params import CorrelationParams
from ..engine.fields.field import DisplacementField
from ..engine.progress import Progress
from ..engine.run_options import RunOptions


def correct_job(
    reference,
    deformed,
    field: DisplacementField | None,
    params: CorrelationParams | None = None,
    *,
    options: CorrectionOptions | None = None,
    cleaning: CleaningOptions | None = None,
    mask=None,
    run: RunOptions | None = None,
) -> Generator[Progress, None, DisplacementField]:
    """Self-correct ``field`` of ``reference`` (G) and ``deformed`` (F); yields progress.

    Parameters
    ----------
    reference, deformed : ndarray or lazy volume, shape (nz, ny, nx)
        ``G`` and ``F`` (lazily read volumes, or paths, out of core).
    field : DisplacementField or None
        The field to correct (None: a DVC of the pair runs first).
    params : CorrelationParams, optional
        DVC parameters (default: the field's).
    options : CorrectionOptions, optional
        How the passes run (default: its defaults).
    cleaning : CleaningOptions, optional
        The cleaning of the field and of every correction (default: its defaults; the
        correction fills masked nodes whatever ``fill_masked`` says).
    mask : ndarray of bool or lazy volume, optional
        Reference-space material mask.
    run : RunOptions, optional
        In memory (default) or out of core (:func:`..tiled.correction.correct_tiled_iter`:
        the warps and residuals block by block, every pass batch by batch, temporary volumes in
        ``run.temp_dir``).

    Returns
    -------
    DisplacementField
        The corrected field (see :func:`..engine.correction.self_correction.correct_iter`).
    """
    options = CorrectionOptions() if options is None else options
    run = RunOptions() if run is None else run
    keywords = dict(
        options.as_dict(), mask=mask, clean_options=None if cleaning is None else cleaning.as_dict()
    )
    if run.out_of_core:
        from ..tiled.correction import correct_tiled_iter

        return (
            yield from correct_tiled_iter(
                reference,
                deformed,
                field,
                params,
                temp_dir=run.temp_dir,
                **run.tiled_keywords(),
                **keywords,
            )
        )
    from ..engine.correction.self_correction import correct_iter

    return (yield from correct_iter(reference, deformed, field, params, **keywords))
