"""Command line: ``napari-dvc-correct SUBCOMMAND ...``, a thin layer over the engine and io.

Each subcommand lives in :mod:`napari_dvc_correct.commands` as a module with
``add_parser(subparsers)`` and ``run(args) -> int``. Bad input exits with status 2 and a one-line
reason on stderr; nothing is written when a run fails. The CLI never imports napari or Qt.
"""

from __future__ import annotations

import argparse
import importlib
import sys

#: Subcommand modules under napari_dvc_correct.commands, in the order ``--help`` lists them.
SUBCOMMANDS = ("correlate", "evaluate", "correct", "series")


class UserError(Exception):
    """Bad input: the CLI prints the message on one line and exits with status 2."""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="napari-dvc-correct",
        description="Digital Volume Correlation with a self-correcting displacement field.",
    )
    subparsers = parser.add_subparsers(dest="command", required=True)
    for name in SUBCOMMANDS:
        module = importlib.import_module(f"napari_dvc_correct.commands.{name}")
        module.add_parser(subparsers)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.run(args) or 0)
    except (UserError, ValueError, FileNotFoundError, OSError) as error:
        message = " ".join(str(error).split())
        print(f"napari-dvc-correct {args.command}: error: {message}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"napari-dvc-correct {args.command}: interrupted, nothing written", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
