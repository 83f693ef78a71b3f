# Two commands set up everything on a fresh Debian machine:
#   make demo   start the server and a receiver on the virtual event camera
#   make docker-demo   the same in containers (docker compose, or docker-compose)
#   make test   run the test suite (slow full-size simulations excluded: make test-slow)
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
SUDO   := $(shell [ "$$(id -u)" = 0 ] || echo sudo)

.PHONY: demo docker-demo test test-slow lint bench bench-quick bench-stale system-deps clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e '.[dev]'
	$(BIN)/eventocc-receiver warmup
	touch $@

# Debian packages: Chromium drives the page tests.
system-deps:
	@command -v chromium >/dev/null || { $(SUDO) apt-get update -qq && \
	  DEBIAN_FRONTEND=noninteractive $(SUDO) apt-get install -y -qq chromium fonts-dejavu-core; }

demo: $(STAMP)
	$(BIN)/python -m eventocc.server.demo

COMPOSE ?= $(shell docker compose version >/dev/null 2>&1 && echo "docker compose" || echo docker-compose)

docker-demo:
	$(COMPOSE) -f docker/docker-compose.yml up --build

test: $(STAMP) system-deps
	$(BIN)/ruff check .
	$(BIN)/python -m pytest

test-slow: $(STAMP) system-deps
	$(BIN)/python -m pytest -m slow

lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

bench: $(STAMP)
	$(BIN)/python -m bench
	$(BIN)/python -m bench.stale

# Which sections of docs/BENCHMARKS.md are older than the code they measure.
bench-stale: $(STAMP)
	$(BIN)/python -m bench.stale

bench-quick: $(STAMP)
	$(BIN)/python -m bench --quick

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache test-artifacts
