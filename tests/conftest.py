"""Fixtures shared by several test modules."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
from fastapi import FastAPI

from eventocc.server.demo import bound_url, start_server
from eventocc.server.settings import Settings

ServeApp = Callable[..., tuple[str, FastAPI]]

CHROMIUM = Path("/usr/bin/chromium")  # Debian's package, installed by `make system-deps`
CHROMIUM_ARGS = [
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
]
ARTIFACTS = Path(__file__).resolve().parent.parent / "test-artifacts"
"""Screenshots the browser tests leave behind for a person to look at (git-ignored)."""


class FakeWall:
    """A wall clock that only sleeps and simulated work move on."""

    def __init__(self) -> None:
        self.now = 100.0

    def clock(self) -> float:
        return self.now

    def sleep(self, seconds: float) -> None:
        self.now += seconds


@pytest.fixture
def wall() -> FakeWall:
    return FakeWall()


@pytest.fixture
def artifacts() -> Path:
    ARTIFACTS.mkdir(exist_ok=True)
    return ARTIFACTS


@pytest.fixture
def browser():
    """Headless Chromium driven by Playwright. A missing browser fails the test: the page
    tests are part of the suite, not an optional extra."""
    assert CHROMIUM.exists(), f"{CHROMIUM} is missing: install it with `make system-deps`"
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        chromium = p.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)
        try:
            yield chromium
        finally:
            chromium.close()


@pytest.fixture
def serve_app(tmp_path: Path) -> Iterator[ServeApp]:
    """``serve_app(**settings) -> (base_url, app)``: a real uvicorn server in a thread on a free
    port (data in ``tmp_path`` unless given); every server started is stopped at teardown."""
    started = []

    def serve(**options) -> tuple[str, FastAPI]:
        settings = Settings(**{"data_dir": tmp_path / "data", "port": 0, **options})
        server, thread = start_server(settings)
        started.append((server, thread))
        return bound_url(server), server.config.app

    yield serve
    for server, thread in started:
        server.should_exit = True
        thread.join(10)


@pytest.fixture(scope="session")
def screen_recording(tmp_path_factory) -> Path:
    """``tests.screen.write_screen_recording``'s recording, made once per test run."""
    from tests.screen import write_screen_recording

    return write_screen_recording(tmp_path_factory.mktemp("screen"))
