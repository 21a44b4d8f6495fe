# Two commands on a fresh machine: `make run` and `make test`. Each creates .venv on first use.
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
CONFIG ?= configs/quick.yaml
# Curricula of CONFIG trained side by side (seeds seed, seed+1, ...), a process each, their final
# models handed over as one ensemble. quick.yaml trains two: out of domain the pair beats its
# average member, in little more than one curriculum's time on 2 cores, where one curriculum
# leaves the second core mostly idle (bench/README.md, "Two curricula"). Other configs train one
# unless MEMBERS says (learnability and canonical-baseline runs hand over no model to join).
MEMBERS ?= $(if $(filter configs/quick.yaml,$(CONFIG)),2,1)
# pytest-xdist workers for `make test`: the suite is mostly one busy core at a time, so two
# workers take about half its time on 2 cores (tests/conftest.py sends them a module at a time).
TEST_WORKERS ?= 2

.PHONY: install run test test-integration lint bench constraints clean

# Packages go in without their bytecode (--no-compile): Python compiles what it imports on first
# use, where compiling all 14,700 files of the packages, most of them never imported (torch's
# CUDA build), took the install about 50 s on 2 cores.
# Installing ends by compiling the render pipeline's numba kernels, as the Docker image does at
# build time: otherwise each of make run's curricula compiles them on its first images, about a
# minute of CPU, inside the run's time.
$(STAMP): pyproject.toml constraints.txt
	@$(PYTHON) -c 'import sys; sys.exit(0 if sys.version_info[:2] == (3, 11) else "foldwise needs Python 3.11 (bpy 5.0.1 requires it)")'
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet --no-compile -c constraints.txt -e '.[dev]'
	$(BIN)/python -c 'from workers.render.pipeline import compile_kernels; compile_kernels()'
	touch $(STAMP)

install: $(STAMP)

## The main job: an experiment on the embedded default (SQLite in ./var, eager Celery).
run: $(STAMP)
	$(BIN)/foldwise run $(CONFIG) --members $(MEMBERS)

## The test suite (tests/integration runs against local Redis + PostgreSQL, or skips saying why).
test: lint
	$(BIN)/python -m pytest -n $(TEST_WORKERS)

test-integration: $(STAMP)
	$(BIN)/python -m pytest tests/integration -v

## Lint and format check (ruff, configured in pyproject.toml's [tool.ruff]).
lint: $(STAMP)
	$(BIN)/ruff check . && $(BIN)/ruff format --check .

bench: $(STAMP)
	$(BIN)/python bench/render.py
	$(BIN)/python bench/train.py

## Re-pin constraints.txt from the current environment.
constraints: $(STAMP)
	{ echo "# Exact versions known to install together on these machines (Python 3.11, x86_64)."; \
	  echo "# Regenerate: make constraints"; \
	  $(BIN)/python -m pip freeze --exclude-editable | grep -v '^foldwise'; } > constraints.txt

clean:
	rm -rf $(VENV) var .pytest_cache
