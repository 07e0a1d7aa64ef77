# Two commands on a fresh machine: `make demo` and `make test`.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo lint test soak bench install clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e '.[test,live,fleet,bench]'
	touch $(STAMP)

install: $(STAMP)

demo: $(STAMP)
	$(BIN)/trundle demo

# mypy resolves `trundle.*` imports through a folder holding a `trundle` link to the repository root
# (the root is the package; see [tool.mypy] in pyproject.toml).
LINT_ROOT := $(VENV)/lint-root

lint: $(STAMP)
	$(BIN)/ruff check .
	mkdir -p $(LINT_ROOT) && ln -sfn ../.. $(LINT_ROOT)/trundle
	cd $(LINT_ROOT) && ../bin/mypy --config-file ../../pyproject.toml

test: lint
	$(BIN)/python -m pytest -q -m "not slow" -n 2 --dist loadfile

soak: $(STAMP)
	$(BIN)/python -m pytest -q -m slow

bench: $(STAMP)
	for b in tools/bench/bench_*.py; do $(BIN)/python $$b || exit 1; done

clean:
	rm -rf $(VENV) build *.egg-info
