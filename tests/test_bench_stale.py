"""``bench.stale``: which benchmark sections are older than the code they measure."""

from __future__ import annotations

import subprocess
from pathlib import Path

from bench.report import BENCHMARKS_MD
from bench.stale import MEASURES, Section, sections, staleness


def _git(root: Path, *args: str) -> str:
    done = subprocess.run(
        ["git", "-c", "user.name=t", "-c", "user.email=t@example.org", *args],
        cwd=root,
        capture_output=True,
        text=True,
        check=True,
    )
    return done.stdout.strip()


def _commit(root: Path, files: dict[str, str]) -> str:
    for name, text in files.items():
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        (root / name).write_text(text)
    _git(root, "add", "-A")
    _git(root, "commit", "-qm", "change")
    return _git(root, "rev-parse", "--short", "HEAD")


def test_sections_read_their_commit_and_whether_the_tree_was_clean():
    text = (
        "<!-- bench:encoder -->\n## E\n\n`cmd`  \nMachine: CPU, 2 cores, commit abc1234 (clean)"
        "\n\nbody\n<!-- /bench:encoder -->\n\n<!-- bench:sim -->\n## S\n\nMachine: CPU, "
        "commit def5678 with uncommitted code changes\n<!-- /bench:sim -->\n"
        "<!-- bench:readers -->\nMachine: CPU\n<!-- /bench:readers -->"
    )
    assert sections(text) == [
        Section("encoder", "abc1234", False),
        Section("sim", "def5678", True),
        Section("readers", None, False),
    ]


def test_a_section_goes_stale_when_its_code_changes(tmp_path):
    _git(tmp_path, "init", "-q")
    before = _commit(tmp_path, {"occ/a.py": "x = 1\n"})
    ran = _commit(tmp_path, {"bench/encoder.py": "run = 1\n"})
    assert "did not exist yet" in staleness(Section("encoder", before, False), tmp_path).reason
    assert staleness(Section("encoder", ran, False), tmp_path).reason is None
    assert "uncommitted" in staleness(Section("encoder", ran, True), tmp_path).reason
    _commit(tmp_path, {"docs/notes.md": "text\n", "receiver/io/r.py": "y = 1\n"})
    assert staleness(Section("encoder", ran, False), tmp_path).reason is None  # not its code
    _commit(tmp_path, {"occ/a.py": "x = 2\n"})
    assert "1 later commit changed" in staleness(Section("encoder", ran, False), tmp_path).reason
    assert "not in this branch" in staleness(Section("encoder", "0" * 7, False), tmp_path).reason
    assert "no entry" in staleness(Section("nobody", ran, False), tmp_path).reason


def test_every_section_says_what_it_measures():
    names = [s.name for s in sections(BENCHMARKS_MD.read_text())]
    assert names and set(names) <= set(MEASURES)
    for paths in MEASURES.values():
        assert all((BENCHMARKS_MD.parent.parent / p).exists() for p in paths), paths
