"""Checks of the engine's inputs at its boundary, with messages that say what to change.

Pure numpy: :mod:`..io` readers call :func:`validate_volume` on what they read, and the engine calls
it on the arrays it is given, so a volume is checked the same way wherever it comes from.
"""

from __future__ import annotations

import numpy as np


def validate_volume(volume, name: str = "volume", check_finite: bool = True) -> np.ndarray:
    """Check that ``volume`` is a non-empty 3-D real array (finite values); return it unchanged.

    Large memory-mapped volumes are checked for NaN slab by slab so they are not loaded whole.
    """
    volume = np.asanyarray(volume)
    if volume.ndim != 3:
        raise ValueError(f"{name} must be a 3-D volume (z, y, x), got shape {volume.shape}")
    if min(volume.shape) < 1:
        raise ValueError(f"{name} is empty (shape {volume.shape})")
    if volume.dtype.kind not in "uif" and volume.dtype != np.bool_:
        raise ValueError(f"{name} must hold real numbers, got dtype {volume.dtype}")
    if check_finite and volume.dtype.kind == "f":
        slab = max(1, int(2**24 // max(1, volume.shape[1] * volume.shape[2])))
        for start in range(0, volume.shape[0], slab):
            if not np.all(np.isfinite(volume[start : start + slab])):
                raise ValueError(f"{name} contains NaN or infinite values")
    return volume
