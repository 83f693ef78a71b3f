"""The deployment files: the compose file checked in every run; the compose file built and run
for real, up to the receiver's container verifying the sample, where a Docker engine is
available (``pytest -m docker``; minutes)."""

from __future__ import annotations

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

from eventocc.server import demo
from eventocc.server.demo import SAMPLE_SHA256
from eventocc.server.settings import Settings

ROOT = Path(__file__).resolve().parent.parent
COMPOSE = ROOT / "docker" / "docker-compose.yml"
DOCKERFILE = ROOT / "docker" / "Dockerfile"
BASE_IMAGE = os.environ.get("EVENTOCC_TEST_BASE_IMAGE", "eventocc-base:bookworm")
"""Base for the test build: a local Debian image (EVENTOCC_TEST_BASE_IMAGE), since a test
machine may reach no registry."""


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


def test_compose_runs_a_server_the_sample_and_a_receiver_on_the_virtual_camera(
    compose: dict,
) -> None:
    services = compose["services"]
    assert set(services) == {"server", "sample", "receiver"}
    receiver = services["receiver"]
    assert receiver["command"][:4] == ["eventocc-receiver", "receive", "--source", "sim:"]
    assert receiver["depends_on"]["server"]["condition"] == "service_healthy"
    assert receiver["environment"]["EVENTOCC_SERVER"] == "http://server:8000"
    sample = services["sample"]
    assert sample["command"][-2:] == ["--upload-to", "http://server:8000"]
    assert sample["depends_on"]["server"]["condition"] == "service_healthy"
    assert sample["restart"] == "no"  # one shot: uploads and exits


def test_compose_keeps_data_in_volumes_and_the_token_in_the_environment(compose: dict) -> None:
    assert set(compose["volumes"]) == {"eventocc-data", "receiver-out"}
    assert "eventocc-data:/data" in compose["services"]["server"]["volumes"]
    for service in compose["services"].values():
        # Passed on from the environment when set, and no compose call needs it set.
        assert service["environment"]["EVENTOCC_TOKEN"] is None
        assert service["build"]["args"]["BASE_IMAGE"] == "${BASE_IMAGE:-python:3.11-slim}"
        assert service["build"]["network"] == "${EVENTOCC_BUILD_NETWORK:-default}"


def test_without_a_token_the_server_is_published_on_loopback_only(compose: dict) -> None:
    (published,) = compose["services"]["server"]["ports"]
    assert published.startswith("${EVENTOCC_BIND:-127.0.0.1}:")


def test_the_build_context_is_what_the_image_copies() -> None:
    """Everything is left out but what the Dockerfile copies (the local .venv, the git history,
    the tests, any output folder stay out without being named)."""
    patterns = [
        line.strip()
        for line in (ROOT / ".dockerignore").read_text().splitlines()
        if line.strip() and not line.startswith("#")
    ]
    assert patterns[0] == "*"
    let_in = {p.removeprefix("!") for p in patterns if p.startswith("!")}
    copied = set()
    for line in DOCKERFILE.read_text().splitlines():
        if line.startswith("COPY "):
            copied |= set(line.split()[1:-1])
    assert copied | {"docker/Dockerfile"} == let_in
    assert all((ROOT / path).exists() for path in let_in)


def test_every_service_that_stays_up_has_a_health_check(compose: dict) -> None:
    for name, service in compose["services"].items():
        if service.get("restart") == "no":
            continue
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


