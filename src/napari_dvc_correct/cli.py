"""Command line: ``napari-dvc-correct SUBCOMMAND ...``, a thin layer over the engine and io.

Each subcommand lives in :mod:`napari_dvc_correct.commands` as a module with
``add_parser(subparsers)`` and ``run(args) -> int``. Bad input exits with status 2 and a one-line
reason on stderr; nothing is written when a run fails. SIGINT (Ctrl-C) and SIGTERM stop a run
the same way (status 130 and 143): temporary files are removed and earlier outputs stay as they
were (docs/faults.md). The CLI never imports napari or Qt.
"""

from __future__ import annotations

import argparse
import importlib
import signal
import sys
import threading

from .commands._common import UserError  # re-exported: bad input, exit status 2

#: Subcommand modules under napari_dvc_correct.commands, in the order ``--help`` lists them.
SUBCOMMANDS = ("correlate", "clean", "evaluate", "correct", "series")

__all__ = ["SUBCOMMANDS", "Terminated", "UserError", "build_parser", "main"]


class Terminated(KeyboardInterrupt):
    """Raised in the main thread on SIGTERM, so a run unwinds (and cleans up) as on Ctrl-C."""


def _terminate(signum, frame):
    raise Terminated()


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
    main_thread = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, _terminate) if main_thread else None
    try:
        return int(args.run(args) or 0)
    except (UserError, ValueError, FileNotFoundError, OSError) as error:
        message = " ".join(str(error).split())
        print(f"napari-dvc-correct {args.command}: error: {message}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as stop:
        name = "SIGTERM" if isinstance(stop, Terminated) else "SIGINT"
        print(
            f"napari-dvc-correct {args.command}: interrupted ({name}), nothing written, "
            "earlier outputs unchanged",
            file=sys.stderr,
        )
        return 143 if isinstance(stop, Terminated) else 130
    finally:
        if main_thread:
            signal.signal(signal.SIGTERM, previous)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
