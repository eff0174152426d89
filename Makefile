# The two commands of the README: `make train` and `make test`. Each sets up .venv first, once.
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
# torch goes in first so that the dependency resolver never pulls a different build. The default
# is the CUDA build on Linux from PyPI (a CPU build where one is provided locally); override with
# e.g. TORCH_SPEC="torch --index-url https://download.pytorch.org/whl/cpu".
TORCH_SPEC ?= torch==2.13.0
ARGS ?=

.PHONY: install lint test train bench
install: $(VENV)/.installed

# The last step fetches the LPIPS weights for evaluation, once (skipped when already there);
# without a network the evaluations report LPIPS as unavailable, so a failure does not stop it.
$(VENV)/.installed: pyproject.toml Makefile
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -c "import torch" 2>/dev/null || $(BIN)/python -m pip install -q $(TORCH_SPEC)
	$(BIN)/python -m pip install -q -e ".[test]"
	$(BIN)/cdcgs weights lpips || echo "LPIPS weights not installed: run .venv/bin/cdcgs weights lpips later"
	touch $@

lint: install
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

test: install
	$(BIN)/python -m pytest -q tests $(ARGS)

train: install
	$(BIN)/python examples/train_garden.py $(ARGS)

bench: install
	$(BIN)/python benchmarks/run.py $(ARGS)
