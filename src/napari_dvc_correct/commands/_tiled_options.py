"""Command-line options for volumes too large for memory (``--tiled`` and friends).

The correlate, correct and series commands wire these in::

    from ._tiled_options import add_tiled_arguments, run_options_from_args

    add_tiled_arguments(parser)             # in add_parser
    ...
    run = run_options_from_args(args)       # in run: a RunOptions for the job (..jobs), which
                                            # goes out of core when run.out_of_core

This module imports no engine code at import time (the CLI stays quick to start).
"""

from __future__ import annotations

import argparse
import sys


def _checked(option: str, **values):
    """``values`` checked by :class:`..engine.run_options.RunOptions` (its checks, not a copy)."""
    from ..engine.run_options import RunOptions

    try:
        return getattr(RunOptions(**values), next(iter(values)))
    except ValueError as error:
        raise argparse.ArgumentTypeError(f"{option}: {error}") from None


def _shape_text(text: str, what: str) -> tuple[int, ...]:
    try:
        values = [int(v) for v in text.replace("x", ",").split(",") if v.strip()]
    except ValueError as error:
        raise argparse.ArgumentTypeError(
            f"{text!r} is not a {what} shape: give N or NZ,NY,NX"
        ) from error
    return tuple(values * 3 if len(values) == 1 else values)


def _batch(text: str) -> tuple[int, int, int]:
    return _checked("--batch", batch_shape=_shape_text(text, "batch"))


def _memory(text: str) -> int:
    from dask.utils import parse_bytes

    try:
        value = parse_bytes(text)
    except (ValueError, KeyError, OverflowError) as error:  # 1e400GB: inf
        raise argparse.ArgumentTypeError(
            f"{text!r} is not a memory size: use e.g. 2GB, 1.5GiB or 512MB"
        ) from error
    return _checked("--max-memory", max_memory=value)


def _existing_folder(text: str) -> str:
    """``--temp-dir``: an existing folder (a missing one is not made, with its parents)."""
    return _checked("--temp-dir", temp_dir=text)


