"""Which sections of docs/BENCHMARKS.md are older than the code they measure.

Each section names the commit it ran at (``bench.report``). A section is stale when a later
commit changed the code it measures (``MEASURES``), when its commit had no such benchmark yet,
when its commit is unknown here, or when it ran on uncommitted code. ``make bench`` ends with
this list; ``python -m bench.stale`` prints it alone.
"""

from __future__ import annotations

import argparse
import re
import subprocess
from dataclasses import dataclass
from pathlib import Path

from bench.report import BENCHMARKS_MD, ROOT

_PIPELINE = ("occ", "receiver/pipeline", "receiver/sim", "receiver/camera.py")
_EXPERIMENTS = (*_PIPELINE, "bench/__main__.py", "bench/experiments", "bench/framecam.py")
MEASURES: dict[str, tuple[str, ...]] = {
    "server_frames": ("bench/server_frames.py", "occ", "server"),
    "readers": ("bench/readers.py", "receiver/io", "receiver/events.py"),
    "encoder": ("bench/encoder.py", "occ"),
    "receiver": ("bench/receiver.py", *_PIPELINE),
    "sim": ("bench/sim.py", "occ", "receiver/sim", "receiver/live/virtual_camera.py"),
    "calibration": ("bench/calibration.py", "bench/experiments/streaming.py", "receiver/sim"),
    "tracking": ("bench/tracking.py", *_PIPELINE),
    "live": ("bench/live.py", *_PIPELINE, "receiver/live", "server"),
    "first_run": ("bench/first_run.py", "Makefile", "pyproject.toml", "occ", "receiver", "server"),
    "realistic": ("bench/realistic.py", *_PIPELINE),
    "scenes": ("bench/scenes", *_PIPELINE),
    "closed_loop": (
        "bench/closed_loop.py",
        "bench/loop_sim.py",
        *_PIPELINE,
        "receiver/live/link_quality.py",
    ),
    "paper_streaming": _EXPERIMENTS,
    "paper_localization": _EXPERIMENTS,
    "paper_comparison": _EXPERIMENTS,
}
"""Per section: the benchmark's own module first, then the code whose speed or output it
reports (files or folders, relative to the repository root)."""

_SECTION = re.compile(r"<!-- bench:(\w+) -->(.*?)<!-- /bench:\1 -->", re.S)
_STAMP = re.compile(r"^Machine: .*?, commit (\w+)( with uncommitted code changes)?", re.M)


@dataclass(frozen=True)
class Section:
    name: str
    commit: str | None
    """The commit its machine line names (None: it names none)."""
    dirty: bool
    """It ran on code with uncommitted changes."""


@dataclass(frozen=True)
class Staleness:
    section: Section
    reason: str | None
    """Why the section is older than its code, or None if it is current."""


def sections(text: str) -> list[Section]:
    """The sections of a BENCHMARKS.md text, in order, with the commit each was run at."""
    out = []
    for match in _SECTION.finditer(text):
        stamp = _STAMP.search(match.group(2))
        commit = stamp.group(1) if stamp else None
        out.append(Section(match.group(1), commit, bool(stamp and stamp.group(2))))
    return out


def _git(root: Path, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(["git", *args], cwd=root, capture_output=True, text=True, check=False)


def staleness(section: Section, root: Path = ROOT, head: str = "HEAD") -> Staleness:
    """Whether ``section`` still measures the code at ``head`` of the repository at ``root``."""
    paths = MEASURES.get(section.name)
    if paths is None:
        return Staleness(section, "no entry in bench.stale.MEASURES says what it measures")
    if section.commit is None:
        return Staleness(section, "its machine line names no commit")
    if _git(root, "merge-base", "--is-ancestor", section.commit, head).returncode != 0:
        return Staleness(section, f"commit {section.commit} is not in this branch's history")
    if _git(root, "cat-file", "-e", f"{section.commit}:{paths[0]}").returncode != 0:
        return Staleness(section, f"{paths[0]} did not exist yet at commit {section.commit}")
    log = _git(root, "rev-list", f"{section.commit}..{head}", "--", *paths)
    later = log.stdout.split()
    if later:
        return Staleness(
            section,
            f"{len(later)} later commit{'s' * (len(later) > 1)} changed what it measures "
            f"({', '.join(paths)})",
        )
    if section.dirty:
        return Staleness(section, f"it ran on uncommitted changes to {section.commit}")
    return Staleness(section, None)


def report(path: Path = BENCHMARKS_MD, root: Path = ROOT) -> list[Staleness]:
    return [staleness(s, root) for s in sections(path.read_text())]


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m bench.stale", description=__doc__)
    parser.add_argument("--path", type=Path, default=BENCHMARKS_MD)
    args = parser.parse_args(argv)
    found = report(args.path)
    stale = [s for s in found if s.reason]
    for s in found:
        state = f"stale: {s.reason}" if s.reason else "current"
        print(f"{s.section.name} (commit {s.section.commit}): {state}")
    print(f"{len(stale)} of {len(found)} sections are older than the code they measure.")


if __name__ == "__main__":
    main()
