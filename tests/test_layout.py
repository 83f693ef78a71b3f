"""The package's shape: one import root, and no import circles among its modules."""

from __future__ import annotations

import ast
from graphlib import CycleError, TopologicalSorter
from pathlib import Path

import pytest

import eventocc

ROOT = Path(__file__).resolve().parent.parent
FOLDERS = {"eventocc": "eventocc", "occ": "eventocc.occ", "server": "eventocc.server"}
FOLDERS |= {"receiver": "eventocc.receiver", "web": "eventocc.web"}


def package_modules() -> dict[str, Path]:
    """Every module of the package by dotted name, from the folders the package maps."""
    modules = {}
    for folder, package in FOLDERS.items():
        for path in sorted((ROOT / folder).rglob("*.py")):
            parts = path.relative_to(ROOT / folder).with_suffix("").parts
            if parts[-1] == "__init__":
                parts = parts[:-1]
            modules[".".join((package, *parts))] = path
    return modules


def imported(tree: ast.AST, known: set[str]) -> set[str]:
    """The package's modules that a module imports anywhere (top level or inside functions);
    ``from a import b`` counts as importing ``a.b`` where that is a module."""
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
            names.add(node.module)
            names.update(f"{node.module}.{alias.name}" for alias in node.names)
    return names & known


def test_every_module_is_under_the_one_root():
    modules = package_modules()
    assert "eventocc.receiver.pipeline.receiver" in modules
    for name, path in modules.items():
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.ImportFrom | ast.Import):
                targets = (
                    [node.module]
                    if isinstance(node, ast.ImportFrom)
                    else [alias.name for alias in node.names]
                )
                for target in filter(None, targets):
                    top = target.split(".")[0]
                    assert top not in ("occ", "server", "receiver", "web"), (
                        f"{name} imports {target}: use eventocc.{target}"
                    )


def test_no_import_circles():
    modules = package_modules()
    graph = TopologicalSorter()
    for name, path in modules.items():
        tree = ast.parse(path.read_text(), str(path))
        graph.add(name, *(dep for dep in imported(tree, set(modules)) if dep != name))
    try:
        graph.prepare()
    except CycleError as error:
        pytest.fail(f"import circle: {' -> '.join(error.args[1])}")


def test_version_comes_from_the_installed_metadata():
    assert eventocc.__version__ != "0+unknown"


def test_server_and_receiver_meet_only_through_the_link_format():
    modules = package_modules()
    for name, path in modules.items():
        side = name.split(".")[1] if "." in name else ""
        other = {"server": "eventocc.receiver", "receiver": "eventocc.server"}.get(side)
        if other is None:
            continue
        deps = imported(ast.parse(path.read_text(), str(path)), set(modules))
        assert not [d for d in deps if d.startswith(other)], f"{name} imports {other}"