def test_the_sample_service_uploads_the_sample_once(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """What the compose file's one-shot ``sample`` service runs, twice (a second ``up``)."""
    server, thread = demo.start_server(Settings(data_dir=tmp_path, port=0))
    try:
        base_url = demo.bound_url(server)
        for _ in range(2):
            demo.main(["--upload-to", base_url + "/"])
        with urllib.request.urlopen(base_url + "/api/messages") as response:
            messages = json.load(response)["messages"]
    finally:
        server.should_exit = True
        thread.join(10)
    assert [m["sha256"] for m in messages] == [SAMPLE_SHA256]
    printed = capsys.readouterr().out.splitlines()
    assert printed == [f"sample message {messages[0]['id']} (hello.txt) on {base_url}/"] * 2


# --- for real ---------------------------------------------------------------------------------


def docker_engine_problem() -> str | None:
    if shutil.which("docker") is None or compose_command() is None:
        return "no docker client or compose CLI on this machine"
    info = subprocess.run(["docker", "info"], capture_output=True, text=True, check=False)
    if info.returncode != 0:
        return "no Docker engine answers (start one to run this test)"
    image = subprocess.run(
        ["docker", "image", "inspect", BASE_IMAGE], capture_output=True, check=False
    )
    if image.returncode != 0:
        return f"base image {BASE_IMAGE} is missing (set EVENTOCC_TEST_BASE_IMAGE)"
    return None


def docker(*args: str) -> str:
    return subprocess.run(["docker", *args], capture_output=True, text=True, check=True).stdout


def usable_base(image: str) -> str:
    """``image``, or a copy of it whose "/" others may enter. A base made without a registry
    (a debootstrap tree in a mktemp -d directory, then ``docker import``) has a 0700 root, which
    the Dockerfile refuses: its non-root user could run nothing. ``docker export`` of a
    container writes the tree without that root entry, so importing it again fixes it."""
    probe = ["run", "--rm", "--network", "none", "--user", "10001:0", image]
    if subprocess.run(["docker", *probe, "/bin/true"], capture_output=True).returncode == 0:
        return image
    fixed = f"{image}-usable-root"
    if subprocess.run(["docker", "image", "inspect", fixed], capture_output=True).returncode:
        container = docker("create", image, "/bin/true").strip()
        try:
            exported = subprocess.Popen(["docker", "export", container], stdout=subprocess.PIPE)
            subprocess.run(
                ["docker", "import", "-", fixed],
                stdin=exported.stdout,
                capture_output=True,
                check=True,
            )
            assert exported.wait() == 0
        finally:
            docker("rm", container)
    return fixed


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def container_of(command: list[str], service: str) -> str | None:
    ids = subprocess.run(
        [*command, "ps", "-q", service], capture_output=True, text=True, check=True
    ).stdout.split()
    return ids[0] if ids else None


def wait_healthy(command: list[str], service: str, timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        container = container_of(command, service)
        if container:
            state = docker("inspect", "--format", "{{json .State.Health.Status}}", container)
            if json.loads(state.strip() or "null") == "healthy":
                return
        time.sleep(2)
    raise AssertionError(f"{service} did not become healthy in {timeout_s:.0f} s")


def get(url: str) -> tuple[int, str, bytes]:
    with urllib.request.urlopen(url, timeout=10) as response:
        return response.status, response.headers.get_content_type(), response.read()


def wait_verified_sample(base_url: str, timeout_s: float) -> dict:
    """The reception of the demo's sample, once a receiver delivered it verified."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        receptions = json.loads(get(base_url + "/api/receptions")[2])["receptions"]
        for reception in receptions:
            if reception["sha256"] == SAMPLE_SHA256 and reception["verified"]:
                return reception
        time.sleep(2)
    raise AssertionError(f"no verified reception of the sample within {timeout_s:.0f} s")


@pytest.mark.docker
@pytest.mark.slow
@pytest.mark.timeout(3600)  # building on the vfs storage driver takes many minutes
def test_the_compose_file_builds_comes_up_and_the_receiver_verifies_the_sample(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The compose file itself, as ``make docker-demo`` runs it, with what a user may set
    (base image, build network, port), and no token: ``up --build``, the pages, the sample
    verified by the receiver's container, then ``ps``, ``logs`` and ``down``."""
    problem = docker_engine_problem()
    if problem:
        pytest.skip(problem)
    port = free_port()
    monkeypatch.delenv("EVENTOCC_TOKEN", raising=False)
    monkeypatch.setenv("BASE_IMAGE", usable_base(BASE_IMAGE))
    monkeypatch.setenv("EVENTOCC_PORT", str(port))
    # Creating a container copies the whole image on the vfs storage driver.
    monkeypatch.setenv("COMPOSE_HTTP_TIMEOUT", "900")
    if subprocess.run(["docker", "network", "inspect", "bridge"], capture_output=True).returncode:
        monkeypatch.setenv("EVENTOCC_BUILD_NETWORK", "host")  # no bridge: no way out but the host's
    command = [*compose_command(), "-p", f"eventocc-test-{port}", "-f", str(COMPOSE)]
    try:
        started = time.monotonic()
        up = subprocess.run(
            [*command, "up", "-d", "--build"], capture_output=True, text=True, check=False
        )
        assert up.returncode == 0, up.stdout[-3000:] + up.stderr[-3000:]
        up_s = time.monotonic() - started
        wait_healthy(command, "server", 180)
        base_url = f"http://127.0.0.1:{port}"
        assert json.loads(get(base_url + "/healthz")[2])["status"] == "ok"
        for page in ("/transmitter", "/dashboard"):
            status, content_type, _ = get(base_url + page)
            assert (status, content_type) == (200, "text/html"), page
        reception = wait_verified_sample(base_url, 600)
        assert reception["name"] == "hello.txt"
        verified_s = time.monotonic() - started - up_s
        print(f"up --build {up_s:.0f} s, then the sample verified in {verified_s:.0f} s")

        server = container_of(command, "server")
        receiver = container_of(command, "receiver")
        assert server and receiver
        for container in (server, receiver):
            assert docker("inspect", "--format", "{{.Config.User}}", container).strip() == "10001:0"
            assert docker("exec", container, "id", "-u").strip() == "10001"
        ps = subprocess.run([*command, "ps"], capture_output=True, text=True, check=False)
        assert ps.returncode == 0, ps.stderr
        assert "receiver" in ps.stdout
        logs = subprocess.run([*command, "logs"], capture_output=True, text=True, check=False)
        assert logs.returncode == 0, logs.stderr
        assert "verified against the sender's sha256" in logs.stdout
        assert "sample message" in logs.stdout
    finally:
        down = subprocess.run([*command, "down", "-v"], capture_output=True, text=True)
    assert down.returncode == 0, down.stderr
