"""The deployment files: the compose file checked in every run; the images built and the compose
file run for real where a Docker engine is available (``pytest -m docker``; minutes)."""

from __future__ import annotations

import copy
import json
import os
import shutil
import socket
import subprocess
import time
import urllib.request
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parent.parent
COMPOSE = ROOT / "docker" / "docker-compose.yml"
DOCKERFILE = ROOT / "docker" / "Dockerfile"
BASE_IMAGE = os.environ.get("EVENTOCC_TEST_BASE_IMAGE", "eventocc-base:bookworm")
"""Base for the test build: made without a registry by the shared docker-engine helper."""


def compose_command() -> list[str] | None:
    if shutil.which("docker-compose"):
        return ["docker-compose"]
    if shutil.which("docker"):
        probe = subprocess.run(["docker", "compose", "version"], capture_output=True, check=False)
        if probe.returncode == 0:
            return ["docker", "compose"]
    return None


@pytest.fixture(scope="module")
def compose() -> dict:
    return yaml.safe_load(COMPOSE.read_text())


def test_compose_runs_a_server_and_a_receiver_on_the_virtual_camera(compose: dict) -> None:
    services = compose["services"]
    assert set(services) == {"server", "receiver"}
    receiver = services["receiver"]
    assert receiver["command"][:4] == ["eventocc-receiver", "receive", "--source", "sim:"]
    assert receiver["depends_on"]["server"]["condition"] == "service_healthy"
    assert receiver["environment"]["EVENTOCC_SERVER"] == "http://server:8000"


def test_compose_keeps_data_in_volumes_and_the_token_in_the_environment(compose: dict) -> None:
    assert set(compose["volumes"]) == {"eventocc-data", "receiver-out"}
    assert "eventocc-data:/data" in compose["services"]["server"]["volumes"]
    for service in compose["services"].values():
        # Passed on from the environment when set, and no compose call needs it set.
        assert service["environment"]["EVENTOCC_TOKEN"] is None
        assert service["build"]["args"]["BASE_IMAGE"] == "${BASE_IMAGE:-python:3.11-slim}"


def test_without_a_token_the_server_is_published_on_loopback_only(compose: dict) -> None:
    (published,) = compose["services"]["server"]["ports"]
    assert published.startswith("${EVENTOCC_BIND:-127.0.0.1}:")


def test_the_build_context_leaves_out_the_venv_and_the_history() -> None:
    ignored = (ROOT / ".dockerignore").read_text().splitlines()
    assert {".venv", ".git", "tests", "data"} <= set(ignored)
    lines = DOCKERFILE.read_text().splitlines()
    copied = [line.split()[1] for line in lines if line.startswith("COPY ")]
    assert not set(copied) & set(ignored), "the image needs what it copies"


def test_every_service_has_a_health_check(compose: dict) -> None:
    for name, service in compose["services"].items():
        check = service["healthcheck"]
        assert check["test"][0] == "CMD" and {"interval", "timeout", "retries"} <= set(check), name
    assert "/healthz" in " ".join(compose["services"]["server"]["healthcheck"]["test"])
    assert "health.json" in " ".join(compose["services"]["receiver"]["healthcheck"]["test"])


def test_dockerfile_takes_the_base_image_as_a_build_argument() -> None:
    lines = DOCKERFILE.read_text().splitlines()
    assert "ARG BASE_IMAGE=python:3.11-slim" in lines
    assert "FROM ${BASE_IMAGE}" in lines


def test_compose_config_is_valid_for_the_cli(tmp_path: Path) -> None:
    command = compose_command()
    if command is None:
        pytest.skip("no docker compose CLI here; the YAML checks above still ran")
    for token in ({"EVENTOCC_TOKEN": "t"}, {}):  # ps, logs, down: none needs a token set
        environment = {k: v for k, v in os.environ.items() if k != "EVENTOCC_TOKEN"}
        run = subprocess.run(
            [*command, "-f", str(COMPOSE), "config"],
            env={**environment, **token},
            capture_output=True,
            text=True,
            check=False,
        )
        assert run.returncode == 0, run.stderr
        assert "eventocc-receiver" in run.stdout


