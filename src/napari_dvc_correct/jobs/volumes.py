"""The volumes of a job: read into memory, or opened lazily for a run out of core."""

from __future__ import annotations

from ..engine.run_options import RunOptions


def load_volume(path, run: RunOptions):
    """The volume at ``path`` as the run needs it.

    Out of core (``run.out_of_core``): opened lazily (:func:`..io.lazy.open_volume`; nothing
    is read until a region is asked for). In memory: read whole (:func:`..io.volumes.read_volume`,
    which refuses NaN and infinite values).
    """
    if run.out_of_core:
        from ..io.lazy import open_volume

        return open_volume(path)
    from ..io.volumes import read_volume

    return read_volume(path)
