"""``make demo``: run the server, upload a sample message, start a receiver daemon on the
virtual event camera, print where to watch it.

Ctrl-C stops everything. Each part of the demo is one step in ``main``. ``--motion`` picks the
virtual camera's motion (``static`` or ``handheld``; default: the receiver's default).
``--upload-to URL`` only uploads the sample to a server already running there and exits: the
docker compose demo, whose server and receiver run in containers of their own, does that.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
import urllib.request
from urllib.parse import quote

import uvicorn

from eventocc.server.app import UVICORN_OPTIONS, create_app
from eventocc.server.settings import Settings

SAMPLE_NAME = "hello.txt"
SAMPLE_TEXT = (
    "Hello from eventocc! This message travels from a screen to an event camera as a blinking "
    "marker, and the camera recovers both the bytes and its own 6-DoF pose.\n"
)
SAMPLE_SHA256 = hashlib.sha256(SAMPLE_TEXT.encode()).hexdigest()


def port_is_free(host: str, port: int) -> bool:
    """Whether the server could listen on ``port``: bound as uvicorn binds it, with
    ``SO_REUSEADDR``, so that a demo restarted within a minute, its last connections still in
    TIME_WAIT, gets its port back."""
    with socket.socket() as sock:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind((host, port))
        except OSError:
            return False
    return True


def start_server(settings: Settings) -> tuple[uvicorn.Server, threading.Thread]:
    """Serve in a background thread; returns once the server accepts connections."""
    server = uvicorn.Server(
        uvicorn.Config(
            create_app(settings),
            host=settings.host,
            port=settings.port,
            log_level="warning",
            **UVICORN_OPTIONS,
        )
    )
    thread = threading.Thread(target=server.run, name="eventocc-server", daemon=True)
    thread.start()
    while not server.started:
        if not thread.is_alive():
            raise SystemExit(f"the server failed to start on {settings.host}:{settings.port}")
        time.sleep(0.05)
    return server, thread


def bound_url(server: uvicorn.Server) -> str:
    host, port = server.servers[0].sockets[0].getsockname()[:2]
    return f"http://{host}:{port}"


def upload_sample(base_url: str, settings: Settings) -> dict:
    """Upload the sample message (reusing an identical earlier upload) and return its facts."""
    with urllib.request.urlopen(f"{base_url}/api/messages") as response:
        for message in json.load(response)["messages"]:
            if message["name"] == SAMPLE_NAME and message["sha256"] == SAMPLE_SHA256:
                return message
    headers = {"Content-Type": "application/json"}
    if settings.token is not None:
        headers["Authorization"] = f"Bearer {settings.token.get_secret_value()}"
    request = urllib.request.Request(
        f"{base_url}/api/messages?name={quote(SAMPLE_NAME)}",
        data=json.dumps({"text": SAMPLE_TEXT}).encode(),
        headers=headers,
        method="POST",
    )
    with urllib.request.urlopen(request) as response:
        return json.load(response)


def start_receiver(
    base_url: str, settings: Settings, message_id: str, motion: str | None = None
) -> subprocess.Popen:
    """The receiver daemon on the virtual event camera, in its own process: the server never
    imports the receiver, they meet over HTTP and websockets only. Until a transmitter page
    reports, the camera watches ``message_id``, whatever else was uploaded since."""
    env = {**os.environ, "NUMBA_NUM_THREADS": "1"}
    if settings.token is not None:
        env["EVENTOCC_TOKEN"] = settings.token.get_secret_value()
    command = [sys.executable, "-m", "eventocc.receiver.cli", "receive"]
    command += ["--source", f"sim:{message_id}"]
    command += ["--server", base_url, "--out", str(settings.data_dir / "receiver")]
    if motion is not None:
        command += ["--motion", motion]
    return subprocess.Popen(command, env=env)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        description="The eventocc demo: the server, a sample message, and a receiver daemon "
        "on the virtual event camera."
    )
    parser.add_argument(
        "--motion",
        choices=("static", "handheld"),  # the receiver's choices: the server cannot import it
        help="the virtual camera's motion (default: the receiver's default)",
    )
    parser.add_argument(
        "--upload-to",
        metavar="URL",
        help="only upload the sample message to the server at URL (with EVENTOCC_TOKEN when "
        "set) and print its id",
    )
    args = parser.parse_args(argv)
    settings = Settings()
    if args.upload_to is not None:
        message = upload_sample(args.upload_to.rstrip("/"), settings)
        print(f"sample message {message['id']} ({SAMPLE_NAME}) on {args.upload_to}", flush=True)
        return
    if settings.port and not port_is_free(settings.host, settings.port):
        settings = settings.model_copy(update={"port": 0})  # let the OS pick a free one
    server, thread = start_server(settings)
    base_url = bound_url(server)
    message = upload_sample(base_url, settings)
    # A SIGTERM (``kill``, a container stopping) stops the demo as Ctrl-C does, receiver
    # included, rather than killing it and leaving the receiver running on. SIGINT gets the
    # handler too: a shell starts background jobs with SIGINT ignored, and Python then keeps
    # ignoring it, so ``kill -INT`` would do nothing.
    for stop_signal in (signal.SIGINT, signal.SIGTERM):
        signal.signal(stop_signal, signal.default_int_handler)
    receiver = start_receiver(base_url, settings, message["id"], args.motion)
    try:
        print(f"eventocc server on {base_url}  (API docs: {base_url}/docs)")
        print(f"transmitter: {base_url}/transmitter?id={message['id']}")
        print(f"dashboard:   {base_url}/dashboard  (a receiver watches on the virtual camera)")
        print("Ctrl-C to stop.", flush=True)
        while thread.is_alive():
            thread.join(0.5)
    except KeyboardInterrupt:
        print("\nstopping")
    finally:
        stop_receiver(receiver)
        server.should_exit = True
        thread.join()


def stop_receiver(receiver: subprocess.Popen, grace_s: float = 10.0) -> None:
    """SIGTERM, then SIGKILL if it has not finished within ``grace_s`` (it may be waiting for
    its simulator's first packet, which compiles the kernels)."""
    receiver.terminate()
    try:
        receiver.wait(grace_s)
    except subprocess.TimeoutExpired:
        receiver.kill()
        receiver.wait()


if __name__ == "__main__":
    main()
