"""The one import of numba.cuda: it works on NumPy without ``row_stack`` and says if simulated."""

import os

import numpy as np

from napari_dvc_correct.engine.cuda import _numba_cuda


def test_numba_cuda_imports_and_the_alias_it_needs_is_there():
    assert _numba_cuda.cuda is not None and hasattr(_numba_cuda.cuda, "jit")
    assert np.vstack([[1], [2]]).shape == (2, 1)


def test_the_simulator_is_on_only_when_asked_for():
    # the tests that use the simulator run it in a subprocess (tests/engine/cuda/_simulate.py)
    asked = os.environ.get("NUMBA_ENABLE_CUDASIM") == "1"
    assert _numba_cuda.simulator_enabled() is asked
