# HAA developer entry points. `make demo` and `make test` work on a fresh clone with Python 3.11 and make.
PYTHON ?= python3.11
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: setup demo test test-fast lint proto verify bench clean docker-setup image chaos compose-up compose-down \
	compose-status idle fuzz results

# The venv, and Debian's chromium for the dashboard's browser test (scripts/browser-setup.sh: never fails setup).
setup: $(STAMP)
	@scripts/browser-setup.sh

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade "pip==25.3"
	$(BIN)/pip install --quiet -e ".[test]"
	touch $(STAMP)

demo: setup
	$(BIN)/haactl mission run missions/demo.yaml --transcript -o mission-runs/demo

test: setup
	$(BIN)/ruff check .
	$(BIN)/python -m pytest -q

test-fast: setup
	$(BIN)/python -m pytest -q -m "not slow and not docker"

lint: setup
	$(BIN)/ruff check .
	$(BIN)/ruff format --check . || true

# A longer fuzzing run: every decoder that reads bytes from outside (tests/test_fuzz.py: host links, agent
# channel, control and sim APIs, agent transactions, DDB) and every YAML file (tests/test_files.py), about
# 20,000 fresh random inputs per target (CI runs a fixed few thousand). A crash found becomes a named test.
fuzz: setup
	HAA_FUZZ_EXAMPLES=20000 $(BIN)/python -m pytest -q tests/test_fuzz.py tests/test_files.py tests/test_apply_total.py

# Regenerate the committed protobuf/gRPC modules (tests/test_proto_fresh.py fails when they are stale).
proto: setup
	$(BIN)/python -m haa.pb.generate

verify: setup
	$(BIN)/haactl verify ufd --schedules 2000 --hosts 7
	$(BIN)/haactl verify oac --schedules 2000 --hosts 7
	$(BIN)/haactl verify membership --schedules 2000 --hosts 7
	$(BIN)/haactl verify ddb --schedules 2000 --hosts 7
	$(BIN)/haactl verify allocation --schedules 2000 --hosts 7
	$(BIN)/haactl verify transfer --schedules 2000 --hosts 7
	$(BIN)/haactl verify recovery --schedules 2000 --hosts 7

bench: setup
	$(BIN)/haactl bench ap1

# docs/results.md from bench-results/*.json (tests/test_results_doc.py fails when the page is stale).
results: setup
	$(BIN)/python -m haa.lab.results

# Container engine (Debian's docker.io + docker-compose v1; starts dockerd if needed) and the haa-hostd image,
# built offline from a debootstrap base and a host-filled wheelhouse. See docs/containers.md.
docker-setup:
	scripts/docker-setup.sh

image:
	PYTHON=$(PYTHON) scripts/build-image.sh

# The container chaos tests alone (tests/chaos, marker docker; fail instead of skip without docker).
chaos: setup
	HAA_REQUIRE_DOCKER=1 $(BIN)/python -m pytest -q -m docker tests/chaos

# The 10-host compose cluster through haactl (docs/cluster.md); `make image` first.
compose-up: setup
	$(BIN)/haactl cluster up --compose --hosts 10

compose-status: setup
	$(BIN)/haactl cluster status --compose

compose-down: setup
	$(BIN)/haactl cluster down --compose

# Idle cost of a 10-host cluster, local processes then containers -> bench-results/idle.json
idle: setup
	$(BIN)/haactl bench idle --hosts 10 --duration 60
	$(BIN)/haactl bench idle --hosts 10 --duration 60 --compose

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache .ruff_cache
