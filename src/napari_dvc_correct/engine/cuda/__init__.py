"""GPU backend of the engine (numba.cuda): tricubic B-spline sampling and IC-GN for batches of POIs.

Importing this package imports ``numba.cuda`` (it raises when that import fails); use
:func:`napari_dvc_correct.engine.backend.select_device` to pick a device safely. The kernels run in
numba's CUDA simulator when ``NUMBA_ENABLE_CUDASIM=1`` is set before numba is imported (slow: for
tests on tiny cases only).
"""

from __future__ import annotations

from ._numba_cuda import cuda, simulator_enabled
from .icgn import FALLBACK
from .launch import match_many_cuda
from .memory import clear_device_cache
from .sampling import sample_cuda

__all__ = [
    "FALLBACK",
    "clear_device_cache",
    "cuda",
    "match_many_cuda",
    "sample_cuda",
    "simulator_enabled",
]
