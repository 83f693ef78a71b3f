"""``eventocc-receiver convert IN OUT``: rewrite an event file in another format (streaming)."""

from __future__ import annotations

import argparse

from eventocc.receiver.commands import add_command, read_with_progress
from eventocc.receiver.io import READ_FORMATS, WRITE_FORMATS, read_events, write_events


def run(args: argparse.Namespace) -> int:
    with read_events(args.input, format=args.from_format) as stream:
        width = args.width or stream.width
        height = args.height or stream.height
        if not width or not height:
            raise ValueError(
                f"{args.input} does not state its sensor size; pass --width and --height"
            )
        chunks = read_with_progress(stream, desc="convert", quiet=args.quiet)
        count = write_events(args.output, chunks, format=args.to_format, width=width, height=height)
    print(f"wrote {count:,} events to {args.output}")
    return 0


def add_parser(subparsers) -> None:
    p = add_command(
        subparsers, "convert", help="convert an event file to another format", doc=__doc__
    )
    p.add_argument("input", help="event file to read")
    p.add_argument("output", help="file to write (format from --to or the extension)")
    p.add_argument(
        "--from", dest="from_format", choices=READ_FORMATS, help="input format (default: detected)"
    )
    p.add_argument(
        "--to",
        dest="to_format",
        choices=WRITE_FORMATS,
        help="output format (default: from the extension; .raw is EVT 3.0)",
    )
    p.add_argument("--width", type=int, help="sensor width, if the input does not say")
    p.add_argument("--height", type=int, help="sensor height, if the input does not say")
    p.set_defaults(func=run)
