"""numba settings shared by every kernel module; import this before defining kernels.

The default ``workqueue`` threading layer aborts the process when two parallel regions overlap
(e.g. a napari worker thread and a test thread), so we ask for a thread-safe layer unless the user
chose one with ``NUMBA_THREADING_LAYER``.
"""

from __future__ import annotations

import os

import numba

if "NUMBA_THREADING_LAYER" not in os.environ:
    numba.config.THREADING_LAYER = "threadsafe"

#: Decorator options every kernel uses (see STYLE.md: nogil so the UI never freezes).
KERNEL_OPTIONS = {"nogil": True, "cache": True, "fastmath": False}

#: For the IC-GN sampling pass and the first-order reference sums only: lets LLVM fuse
#: multiply-adds and reorder the sums (measured +10% and +15% there). No "nnan"/"ninf" flags, so
#: NaN checks keep working.
FAST_KERNEL_OPTIONS = {"nogil": True, "cache": True, "fastmath": {"contract", "reassoc"}}
