# make install: create .venv and install cv2x_marl with every extra, under constraints.txt (idempotent)
# make run:     install, then the main job
# make test:    install, then lint (ruff), types (mypy) and the test suite (pytest)
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV ?= .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: install run test lint bench docs clean

install: $(STAMP)

$(STAMP): pyproject.toml constraints.txt
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --disable-pip-version-check -c constraints.txt -e ".[train,ray,torchrl,sumo,dev]"
	touch $(STAMP)

run: install
	$(BIN)/cv2x-marl reproduce --quick --out results --overwrite

lint: install
	$(BIN)/ruff check cv2x_marl tests benchmarks examples
	$(BIN)/ruff format --check cv2x_marl tests benchmarks examples
	$(BIN)/mypy cv2x_marl

test: lint
	$(BIN)/python -m pytest

bench: install
	$(BIN)/python benchmarks/bench_sim.py
	$(BIN)/python benchmarks/bench_regression.py
	$(BIN)/python benchmarks/bench_gbmu.py
	$(BIN)/python benchmarks/bench_env.py
	$(BIN)/python benchmarks/bench_train.py

docs: install
	$(BIN)/cv2x-marl config --markdown > docs/config.md

clean:
	rm -rf $(VENV) results .pytest_cache .mypy_cache .ruff_cache
