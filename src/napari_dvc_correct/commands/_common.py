"""What the subcommands share: the progress bar, driving an engine generator, output checks.

Output rules (docs/faults.md): every output path is checked before any work (suffix, folder
exists and is writable, not a folder, not one of the inputs); a single file is written
atomically (:func:`napari_dvc_correct.io.atomic.atomic_path`); a command that writes several files
writes them as one set (:func:`output_set`): all of them or none, the earlier set replaced whole.

This module imports no engine code at import time (the CLI stays quick to start).
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import signal
import sys
from collections.abc import Iterable, Iterator
from pathlib import Path


class UserError(Exception):
    """Bad input: the CLI prints the message on one line and exits with status 2."""


class Terminated(KeyboardInterrupt):
    """Raised in the main thread on SIGTERM, so a run unwinds (and cleans up) as on Ctrl-C."""


#: The signal received during the run (set by the handlers), so one swallowed by a library
#: (e.g. while numba loads its cache) still stops the run at the next step.
_received: list[int] = []


def _terminate(signum, frame):
    _received.append(signum)
    raise Terminated()


def _interrupt(signum, frame):
    _received.append(signum)
    raise KeyboardInterrupt()


def check_signals() -> None:
    """Raise again a signal that arrived and was swallowed (called at every progress step)."""
    if _received:
        raise Terminated() if _received[-1] == signal.SIGTERM else KeyboardInterrupt()


class ProgressBar:
    """A one-line progress bar on stderr (silent when ``quiet`` or stderr is not a terminal)."""

    def __init__(self, quiet: bool = False):
        self.enabled = not quiet
        self.tty = sys.stderr.isatty()
        self.last_stage = None

    def update(self, progress) -> None:
        if not self.enabled:
            return
        width = 30
        filled = int(round(width * progress.fraction))
        line = f"{progress.stage:>14} [{'#' * filled}{'.' * (width - filled)}] {progress.message}"
        if self.tty:
            sys.stderr.write("\r" + line[:100].ljust(100))
            if progress.stage == "done":
                sys.stderr.write("\n")
        elif progress.stage != self.last_stage or progress.fraction >= 1.0:
            sys.stderr.write(line + "\n")
        sys.stderr.flush()
        self.last_stage = progress.stage


def warn(args, note: str | None) -> None:
    """Print ``note`` as one warning line on stderr (``napari-dvc-correct CMD: warning: ...``)."""
    if note:
        command = getattr(args, "command", None) or "napari-dvc-correct"
        print(f"napari-dvc-correct {command}: warning: {note}", file=sys.stderr, flush=True)


def drive(generator, bar: ProgressBar):
    """Run an engine generator, feeding its progress to ``bar``; return its result."""
    while True:
        check_signals()  # a signal a library swallowed (numba loading its cache) stops here
        try:
            bar.update(next(generator))
        except StopIteration as stop:
            return stop.value


def _same_file(a: Path, b: Path) -> bool:
    try:
        if a.exists() and b.exists():
            return os.path.samefile(a, b)
    except OSError:
        pass
    return os.path.abspath(a) == os.path.abspath(b)


def _inside(path: Path, folder: Path) -> bool:
    try:
        Path(os.path.realpath(path)).relative_to(os.path.realpath(folder))
    except ValueError:
        return False
    return True


def _check_folder_writable(folder: Path, option: str) -> None:
    if not folder.exists():
        raise FileNotFoundError(f"{option}: output folder does not exist: {folder}")
    if not folder.is_dir():
        raise ValueError(f"{option}: {folder} is not a folder")
    from ..io.atomic import check_writable

    try:
        check_writable(folder)
    except PermissionError as error:
        raise PermissionError(f"{option}: {error}") from None


def check_output_path(
    path: str, suffixes=(".npz",), inputs: Iterable[str | None] = (), option: str = "--out"
) -> Path:
    """Refuse an output before any work: wrong suffix, missing or unwritable folder, a folder,
    or one of ``inputs``. ``suffixes=None`` leaves the suffix to the caller (``--out-format``)."""
    out = Path(path)
    if out.is_dir():
        raise ValueError(f"{option} {out} is a folder: give a file name")
    if suffixes is not None and out.suffix.lower() not in suffixes:
        raise ValueError(f"{option} {out} must end with {' or '.join(suffixes)}")
    folder = out.parent if str(out.parent) else Path(".")
    _check_folder_writable(folder, option)
    for item in inputs:
        if item and _same_file(out, Path(item)):
            raise ValueError(f"{option} {out} is also an input: choose another output file")
    return out


#: Options (argparse ``dest``) that name files a command reads: every output is checked against
#: all of them (a points list and a mask are inputs as much as the volumes).
INPUT_OPTIONS = ("reference", "deformed", "volumes", "field", "compare", "mask", "points")


def command_inputs(args) -> list[str]:
    """Every input file named in ``args`` (volumes, fields, masks, points), in option order; a
    volume named as one array of an ``.npz`` (``rock.npz:reference``) is its file ``rock.npz``."""
    from ..io.volumes import split_member

    paths = []
    for name in INPUT_OPTIONS:
        value = getattr(args, name, None)
        if value is None:
            continue
        for item in value if isinstance(value, (list, tuple)) else [value]:
            paths.append(str(split_member(str(item))[0]))
    return paths


def check_side_file(side: Path, inputs: Iterable[str | None], out: Path) -> Path:
    """Refuse before any work a side file of ``out`` (``OUT_points.csv``, ``OUT_grid.npz``) that
    is a folder or one of ``inputs``: it is written next to ``out`` when the field is on points."""
    if side.is_dir():
        raise ValueError(
            f"--out {out} would write its side file {side}, which is a folder: choose another --out"
        )
    for item in inputs:
        if item and _same_file(side, Path(item)):
            raise ValueError(
                f"--out {out} would write its side file {side}, which is the input {item}: "
                "choose another --out"
            )
    return side


def check_output_dir(
    path: str, inputs: Iterable[str | None] = (), patterns: Iterable[str] = (), option="--out-dir"
) -> Path:
    """Refuse an output folder before any work (see :func:`output_set` for what it replaces)."""
    from ..io.atomic import check_set_target

    out = Path(path)
    folder = out.parent if str(out.parent) else Path(".")
    _check_folder_writable(folder, option)
    if out.is_dir():  # replaced whole: the folder itself must take changes too
        _check_folder_writable(out, option)
    for item in inputs:
        if item and (_same_file(out, Path(item)) or _inside(Path(item), out)):
            raise ValueError(
                f"{option} {out} holds the input {item}: the folder is replaced as a whole, "
                "choose another one"
            )
    try:
        check_set_target(out, patterns)
    except ValueError as error:
        raise ValueError(f"{option} {error}") from None
    return out


@contextlib.contextmanager
def output_set(out_dir: Path, patterns: Iterable[str] = (), manifest: dict | None = None
               ) -> Iterator[Path]:  # fmt: skip
    """Write a command's files as one set: yields a temporary folder that replaces ``out_dir``."""
    from ..io.atomic import atomic_dir

    with atomic_dir(out_dir, patterns=patterns, manifest=manifest) as temp:
        yield temp


def check_search(params, volume_shape) -> None:
    """Refuse before any work a ``--search`` radius larger than the volume or than the memory
    (:func:`..engine.pair_checks.check_search_radius`)."""
    from ..engine.pair_checks import check_search_radius
    from ..io.sizes import available_memory

    try:
        check_search_radius(params, volume_shape, available_memory())
    except ValueError as error:
        raise ValueError(f"--search {params.effective_search_radius}: {error}") from None


# --- defaults read from the engine's records (never retyped in the CLI) ------------------------
def correlation_defaults() -> dict:
    """Field name -> default of :class:`~napari_dvc_correct.engine.correlation.params.CorrelationParams`."""
    from ..engine.correlation.params import CorrelationParams

    return {
        f.name: f.default
        for f in dataclasses.fields(CorrelationParams)
        if f.default is not dataclasses.MISSING
    }


def correction_defaults() -> dict:
    """Defaults of the self-correction and of the cleaning (frame, update, passes, threshold,
    smoothing...), from :mod:`..engine.correction.options`, which loads neither numba nor scipy."""
    from ..engine.correction.options import defaults

    return defaults()
