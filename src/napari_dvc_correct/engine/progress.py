"""Progress reports yielded by the engine's long-running generators."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Progress:
    """One progress report.

    Attributes
    ----------
    stage : str
        What runs now, e.g. ``"prefilter"``, ``"initial guess"``, ``"IC-GN"``, ``"correction pass 2"``.
    done, total : int
        Units of work finished and planned in this stage (POIs, chunks...).
    message : str
        A short sentence for a status bar.
    """

    stage: str
    done: int
    total: int
    message: str = ""

    @property
    def fraction(self) -> float:
        return 1.0 if self.total <= 0 else min(1.0, self.done / self.total)


def run_to_completion(generator):
    """Drive an engine generator to its end and return its result (discarding progress)."""
    while True:
        try:
            next(generator)
        except StopIteration as stop:
            return stop.value


def _relabel(progress, prefix: str):
    if not isinstance(progress, Progress):  # anything else a generator yields goes through
        return progress
    return Progress(f"{prefix}: {progress.stage}", progress.done, progress.total, progress.message)


def forward_progress(generator, prefix: str):
    """Re-yield an engine generator's progress with stages prefixed by ``prefix``; return its
    result (use as ``result = yield from forward_progress(gen, "pass 1")``)."""
    try:
        while True:
            try:
                progress = next(generator)
            except StopIteration as stop:
                return stop.value
            yield _relabel(progress, prefix)
    finally:
        generator.close()  # a cancelled caller stops the inner run too (its Dask work, its files)


def state_of(k: int, n: int) -> str:
    """The stage prefix of state ``k`` of ``n`` in a loop over a series' states (``"state 2 of
    3"``), so that every stage line of the loop says which state runs and how many there are."""
    return f"state {k} of {n}"
