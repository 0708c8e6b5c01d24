"""Command line: ``napari-dvc-correct SUBCOMMAND ...``, a thin layer over the engine and io.

Each subcommand lives in :mod:`napari_dvc_correct.commands` as a module with
``add_parser(subparsers)`` and ``run(args) -> int``. Bad input exits with status 2 and a one-line
reason on stderr; nothing is written when a run fails. SIGINT (Ctrl-C) and SIGTERM stop a run
the same way (status 130 and 143): temporary files are removed and earlier outputs stay as they
were (docs/faults.md). The CLI never imports napari or Qt. numba's kernels use the cores
(``NUMBA_NUM_THREADS``); BLAS runs on one thread unless ``OPENBLAS_NUM_THREADS`` says otherwise.
"""

from __future__ import annotations

import argparse
import importlib
import os
import signal
import sys
import threading

# One BLAS thread unless the user sets OPENBLAS_NUM_THREADS: numba's kernels already use every
# core, and OpenBLAS's own threads beside them only wait for one (on a loaded 2-core machine the
# correction's least-squares trend fits of 1 000 × 9 values took 60–80 ms each instead of 0.2 ms;
# docs/performance.md). Set before anything loads numpy, which reads it once; same results.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from .commands._common import (  # noqa: E402  (re-exported: bad input (exit 2), SIGTERM as an exception)
    Terminated,
    UserError,
    _interrupt,
    _received,
    _terminate,
    check_signals,
)

#: Subcommand modules under napari_dvc_correct.commands, in the order ``--help`` lists them.
SUBCOMMANDS = ("correlate", "clean", "evaluate", "correct", "series", "export")

__all__ = ["SUBCOMMANDS", "Terminated", "UserError", "build_parser", "main"]


def _interrupted(command: str, name: str) -> str:
    from .io.atomic import committed

    written = committed()
    if written:
        return (
            f"napari-dvc-correct {command}: interrupted ({name}) after writing "
            f"{', '.join(str(p) for p in written)}: those outputs are complete"
        )
    return (
        f"napari-dvc-correct {command}: interrupted ({name}), nothing written, earlier outputs "
        "unchanged"
    )


def build_parser(commands=SUBCOMMANDS) -> argparse.ArgumentParser:
    """The command line's parser, with the subcommands ``commands`` (default: all of them)."""
    parser = argparse.ArgumentParser(
        prog="napari-dvc-correct",
        description="Digital Volume Correlation with a self-correcting displacement field.",
    )
    subparsers = parser.add_subparsers(dest="command", required=True)
    for name in commands:
        module = importlib.import_module(f"napari_dvc_correct.commands.{name}")
        module.add_parser(subparsers)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    # a named subcommand needs only its own parser (and imports): quicker start-up
    parser = build_parser((argv[0],) if argv and argv[0] in SUBCOMMANDS else SUBCOMMANDS)
    args = parser.parse_args(argv)
    from .io.atomic import reset_committed

    reset_committed()
    _received.clear()
    main_thread = threading.current_thread() is threading.main_thread()
    previous = (
        (signal.signal(signal.SIGTERM, _terminate), signal.signal(signal.SIGINT, _interrupt))
        if main_thread
        else None
    )
    try:
        status = int(args.run(args) or 0)
        check_signals()  # one swallowed on the way: the run was interrupted all the same
        return status
    except (UserError, ValueError, FileNotFoundError, OSError) as error:
        message = " ".join(str(error).split())
        print(f"napari-dvc-correct {args.command}: error: {message}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as stop:
        terminated = isinstance(stop, Terminated) or _received[-1:] == [signal.SIGTERM]
        name = "SIGTERM" if terminated else "SIGINT"
        print(_interrupted(args.command, name), file=sys.stderr, flush=True)
        return 143 if terminated else 130
    finally:
        if main_thread:
            signal.signal(signal.SIGTERM, previous[0])
            signal.signal(signal.SIGINT, previous[1])


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
