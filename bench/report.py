"""Write one benchmark's section of docs/BENCHMARKS.md, leaving the other sections alone.

Each section's machine line ends with the commit the benchmark ran and whether the code was
that commit's: ``commit abc1234 (clean)`` or ``commit abc1234 with uncommitted code changes``.
The commit is read when this module is imported, at the benchmark's start, so edits made while
a long benchmark runs do not change what its section claims (``bench.stale`` reads it back).
"""

from __future__ import annotations

import os
import platform
import re
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
BENCHMARKS_MD = ROOT / "docs" / "BENCHMARKS.md"
HEADER = "# Benchmarks\n\nEvery section is written by the command it names; rerun it to refresh.\n"


def _git(*args: str, cwd: Path = ROOT) -> str:
    done = subprocess.run(["git", *args], capture_output=True, text=True, check=False, cwd=cwd)
    return done.stdout.strip()


def machine() -> str:
    """One line describing this machine, for every section."""
    return (
        f"{_cpu()}, {os.cpu_count()} cores, Python {platform.python_version()}, "
        f"{platform.system()} {platform.release()}" + REVISION
    )


def _cpu() -> str:
    """The CPU's name, with its family, model and widest vector extension: virtual machines
    often name only the brand ("AMD EPYC"), behind which the receiver's bench has run half as
    fast again on one day as on others."""
    try:
        info = Path("/proc/cpuinfo").read_text().split("\n\n", 1)[0]
    except OSError:
        return platform.processor() or platform.machine()
    fields = {
        k.strip(): v.strip() for k, _, v in (line.partition(":") for line in info.splitlines())
    }
    details = []
    if "cpu family" in fields:
        details.append(f"family {fields['cpu family']} model {fields.get('model', '?')}")
    flags = fields.get("flags", "").split()
    details += [v for v in ("avx512f", "avx2") if v in flags][:1]  # numba compiles for it
    name = fields.get("model name") or platform.processor() or platform.machine()
    return f"{name} ({', '.join(details)})" if details else name


def _revision() -> str:
    try:
        rev = _git("rev-parse", "--short", "HEAD")
        if not rev:
            return ""
        dirty = _git("status", "--porcelain", "--", "*.py")
    except OSError:
        return ""
    # Uncommitted code: the numbers are not that commit's.
    return f", commit {rev}" + (" with uncommitted code changes" if dirty else " (clean)")


REVISION = _revision()
"""The code this process runs: read once, at the benchmark's start."""


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
