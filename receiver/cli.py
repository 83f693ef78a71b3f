"""``eventocc-receiver``: one command, a subcommand per job (each in ``receiver/commands/``)."""

from __future__ import annotations

import argparse
import importlib
import logging
import sys

from eventocc.receiver.io.errors import MissingExtraError
from eventocc.receiver.live.sources import SourceError

log = logging.getLogger(__name__)

# Each module defines ``add_parser(subparsers)``, which registers its subcommand and sets
# ``func(args) -> int`` as the parser default.
COMMANDS: tuple[str, ...] = ("info", "convert", "decode", "receive", "simulate", "warmup")
USER_ERRORS = (OSError, ValueError, MissingExtraError, SourceError)
"""What a command raises for a file, an option or a source it cannot use: the domain errors
(``EventFileError``, ``CalibrationError``, ...) are ``ValueError``s, a missing or unreadable
file an ``OSError``. Each is said in one line, without a traceback (``-v`` shows it)."""
EXIT_USER_ERROR, EXIT_INTERRUPTED = 2, 130


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="eventocc-receiver",
        description="Read, convert and simulate event data; decode the eventocc marker from it.",
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in COMMANDS:
        importlib.import_module(f"eventocc.receiver.commands.{name}").add_parser(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    quiet = args.quiet and not args.verbose
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.WARNING if quiet else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    try:
        return int(args.func(args) or 0)
    except USER_ERRORS as error:
        log.debug("the traceback", exc_info=True)
        print(f"eventocc-receiver {args.command}: error: {error}", file=sys.stderr)
        return EXIT_USER_ERROR
    except KeyboardInterrupt:
        return EXIT_INTERRUPTED


if __name__ == "__main__":
    sys.exit(main())
