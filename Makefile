# HAA developer entry points. `make demo` and `make test` work on a fresh clone with Python 3.11 and make.
PYTHON ?= python3.11
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: setup demo test test-fast lint proto verify bench clean docker-setup image

setup: $(STAMP)

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade "pip==25.3"
	$(BIN)/pip install --quiet -e ".[test]"
	touch $(STAMP)

demo: setup
	$(BIN)/haactl demo

test: setup
	$(BIN)/ruff check .
	$(BIN)/python -m pytest -q

test-fast: setup
	$(BIN)/python -m pytest -q -m "not slow"

lint: setup
	$(BIN)/ruff check .
	$(BIN)/ruff format --check . || true

# Regenerate the committed protobuf/gRPC modules (tests/test_proto_fresh.py fails when they are stale).
proto: setup
	$(BIN)/python -m haa.pb.generate

verify: setup
	$(BIN)/haactl verify ufd --schedules 2000 --hosts 7
	$(BIN)/haactl verify oac --schedules 2000 --hosts 7

bench: setup
	$(BIN)/haactl bench ap1

# Container engine (Debian's docker.io + docker-compose v1; starts dockerd if needed) and the haa-hostd image,
# built offline from a debootstrap base and a host-filled wheelhouse. See docs/containers.md.
docker-setup:
	scripts/docker-setup.sh

image:
	PYTHON=$(PYTHON) scripts/build-image.sh

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache .ruff_cache
