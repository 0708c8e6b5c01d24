"""Device copies of the volumes, kept while the host array lives.

The engine calls the IC-GN kernel once per batch of POIs (and once per POI during the reliability
repair) with the same volume objects; copying a volume to the GPU at every call would cost more than
the matching. A device copy is therefore cached under the host array's identity and dropped when
that array is garbage collected. The engine never modifies a volume in place after building it; code
that does must call :func:`clear_device_cache`.
"""

from __future__ import annotations

import weakref

import numpy as np

from ._numba_cuda import cuda, simulator_enabled

_CACHE: dict[tuple[int, bool], object] = {}


def default_threads() -> int:
    """Threads per block: 128 on a GPU, 32 in the (slow, one Python thread per CUDA thread)
    simulator."""
    return 32 if simulator_enabled() else 128


def to_device_cached(array: np.ndarray, flat: bool = False):
    """Device copy of ``array`` (C-contiguous), reused while ``array`` is alive.

    Parameters
    ----------
    array : ndarray
        Host array; must not be modified in place afterwards (or call :func:`clear_device_cache`).
    flat : bool
        Return a 1-D view of the copy (the sampling kernels index coefficients linearly).
    """
    key = (id(array), flat)
    entry = _CACHE.get(key)
    if entry is not None:
        ref, shape, dtype, device_array = entry
        if ref() is array and shape == array.shape and dtype == array.dtype:
            return device_array
    host = np.ascontiguousarray(array)
    device_array = cuda.to_device(host.reshape(-1) if flat else host)
    try:
        ref = weakref.ref(array)
        weakref.finalize(array, _CACHE.pop, key, None)
    except TypeError:  # not weak-referenceable (a subclass or a scalar): do not cache
        return device_array
    _CACHE[key] = (ref, array.shape, array.dtype, device_array)
    return device_array


def clear_device_cache() -> None:
    """Drop every cached device copy (frees GPU memory)."""
    _CACHE.clear()
