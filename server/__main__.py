"""``eventocc-server``: run the transmit service with uvicorn.

Options override the ``EVENTOCC_*`` environment variables.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import uvicorn
from pydantic import ValidationError

from eventocc.server.app import UVICORN_OPTIONS, create_app
from eventocc.server.settings import Settings


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="eventocc-server", description=__doc__.splitlines()[0])
    parser.add_argument("--host", help="interface to listen on (default 127.0.0.1)")
    parser.add_argument("--port", type=int, help="TCP port (default 8000; 0 picks a free one)")
    parser.add_argument("--data-dir", type=Path, help="where the SQLite database lives")
    parser.add_argument("--token", help="bearer token required for uploads and deletes")
    return parser.parse_args(argv)


def settings_from_args(args: argparse.Namespace) -> Settings:
    """``EVENTOCC_*`` settings, overridden by the options given; SystemExit with the reason
    if they are invalid."""
    overrides = {k: v for k, v in vars(args).items() if v is not None}
    try:
        return Settings(**overrides)
    except ValidationError as error:
        raise SystemExit(f"eventocc-server: bad settings: {error}") from None


def main(argv: list[str] | None = None) -> None:
    settings = settings_from_args(parse_args(argv))
    uvicorn.run(create_app(settings), host=settings.host, port=settings.port, **UVICORN_OPTIONS)


if __name__ == "__main__":
    main()