def _positive(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
    return _checked("--workers", workers=value)


def add_tiled_arguments(parser: argparse.ArgumentParser) -> None:
    """Add ``--tiled``, ``--scheduler``, ``--max-memory``, ``--batch``, ``--workers`` and
    ``--temp-dir``."""
    group = parser.add_argument_group(
        "large volumes",
        "Correlate batch by batch, reading only each batch's region of the volumes (TIFF, Zarr, "
        "OME-Zarr, .npy, folders of TIFF slices). Any of these options turns it on.",
    )
    group.add_argument(
        "--tiled",
        action="store_true",
        help="correlate in spatial batches from lazily read volumes, on dask's local threads",
    )
    group.add_argument(
        "--scheduler",
        metavar="ADDRESS",
        help="send the batches to a dask.distributed scheduler (e.g. tcp://10.0.0.5:8786)",
    )
    group.add_argument(
        "--max-memory",
        metavar="SIZE",
        type=_memory,
        help="peak memory the run may use (e.g. 2GB); picks the batch size. The estimated peak "
        "is printed before the run, which is refused if it exceeds this or the machine",
    )
    group.add_argument(
        "--batch",
        metavar="N|NZ,NY,NX",
        type=_batch,
        help="POIs per batch (default: the largest that fits the memory)",
    )
    group.add_argument(
        "--workers",
        metavar="N",
        type=_positive,
        help="batches correlated at once on this machine (default: up to 4)",
    )
    group.add_argument(
        "--temp-dir",
        metavar="FOLDER",
        type=_existing_folder,
        help="where a tiled self-correction (or series) writes its temporary warped volumes "
        "(default: the system's temporary folder; on a cluster of several machines, a folder "
        "every worker sees at the same path; it must exist). They are removed at the end, and "
        "those of runs that were killed by the next run",
    )


def run_options_from_args(args: argparse.Namespace):
    """The :class:`..engine.run_options.RunOptions` of a command's arguments."""
    from ..engine.run_options import RunOptions

    return RunOptions(
        tiled=bool(getattr(args, "tiled", False)),
        # a command without --device (correct, series) runs its tiled batches on the CPU
        device=getattr(args, "device", "cpu"),
        max_memory=getattr(args, "max_memory", None),
        workers=getattr(args, "workers", None),
        scheduler=getattr(args, "scheduler", None) or None,
        batch_shape=getattr(args, "batch", None),
        block_shape=getattr(args, "block", None),
        temp_dir=getattr(args, "temp_dir", None),
    )


def wants_tiled(args: argparse.Namespace) -> bool:
    """True when any of the large-volume options was given (``--block`` aside)."""
    return run_options_from_args(args).replace(block_shape=None).out_of_core


def _plan_reporter(args: argparse.Namespace, progress, label: str):
    """A reporter that prints the plan's memory estimate to stderr (``label: ...``, unless
    ``args.quiet``) and forwards every report to ``progress`` (default: the command's progress
    bar)."""
    from ._common import ProgressBar

    quiet = bool(getattr(args, "quiet", False))
    if progress is None:
        progress = ProgressBar(quiet).update

    class _Reporter:
        @staticmethod
        def update(report):
            if report.stage == "plan" and not quiet:
                print(f"{label}: {report.message}", file=sys.stderr, flush=True)
            progress(report)

    return _Reporter()


def _run_options(args: argparse.Namespace) -> dict:
    """The keyword arguments every tiled run takes from the options of :func:`add_tiled_arguments`."""
    return run_options_from_args(args).tiled_keywords()


def _lazy_inputs_and_reporter(args: argparse.Namespace, progress, label: str):
    """``(reference, deformed, reporter, common)`` of a tiled command (``common`` holds the mask).

    The volumes (and ``args.mask``) opened lazily; the reporter of :func:`_plan_reporter`; the
    keyword arguments every tiled run takes from the options of :func:`add_tiled_arguments`.
    """
    from ..io.lazy import open_volume

    reference = open_volume(args.reference)
    deformed = open_volume(args.deformed)
    mask = open_volume(args.mask) if getattr(args, "mask", None) else None
    common = dict(mask=mask, **_run_options(args))
    return reference, deformed, _plan_reporter(args, progress, label), common


def run_tiled(args: argparse.Namespace, params, progress=None):
    """Correlate ``args.reference`` with ``args.deformed`` by batches; return the field.

    Reads ``args.reference``, ``args.deformed``, ``args.mask`` (optional) lazily and prints the
    estimated peak memory to stderr before the work starts (unless ``args.quiet``).

    Parameters
    ----------
    args : argparse.Namespace
        Parsed options, with those of :func:`add_tiled_arguments`.
    params : CorrelationParams
    progress : callable, optional
        Called with every :class:`Progress` (default: the command's progress bar).
    """
    from ..jobs.correlate import correlate_job
    from ._common import drive

    run = run_options_from_args(args).replace(tiled=True)
    reference, deformed, reporter, common = _lazy_inputs_and_reporter(args, progress, "tiled")
    field = drive(
        correlate_job(reference, deformed, params, mask=common["mask"], run=run), reporter
    )
    field.metadata["reference"] = str(args.reference)
    field.metadata["deformed"] = str(args.deformed)
    return field


def _block(text: str) -> tuple[int, int, int]:
    return _checked("--block", block_shape=_shape_text(text, "block"))


def add_tiled_evaluation_arguments(parser: argparse.ArgumentParser) -> None:
    """``--tiled``, ``--scheduler``, ``--max-memory``, ``--block`` and ``--workers`` for ``evaluate``."""
    group = parser.add_argument_group(
        "large volumes",
        "Evaluate block by block, reading only each block's region of the volumes (TIFF, Zarr, "
        "OME-Zarr, .npy, folders of TIFF slices); the numbers of the in-memory run (to float32 "
        "rounding). Any of these options turns it on.",
    )
    group.add_argument(
        "--tiled",
        action="store_true",
        help="evaluate in blocks from lazily read volumes, on dask's local threads",
    )
    group.add_argument(
        "--scheduler",
        metavar="ADDRESS",
        help="send the blocks to a dask.distributed scheduler (e.g. tcp://10.0.0.5:8786)",
    )
    group.add_argument(
        "--max-memory",
        metavar="SIZE",
        type=_memory,
        help="peak memory the run may use (e.g. 2GB); picks the block size. The estimated peak "
        "is printed before the run, which is refused if it exceeds this or the machine",
    )
    group.add_argument(
        "--block",
        metavar="N|NZ,NY,NX",
        type=_block,
        help="voxels per block (default: the largest cube up to 128 that fits the memory)",
    )
    group.add_argument(
        "--workers", metavar="N", type=_positive, help="blocks evaluated at once (default: up to 4)"
    )


def wants_tiled_evaluation(args: argparse.Namespace) -> bool:
    """True when any of :func:`add_tiled_evaluation_arguments`' options was given."""
    return run_options_from_args(args).out_of_core
