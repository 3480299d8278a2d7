"""The ``msk`` command line. Sub-commands live in :mod:`services.commands`, one module per concern.

``msk X`` imports only the module that registers ``X``; the other commands are listed (name and help, read from
their modules' source by :func:`services.commands.command_modules`) without importing them, so a command's start-up
does not pay for every other command's imports (scipy, numba, pinocchio).
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence

from msk_core import __version__
from msk_core.errors import MskError
from services.commands import command_modules


def _command_word(argv: Sequence[str]) -> str | None:
    """The command ``argv`` names: its first word that is not an option (``msk`` itself has only -h and --version)."""
    return next((word for word in argv if not word.startswith("-")), None)


def build_parser(argv: Sequence[str] | None = None) -> argparse.ArgumentParser:
    """The parser for ``argv``: the command it names in full, every other one listed by name and help only. With no
    ``argv``, every command in full (for callers that parse many command lines with one parser)."""
    parser = argparse.ArgumentParser(
        prog="msk",
        description="msk-live: live muscle-activation estimation for strength training.",
    )
    parser.add_argument("--version", action="version", version=f"msk-live {__version__}")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    word = None if argv is None else _command_word(argv)
    for entry in command_modules():
        if entry.commands is None or argv is None or (word is not None and entry.declares(word)):
            importlib.import_module(entry.module).register(subparsers)
            continue
        for command in entry.commands:
            subparsers.add_parser(command.name, help=command.help, aliases=command.aliases, add_help=False)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = build_parser(argv)
    args = parser.parse_args(argv)
    handler = getattr(args, "handler", None)
    if handler is None:
        parser.print_help()
        return 0
    try:
        try:
            return int(handler(args) or 0)
        except BaseException:
            from services.commands.estimate import remove_unfilled_folders

            remove_unfilled_folders()  # a report folder made for work that never came is not left behind, empty
            raise
    except MskError as error:
        print(f"msk {args.command}: error: {error}", file=sys.stderr)
        return 2
    except OSError as error:  # the file system's answer (no such folder, no permission, disk full): said, no traceback
        where = f"{error.filename}: " if error.filename else ""
        print(f"msk {args.command}: error: {where}{error.strerror or error}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"msk {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
