# recslam — setup and entry points. `make demo` and `make test` are the README's two commands.
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
DATA   ?= data/synth
SEED   ?= 0
ROBOTS ?= 3
SECONDS ?= 60

.PHONY: setup demo test lint typecheck bench clean compose-test swarm-test

$(STAMP): pyproject.toml requirements.lock
	@$(PYTHON) -c 'import sys; assert sys.version_info[:2] == (3, 11), "recslam needs Python 3.11, found " + sys.version' 
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -c requirements.lock -e '.[test]'
	@touch $(STAMP)

## ROS 1 from Debian (roscore, rospy, the messages) for `recslam robot --source ros1` and its
## live test; skipped (with a line saying so) when not root or without apt-get.
setup: $(STAMP)
	@sh scripts/install-ros.sh

## The main job: build the embedded synthetic dataset (if missing) and summarise it.
demo: $(STAMP)
	$(BIN)/recslam demo --data $(DATA) --robots $(ROBOTS) --seconds $(SECONDS) --seed $(SEED)

## The test suite (what CI runs): lint, format check, type check, then pytest.
test: $(STAMP)
	@bash scripts/install-browser.sh
	@sh scripts/install-ros.sh
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/python -m mypy
	$(BIN)/python -m pytest

lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

## mypy over the packages listed in pyproject.toml ([tool.mypy] files).
typecheck: $(STAMP)
	$(BIN)/python -m mypy

## docker compose's shared secret: a fresh random one, mode 600, never overwritten (git-ignored).
docker/secret.env:
	@umask 077 && $(PYTHON) -c "import secrets; print('RECSLAM_SECRET=' + secrets.token_hex(24))" > $@
	@echo "wrote $@: a new random RECSLAM_SECRET for every service of the stack"

## The real Docker test (not part of `make test`; needs root and a few GB of disk): starts a
## Docker daemon if none runs, builds the image in a fresh clone, runs `docker compose up` on a
## short synthetic dataset and checks the cloud's outputs (scripts/compose-test.sh).
compose-test:
	bash scripts/compose-test.sh

## The Docker Swarm stack on a one-node swarm here (not part of `make test`; root, a few GB of
## disk): starts a daemon if none runs, builds the image, `docker swarm init`, deploys
## docker-compose.swarm.yml on the host network, kills the edge's and a robot's task mid-run
## and checks the cloud's outputs each time (scripts/swarm-test.sh).
swarm-test:
	bash scripts/swarm-test.sh

bench: $(STAMP)
	@for b in benchmarks/bench_*.py; do echo "== $$b"; $(BIN)/python $$b || exit 1; done

clean:
	rm -rf $(VENV) build *.egg-info
