"""Volumes larger than memory, in spatial batches on Dask: above :mod:`..engine` and :mod:`..io`.

* :mod:`.correlate`: :func:`correlate_tiled` — the in-memory :func:`..engine.correlation.correlate.correlate`
  batch by batch on lazily read volumes, equal to it within the IC-GN tolerance;
* :mod:`.correction`: :func:`correct_tiled` — the engine's self-correction loop with every volume
  operation block by block (warps to temporary Zarr, tiled correcting DVC, local residuals);
* :mod:`.series`: :func:`series_tiled` — the in-memory scan series
  (:func:`..engine.series.strategies.series_iter`, on a grid) with every pair correlated, corrected and
  judged batch by batch and block by block;
* :mod:`.evaluation`: :func:`evaluate_tiled` — the in-memory accuracy evaluation block by block,
  equal to it to float32 rounding;
* :mod:`.volumes`: dense fields, warps, residuals and strain written block by block to Zarr/TIFF;
* :mod:`.memory`: halos, region sizes, the peak-memory estimate and refusal;
* :mod:`.scheduling`: dask's local threads or a ``dask.distributed`` cluster.
"""

from .correction import correct_tiled, correct_tiled_iter
from .correlate import correlate_tiled, correlate_tiled_iter
from .evaluation import evaluate_tiled, evaluate_tiled_iter
from .memory import MemoryBudgetError, choose_batch_shape, estimate_peak_memory
from .series import series_tiled, series_tiled_iter

__all__ = [
    "MemoryBudgetError",
    "choose_batch_shape",
    "correct_tiled",
    "correct_tiled_iter",
    "correlate_tiled",
    "correlate_tiled_iter",
    "estimate_peak_memory",
    "evaluate_tiled",
    "evaluate_tiled_iter",
    "series_tiled",
    "series_tiled_iter",
]
