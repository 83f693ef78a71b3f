"""``eventocc-server``: run the transmit service with uvicorn.

Options override the ``EVENTOCC_*`` environment variables.
"""

from __future__ import annotations

import argparse
import logging
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


LOG_HANDLER = logging.StreamHandler()
LOG_HANDLER.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))


def log_to_stderr() -> None:
    """The service's own INFO lines (receivers connecting, messages received and whether they
    were verified) beside uvicorn's: uvicorn sets up its loggers only, which left them unseen,
    in ``docker compose logs`` too."""
    logger = logging.getLogger("eventocc")
    if LOG_HANDLER not in logger.handlers:
        logger.addHandler(LOG_HANDLER)
    logger.setLevel(logging.INFO)


def main(argv: list[str] | None = None) -> None:
    settings = settings_from_args(parse_args(argv))
    log_to_stderr()
    uvicorn.run(create_app(settings), host=settings.host, port=settings.port, **UVICORN_OPTIONS)


if __name__ == "__main__":
    main()
