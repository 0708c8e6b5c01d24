"""Atomic file writes: write to a temporary file in the target folder, then rename."""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; rename it onto ``path`` only on success.

    If the body raises, the temporary file is removed and ``path`` is left untouched, so a failed
    or cancelled write never destroys an earlier result.

    The temporary name keeps the suffix of ``path`` so libraries that pick a format from the
    extension (numpy's ``.npz``, tifffile, h5py) behave as for the final name.
    """
    path = Path(path)
    folder = path.parent if str(path.parent) else Path(".")
    if not folder.exists():
        raise FileNotFoundError(f"output folder does not exist: {folder}")
    handle, temp_name = tempfile.mkstemp(
        prefix=f".{path.stem}.", suffix=".tmp" + "".join(path.suffixes), dir=folder
    )
    os.close(handle)
    temp = Path(temp_name)
    try:
        yield temp
        os.replace(temp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            temp.unlink()
        raise
