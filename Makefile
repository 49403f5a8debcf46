# The two sacred commands: `make run` and `make test`. Both set everything up first.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
# The CPU build of torch lies on this disk; an unpinned torch pulls a multi-GB CUDA build.
TORCH_PIN := torch==2.13.0
STAMP := $(VENV)/.installed
# pytest workers: most tests wait on processes they started, so two share two cores well; a
# module's tests stay on one worker (--dist loadscope), as they share its fixtures' runs
TEST_WORKERS ?= 2

.PHONY: setup run test lint bench clean

$(BIN)/python:
	$(PY) -m venv $(VENV)

$(STAMP): $(BIN)/python pyproject.toml
	$(BIN)/pip install -q --upgrade pip
	$(BIN)/pip install -q "$(TORCH_PIN)"
	$(BIN)/pip install -q -e ".[test]" "$(TORCH_PIN)"
	touch $(STAMP)

setup: $(STAMP)

run: setup
	$(BIN)/neoslam run $(ARGS)

test: setup
	$(BIN)/ruff check .
	$(BIN)/python -m pytest -q -n $(TEST_WORKERS) --dist loadscope $(PYTEST_ARGS)

lint: setup
	$(BIN)/ruff check .

bench: setup
	$(BIN)/python bench/transport.py
	$(BIN)/python bench/frontend.py
	$(BIN)/python bench/tm.py
	$(BIN)/python bench/ratslam.py
	$(BIN)/python bench/e2e.py
	$(BIN)/python bench/stages.py
	$(BIN)/neoslam bench emulate --no-live --out bench/results/emulate
	$(BIN)/neoslam bench throughput --backbone random_alexnet --rates 10,13,20,30,35,40,45,60 --duration 30 --topology both --out bench/results/throughput
	$(BIN)/neoslam bench throughput --backbone random_alexnet --rates 30 --duration 300 --topology pipeline --out bench/results/throughput
	$(BIN)/neoslam bench throughput --backbone random_alexnet --rates 30,45,60 --duration 30 --topology pipeline --projection sparse --out bench/results/throughput_sparse
	$(BIN)/neoslam bench throughput --backbone random_alexnet --rates "" --scaling 20000 --out bench/results/throughput
	$(BIN)/neoslam bench throughput --rates 30,45,60 --duration 30 --topology both --out bench/results/throughput_default
	$(BIN)/python bench/stage_a.py
	$(BIN)/python bench/cores.py
	$(BIN)/python bench/soak.py --backbone random_alexnet
	$(BIN)/python bench/soak.py --out bench/results/soak_default.json

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache .ruff_cache
