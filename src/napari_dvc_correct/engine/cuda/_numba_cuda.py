"""The one place that imports ``numba.cuda`` (built-in numba or the ``numba-cuda`` package).

``numba-cuda`` still calls ``np.row_stack``, which NumPy 2.5 removed; we restore the alias before the
import. Everything in :mod:`napari_dvc_correct.engine.cuda` imports ``cuda`` from here.
"""

from __future__ import annotations

import numpy as np

if not hasattr(np, "row_stack"):  # NumPy >= 2.5 removed the alias numba-cuda still uses
    np.row_stack = np.vstack  # noqa: NPY201 - restoring the removed alias on purpose

from numba import cuda  # noqa: E402

__all__ = ["cuda", "simulator_enabled"]


def simulator_enabled() -> bool:
    """True when numba runs CUDA kernels in its Python simulator (``NUMBA_ENABLE_CUDASIM=1``)."""
    from numba.core import config

    return bool(config.ENABLE_CUDASIM)
