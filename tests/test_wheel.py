"""The wheel: one import root, and a server that serves its pages from wherever it is installed."""

from __future__ import annotations

import os
import re
import shutil
import socket
import subprocess
import sys
import sysconfig
import time
import urllib.request
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PACKAGE_FOLDERS = ("eventocc", "occ", "server", "receiver", "web")


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    """Built from a copy of the checkout's sources: an in-tree build would reuse a stale
    ``build/`` left by an earlier one."""
    source, out = tmp_path_factory.mktemp("source"), tmp_path_factory.mktemp("wheel")
    for name in ("pyproject.toml", "README.md", "LICENSE"):
        shutil.copy(ROOT / name, source)
    for folder in PACKAGE_FOLDERS:
        shutil.copytree(
            ROOT / folder, source / folder, ignore=shutil.ignore_patterns("__pycache__")
        )
    subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(out), str(source)],
        check=True,
    )
    (built,) = out.glob("eventocc-*.whl")
    return built


def test_the_wheel_holds_only_the_package(wheel):
    names = zipfile.ZipFile(wheel).namelist()
    tops = {name.split("/")[0] for name in names}
    assert {t for t in tops if not t.endswith(".dist-info")} == {"eventocc"}
    pages = ("transmitter.html", "transmitter.js", "dashboard.html", "dashboard.js", "favicon.svg")
    for page in pages:
        assert f"eventocc/web/{page}" in names
    sources = {
        f"eventocc/{path.relative_to(ROOT).as_posix()}"
        for folder in PACKAGE_FOLDERS[1:]
        for path in (ROOT / folder).rglob("*.py")
    }
    assert sources <= set(names), "modules missing from the wheel (pyproject's packages list)"


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def test_an_installed_wheel_serves_the_pages_outside_the_checkout(wheel, tmp_path):
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True)
    python = venv / "bin" / "python"
    # The dependencies come from this environment's site-packages (a plain path: its .pth
    # files, such as an editable install of this checkout, are not run); the package itself
    # only from the wheel.
    site = Path(subprocess.check_output(
        [python, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"], text=True
    ).strip())  # fmt: skip
    (site / "deps.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    subprocess.run(
        [sys.executable, "-m", "pip", "--python", str(python), "install", "-q", "--no-deps",
         "--no-index", str(wheel)],
        check=True,
    )  # fmt: skip
    found = subprocess.check_output(
        [python, "-c", "import eventocc.server; print(eventocc.server.__file__)"],
        cwd=tmp_path, text=True,
    )  # fmt: skip
    assert Path(found.strip()).is_relative_to(site)

    port = free_port()
    env = {k: v for k, v in os.environ.items() if not k.startswith("EVENTOCC_")}
    server = subprocess.Popen(
        [venv / "bin" / "eventocc-server", "--port", str(port), "--data-dir", tmp_path / "data"],
        cwd=tmp_path, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
    )  # fmt: skip
    try:
        pages = {}
        deadline = time.monotonic() + 60
        for page in ("transmitter", "dashboard", "static/dashboard.js"):
            while True:
                try:
                    with urllib.request.urlopen(f"http://127.0.0.1:{port}/{page}") as response:
                        pages[page] = response.read().decode()
                    break
                except OSError:
                    assert server.poll() is None, server.stderr.read().decode()
                    assert time.monotonic() < deadline, "the server did not come up"
                    time.sleep(0.2)
        assert re.search(r"<title>[^<]*transmitter", pages["transmitter"], re.I)
        assert re.search(r"<title>[^<]*dashboard", pages["dashboard"], re.I)
        assert "WebSocket" in pages["static/dashboard.js"]
    finally:
        server.terminate()
        server.wait(timeout=10)