# --- for real ---------------------------------------------------------------------------------


def docker_engine_problem() -> str | None:
    if shutil.which("docker") is None or compose_command() is None:
        return "no docker client or compose CLI on this machine"
    info = subprocess.run(["docker", "info"], capture_output=True, text=True, check=False)
    if info.returncode != 0:
        return "no Docker engine answers (start one, e.g. with the shared docker-engine helper)"
    image = subprocess.run(
        ["docker", "image", "inspect", BASE_IMAGE], capture_output=True, check=False
    )
    if image.returncode != 0:
        return f"base image {BASE_IMAGE} is missing (set EVENTOCC_TEST_BASE_IMAGE)"
    return None


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def host_network_variant(compose: dict, port: int) -> dict:
    """The compose file for the test engine: no bridge network, so every container on the
    host's network (where published ports make no sense) and the server on a free port; and
    root inside, because the registry-less base image is a debootstrap tree imported with a
    0700 "/" that no later layer can widen, which locks an unprivileged user out."""
    variant = copy.deepcopy(compose)
    for service in variant["services"].values():
        service.pop("ports", None)
        service.pop("build", None)  # built beforehand; the context is relative to the original
        service["network_mode"] = "host"
        service["user"] = "root"
    variant["services"]["server"]["environment"]["EVENTOCC_PORT"] = str(port)
    variant["services"]["receiver"]["environment"]["EVENTOCC_SERVER"] = f"http://127.0.0.1:{port}"
    return variant


def wait_healthy(command: list[str], service: str, timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        ids = subprocess.run(
            [*command, "ps", "-q", service], capture_output=True, text=True, check=True
        ).stdout.split()
        if ids:
            state = subprocess.run(
                ["docker", "inspect", "--format", "{{json .State.Health.Status}}", ids[0]],
                capture_output=True,
                text=True,
                check=False,
            ).stdout.strip()
            if json.loads(state or "null") == "healthy":
                return
        time.sleep(2)
    raise AssertionError(f"{service} did not become healthy in {timeout_s:.0f} s")


@pytest.mark.docker
@pytest.mark.slow
@pytest.mark.timeout(1800)  # building on the vfs storage driver takes minutes
def test_images_build_and_the_compose_file_runs(
    compose: dict, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    problem = docker_engine_problem()
    if problem:
        pytest.skip(problem)
    port = free_port()
    variant = tmp_path / "docker-compose.yml"
    variant.write_text(yaml.safe_dump(host_network_variant(compose, port)))
    command = [*compose_command(), "-p", f"eventocc-test-{port}", "-f", str(variant)]
    # Every compose call (up, ps, down) interpolates the file, so each needs these.
    for name, value in {
        "EVENTOCC_TOKEN": "docker-test",
        "BASE_IMAGE": BASE_IMAGE,
        "DOCKER_BUILDKIT": "0",
        "COMPOSE_HTTP_TIMEOUT": "900",  # creating a container copies the image on vfs
    }.items():
        monkeypatch.setenv(name, value)
    build = subprocess.run(
        [
            "docker",
            "build",
            "--network",
            "host",
            "--build-arg",
            f"BASE_IMAGE={BASE_IMAGE}",
            "-f",
            str(DOCKERFILE),
            "-t",
            "eventocc:latest",
            str(ROOT),
        ],
        capture_output=True,
        text=True,
        check=False,
    )
    assert build.returncode == 0, build.stdout[-3000:] + build.stderr[-3000:]
    try:
        up = subprocess.run(
            [*command, "up", "-d", "--no-build"],
            capture_output=True,
            text=True,
            check=False,
        )
        assert up.returncode == 0, up.stderr
        wait_healthy(command, "server", 120)
        base = f"http://127.0.0.1:{port}"
        with urllib.request.urlopen(base + "/healthz", timeout=5) as response:
            assert json.load(response)["status"] == "ok"
        wait_healthy(command, "receiver", 240)
        with urllib.request.urlopen(base + "/metrics", timeout=5) as response:
            assert "eventocc_receivers_connected 1" in response.read().decode()
    finally:
        subprocess.run([*command, "down", "-v"], capture_output=True, check=False)
