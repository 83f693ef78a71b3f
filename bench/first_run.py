"""A new user's first ``make demo``: from the URLs printed to the sample verified.

Run: ``python -m bench.first_run`` (a few minutes: most of it is the install).

1. **A fresh clone.** The repository's HEAD is cloned into a temporary folder: only committed
   code, no ``.venv``, no compiled kernels, no data.
2. **The install**, as ``make demo`` does it first (``make .venv/.installed``): its own
   virtualenv, the packages from pip's cache, and ``eventocc-receiver warmup``, which compiles
   the numba kernels into the clone.
3. **The demo** (``make demo``, on a free port). Its clock starts when the three URLs are
   printed, the moment a user would open them, and stops when the dashboard's websocket
   reports the sample message received and verified against its upload.

The demo is stopped with Ctrl-C (SIGINT to its process group) and the clone removed.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import socket
import subprocess
import tempfile
import time
from contextlib import suppress
from pathlib import Path

from websockets.sync.client import connect

from bench.report import ROOT, write_section

TIMEOUT_S = 300.0
"""Longest wait for each step: past it, the run is reported as failed."""
GOAL_S = 30.0
"""URLs to the sample verified, on a first run."""


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def clone(into: Path) -> Path:
    repo = into / "eventocc"
    subprocess.run(["git", "clone", "--quiet", str(ROOT), str(repo)], check=True)
    return repo


def install(repo: Path) -> float:
    """``make .venv/.installed`` in the clone; its seconds."""
    started = time.monotonic()
    subprocess.run(
        ["make", "-C", str(repo), ".venv/.installed"],
        check=True,
        stdout=subprocess.DEVNULL,
        timeout=TIMEOUT_S * 3,
    )
    return time.monotonic() - started


def first_demo(repo: Path) -> dict:
    """``make demo`` in the clone: seconds to the URLs, and from them to the sample verified."""
    port = free_port()
    env = {**os.environ, "EVENTOCC_PORT": str(port)}
    env.pop("EVENTOCC_TOKEN", None)
    started = time.monotonic()
    demo = subprocess.Popen(
        ["make", "-C", str(repo), "demo"],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
        start_new_session=True,
    )
    try:
        sample_id = None
        for line in demo.stdout:
            if line.startswith("transmitter:"):
                sample_id = line.rsplit("id=", 1)[1].strip()
            if line.startswith("dashboard:"):
                break
        if sample_id is None:
            raise RuntimeError("the demo printed no transmitter URL")
        urls_at = time.monotonic()
        verified_at = wait_for_verified(port, sample_id)
    finally:
        with suppress(ProcessLookupError):
            os.killpg(demo.pid, signal.SIGINT)
        try:
            demo.wait(30)
        except subprocess.TimeoutExpired:
            os.killpg(demo.pid, signal.SIGKILL)
            demo.wait()
    return {
        "to_urls_s": urls_at - started,
        "urls_to_verified_s": None if verified_at is None else verified_at - urls_at,
    }


def wait_for_verified(port: int, sample_id: str) -> float | None:
    """The monotonic time the dashboard heard of the sample verified; None after TIMEOUT_S."""
    deadline = time.monotonic() + TIMEOUT_S
    with connect(f"ws://127.0.0.1:{port}/ws/dashboard") as ws:
        while time.monotonic() < deadline:
            try:
                update = json.loads(ws.recv(timeout=1.0))
            except TimeoutError:
                continue
            if update.get("type") == "reception" and update.get("message_id") == sample_id:
                return time.monotonic()
    return None


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--no-write", action="store_true", help="print, do not write the doc")
    args = parser.parse_args(argv)
    load = os.getloadavg()[0]  # the machine may be shared: say how busy it was
    with tempfile.TemporaryDirectory(prefix="eventocc-first-run-") as tmp:
        repo = clone(Path(tmp))
        install_s = install(repo)
        demo = first_demo(repo)
    verified = demo["urls_to_verified_s"]
    verdict = (
        f"**{verified:.1f} s**, within the {GOAL_S:.0f} s goal"
        if verified is not None and verified <= GOAL_S
        else f"**{verified:.1f} s**, over the {GOAL_S:.0f} s goal"
        if verified is not None
        else f"**not verified** within {TIMEOUT_S:.0f} s"
    )
    shown = "-" if verified is None else f"{verified:.1f}"
    rows = [
        ("install: venv, packages from pip's cache, kernels compiled", f"{install_s:.0f}"),
        ("`make demo` started to its URLs printed", f"{demo['to_urls_s']:.1f}"),
        ("URLs printed to the sample verified on the dashboard's websocket", shown),
    ]
    table = "\n".join(f"| {step} | {seconds} |" for step, seconds in rows)
    body = (
        "A fresh clone of HEAD, installed (`make .venv/.installed`) and started "
        "(`make demo`) as a new user would.\n\n| step | seconds |\n|---|---|\n"
        f"{table}\n\nURLs to the sample verified: {verdict}. Machine load average {load:.1f} when "
        f"it started, on {os.cpu_count()} cores."
    )
    print(body)
    if not args.no_write:
        write_section(
            "first_run", "First run: make demo on a fresh clone", "python -m bench.first_run", body
        )


if __name__ == "__main__":
    main()
