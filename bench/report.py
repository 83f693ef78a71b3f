"""Write one benchmark's section of docs/BENCHMARKS.md, leaving the other sections alone."""

from __future__ import annotations

import os
import platform
import re
import subprocess
from pathlib import Path

BENCHMARKS_MD = Path(__file__).resolve().parent.parent / "docs" / "BENCHMARKS.md"
HEADER = "# Benchmarks\n\nEvery section is written by the command it names; rerun it to refresh.\n"


def _git(*args: str) -> str:
    done = subprocess.run(["git", *args], capture_output=True, text=True, check=False)
    return done.stdout.strip()


def machine() -> str:
    """One line describing this machine, for every section."""
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    try:
        rev = _git("rev-parse", "--short", "HEAD")
        if rev and _git("status", "--porcelain", "--", "*.py"):
            rev += " with uncommitted code changes"  # the numbers are not that commit's
    except OSError:
        rev = ""
    return (
        f"{cpu}, {os.cpu_count()} cores, Python {platform.python_version()}, "
        f"{platform.system()} {platform.release()}" + (f", commit {rev}" if rev else "")
    )


def write_section(
    name: str, title: str, command: str, body: str, path: Path = BENCHMARKS_MD
) -> None:
    """Replace (or append) the section ``name`` with ``body`` (Markdown)."""
    begin, end = f"<!-- bench:{name} -->", f"<!-- /bench:{name} -->"
    section = f"{begin}\n## {title}\n\n`{command}`  \nMachine: {machine()}\n\n{body.strip()}\n{end}"
    text = path.read_text() if path.exists() else HEADER
    pattern = re.compile(re.escape(begin) + r".*?" + re.escape(end), re.S)
    text = (
        pattern.sub(lambda _: section, text)
        if pattern.search(text)
        else f"{text.rstrip()}\n\n{section}\n"
    )
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
