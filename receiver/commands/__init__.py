"""The subcommands of ``eventocc-receiver``, one module each; what they share is here: how a
command's parser is made (a description, ``-q``, the defaults shown) and the progress bar over
an event file."""

from __future__ import annotations

import argparse
import re
from collections.abc import Iterator

import numpy as np
from tqdm import tqdm

from eventocc.receiver.io import EventStream


class HelpFormatter(argparse.RawDescriptionHelpFormatter):
    """The description as written (paragraphs kept), and each option's default where it has
    one its help does not already state."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        default = action.default
        unset = default is None or default is False or default == []
        shown = "default" in text or unset or default is argparse.SUPPRESS
        if shown or not action.option_strings:
            return text
        return f"{text} (default: %(default)s)" if text else "default: %(default)s"


def plain(text: str) -> str:
    """A docstring for a terminal: without the reST literal markup (``name`` -> name)."""
    return re.sub(r"``([^`]*)``", r"\1", text)


def add_command(
    subparsers: argparse._SubParsersAction, name: str, *, help: str, doc: str
) -> argparse.ArgumentParser:
    """The subcommand's parser: ``help`` in the list of commands, ``doc`` (the module's
    docstring) as its description, ``-q`` to keep it quiet."""
    parser = subparsers.add_parser(
        name, help=help, description=plain(doc), formatter_class=HelpFormatter
    )
    parser.add_argument(
        "-q", "--quiet", action="store_true", help="no progress bar; log warnings and errors only"
    )
    return parser


def read_with_progress(stream: EventStream, *, desc: str, quiet: bool) -> Iterator[np.ndarray]:
    """The stream's chunks, with a bar over the bytes read (none with ``quiet`` or off a
    terminal). A reader may count past the size it announced (a read-ahead buffer, a header
    it did not count): the bar stops at its total rather than warn and show a negative ETA."""
    total = stream.size or None
    with tqdm(
        total=total, unit="B", unit_scale=True, disable=quiet or None, desc=desc, leave=False
    ) as bar:
        for chunk in stream:
            done = stream.position if total is None else min(stream.position, total)
            bar.update(done - bar.n)
            yield chunk
