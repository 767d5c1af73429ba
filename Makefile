# make install: create .venv and install cv2x_marl with every extra, under constraints.txt, then compile the
#               numba kernels once into their on-disk cache (about 30 s; again only when a compiled source
#               changed), so a user's first env call does not pay it (idempotent)
# make run:     install, then the main job
# make test:    install, then lint (ruff), types (mypy) and the test suite (pytest)
# make numba-cache: drop numba's on-disk caches when a compiled module's source changed (numba keys a cache
#               to its own file only, so a kernel calling into a changed module would keep stale code), then
#               compile them again (python -m cv2x_marl.experiments.warm); part of make install
# make test-portable: the kernel-equality tests (pytest -m kernel_equality) again under numpy's baseline
#               SIMD paths and numba's generic x86-64 target, with a fresh numba cache, then once more with
#               numpy's exp/log/log10/power moved by 1-2 ulp (tests/conftest.py) (.ci/run runs it)
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV ?= .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: install run test test-portable lint bench docs clean numba-cache

install: $(STAMP) numba-cache

$(STAMP): pyproject.toml constraints.txt
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --disable-pip-version-check -c constraints.txt -e ".[train,ray,torchrl,sumo,dev]"
	touch $(STAMP)

numba-cache: $(STAMP)
	@h=$$(grep -rl --include='*.py' njit cv2x_marl | sort | xargs cat | sha256sum | cut -c1-16); \
	if [ "$$(cat $(VENV)/.numba-sources 2>/dev/null)" != "$$h" ]; then \
		find cv2x_marl -name '*.nb[ic]' -delete; mkdir -p $(VENV); echo "$$h" > $(VENV)/.numba-sources; \
		echo "numba caches cleared (compiled sources changed)"; fi; \
	if [ "$$(cat $(VENV)/.numba-warm 2>/dev/null)" != "$$h" ]; then \
		$(BIN)/python -m cv2x_marl.experiments.warm && echo "$$h" > $(VENV)/.numba-warm; fi

run: install numba-cache
	$(BIN)/cv2x-marl reproduce --quick --out results --overwrite

lint: install
	$(BIN)/ruff check cv2x_marl tests benchmarks examples
	$(BIN)/ruff format --check cv2x_marl tests benchmarks examples
	$(BIN)/mypy cv2x_marl

test: lint numba-cache
	$(BIN)/python -m pytest

PORTABLE_ENV := NPY_DISABLE_CPU_FEATURES="X86_V3 X86_V4 AVX512_ICL AVX512_SPR" NUMBA_CPU_NAME=generic

test-portable: install
	cache=$$(mktemp -d) && trap 'rm -rf "$$cache"' EXIT && export $(PORTABLE_ENV) NUMBA_CACHE_DIR="$$cache" && \
	$(BIN)/python -c "from numpy._core._multiarray_umath import __cpu_dispatch__ as d, __cpu_features__ as f; \
	print('numpy SIMD dispatch in use:', ' '.join(x for x in d if f.get(x)) or 'none (baseline)')" && \
	$(BIN)/python -m pytest -m kernel_equality -p no:cacheprovider && \
	CV2X_MARL_TEST_ULP_NOISE=1 $(BIN)/python -m pytest -m kernel_equality -p no:cacheprovider

bench: install
	$(BIN)/python benchmarks/bench_sim.py
	$(BIN)/python benchmarks/bench_regression.py
	$(BIN)/python benchmarks/bench_gbmu.py
	$(BIN)/python benchmarks/bench_env.py
	$(BIN)/python benchmarks/bench_train.py

docs: install
	$(BIN)/cv2x-marl config --markdown > docs/config.md
	$(BIN)/python -m cv2x_marl.env.pages docs/envs > /dev/null
	$(BIN)/python -m cv2x_marl.cli.reference > docs/cli.md
	$(BIN)/python -m cv2x_marl.cli.reference api > docs/api.md

clean:
	rm -rf $(VENV) results .pytest_cache .mypy_cache .ruff_cache
