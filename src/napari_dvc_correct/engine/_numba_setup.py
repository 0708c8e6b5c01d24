"""numba settings shared by every kernel module; import this before defining kernels.

The default ``workqueue`` threading layer aborts the process when two parallel regions overlap
(e.g. a napari worker thread and a test thread), so we ask for a thread-safe layer unless the user
chose one with ``NUMBA_THREADING_LAYER``.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import time
from pathlib import Path

import numba

if "NUMBA_THREADING_LAYER" not in os.environ:
    numba.config.THREADING_LAYER = "threadsafe"

#: Cache folders of other engine versions untouched for this long are removed (seconds).
STALE_CACHE_AGE = 14 * 24 * 3600.0


def engine_source_stamp(engine_dir: Path | None = None) -> str:
    """A hash of every engine source file (names and contents) and of numba's version.

    numba keys a cached kernel on its *own* file only, so a kernel that inlines a function from
    another module (``inline="always"``, or a callee LLVM inlined) keeps the old code when only
    that other module changes, and silently computes with it. Keying the whole cache folder on
    all engine sources makes any engine change start a fresh cache.
    """
    engine = Path(engine_dir) if engine_dir is not None else Path(__file__).parent
    digest = hashlib.sha1(numba.__version__.encode())
    for path in sorted(engine.rglob("*.py")):
        digest.update(path.relative_to(engine).as_posix().encode())
        digest.update(path.read_bytes())
    return digest.hexdigest()[:16]


def user_cache_root() -> Path:
    """Where this user's caches live: ``$XDG_CACHE_HOME``, ``%LOCALAPPDATA%`` or ``~/.cache``."""
    base = os.environ.get("XDG_CACHE_HOME") or os.environ.get("LOCALAPPDATA")
    return (Path(base) if base else Path.home() / ".cache") / "napari-dvc-correct"


def use_versioned_cache(root: Path, stamp: str) -> Path | None:
    """Point numba's cache at ``root/numba-<stamp>``; remove other stamps' stale folders.

    Returns the folder, or None where it cannot be written (numba then keeps its own places).
    """
    folder = Path(root) / f"numba-{stamp}"
    try:
        folder.mkdir(parents=True, exist_ok=True)
        probe = folder / f".probe-{os.getpid()}"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError:
        return None
    numba.config.CACHE_DIR = str(folder)
    now = time.time()
    for other in Path(root).glob("numba-*"):
        try:
            if other != folder and now - other.stat().st_mtime > STALE_CACHE_AGE:
                shutil.rmtree(other, ignore_errors=True)
        except OSError:
            pass
    return folder


if not os.environ.get("NUMBA_CACHE_DIR"):
    use_versioned_cache(user_cache_root(), engine_source_stamp())

#: Decorator options every kernel uses (see STYLE.md: nogil so the UI never freezes).
KERNEL_OPTIONS = {"nogil": True, "cache": True, "fastmath": False}

#: For the IC-GN sampling pass and the first-order reference sums only: lets LLVM fuse
#: multiply-adds and reorder the sums (measured +10% and +15% there). No "nnan"/"ninf" flags, so
#: NaN checks keep working.
FAST_KERNEL_OPTIONS = {"nogil": True, "cache": True, "fastmath": {"contract", "reassoc"}}
