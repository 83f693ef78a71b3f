"""Fixtures shared by several test modules."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
from fastapi import FastAPI

from server.demo import bound_url, start_server
from server.settings import Settings

ServeApp = Callable[..., tuple[str, FastAPI]]


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
