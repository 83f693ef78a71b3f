"""``eventocc-receiver info FILE``: what an event file holds (streams, so any size works)."""

from __future__ import annotations

import argparse
from dataclasses import dataclass

from eventocc.receiver.commands import add_command, read_with_progress
from eventocc.receiver.io import READ_FORMATS, EventStream, read_events


@dataclass(frozen=True)
class EventFileSummary:
    format: str
    width: int | None
    height: int | None
    count: int
    t_first: int | None
    t_last: int | None
    positive: int
    max_x: int
    max_y: int

    @property
    def duration_us(self) -> int:
        return 0 if self.t_first is None else self.t_last - self.t_first

    def lines(self) -> list[str]:
        size = f"{self.width}x{self.height}" if self.width else "not in the file"
        rate = self.count / (self.duration_us / 1e6) if self.duration_us else 0.0
        share = self.positive / self.count if self.count else 0.0
        lines = [
            f"format      {self.format}",
            f"resolution  {size}"
            + (f" (events reach x={self.max_x}, y={self.max_y})" if self.count else ""),
            f"events      {self.count:,}",
        ]
        if self.count:
            lines += [
                f"time        {self.t_first} .. {self.t_last} us",
                f"duration    {self.duration_us / 1e6:.6f} s",
                f"rate        {rate / 1e6:.3f} Mev/s",
                f"polarity    {share:.1%} ON, {1 - share:.1%} OFF",
            ]
        return lines


def summarize(stream: EventStream, progress: bool = False) -> EventFileSummary:
    """Count and time range of a stream, read to its end."""
    count = positive = max_x = max_y = 0
    t_first = t_last = None
    for chunk in read_with_progress(stream, desc=stream.path.name, quiet=not progress):
        if not len(chunk):
            continue
        t_first = int(chunk["t"].min()) if t_first is None else min(t_first, int(chunk["t"].min()))
        t_last = int(chunk["t"].max()) if t_last is None else max(t_last, int(chunk["t"].max()))
        count += len(chunk)
        positive += int((chunk["p"] > 0).sum())
        max_x = max(max_x, int(chunk["x"].max()))
        max_y = max(max_y, int(chunk["y"].max()))
    return EventFileSummary(
        stream.format, stream.width, stream.height, count, t_first, t_last, positive, max_x, max_y
    )


def run(args: argparse.Namespace) -> int:
    with read_events(args.file, format=args.format) as stream:
        summary = summarize(stream, progress=not args.quiet)
    print(f"file        {args.file}")
    print("\n".join(summary.lines()))
    return 0


def add_parser(subparsers) -> None:
    p = add_command(
        subparsers,
        "info",
        help="count, duration, rate and geometry of an event file",
        doc=__doc__,
    )
    p.add_argument("file", help="event file (RAW, DAT, AEDAT4, bag, text, npz, HDF5)")
    p.add_argument("--format", choices=READ_FORMATS, help="override format detection")
    p.set_defaults(func=run)
