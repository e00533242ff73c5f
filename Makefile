# `make demo` and `make test` do all the set-up on a fresh machine.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: demo test docs lint format clean

$(PY):
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip

$(STAMP): $(PY) pyproject.toml constraints.txt
	$(PY) -m pip install --quiet -c constraints.txt -e ".[dev]"
	touch $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/dorp demo

test: $(STAMP)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .
	$(PY) -m pytest

# The HTML API reference from the docstrings, into docs/api/; any output from pdoc (a warning,
# an error) fails it. dorp_rl.envs and dorp_rl.trainers are named as well: they live outside
# dorp_rl/ (package-dir), where pdoc does not look for submodules. The -W filters hide only
# pdoc's warnings about torchrl 0.14.1's own annotations, which name types torchrl imports for
# type checkers alone (EnvBase.collector and ._collector, LossModule.tensor_keys); the envs
# and losses here inherit them.
PDOC_FILTERS := \
	-W 'ignore:Error parsing type annotation BaseCollector | None for ' \
	-W 'ignore:Error parsing type annotation weakref.ReferenceType[LLMCollector] | None for ' \
	-W 'ignore:Error parsing type annotation _AcceptedKeys for '

docs: $(STAMP)
	rm -rf docs/api
	@out=$$($(PY) $(PDOC_FILTERS) -m pdoc --docformat google -o docs/api \
		dorp_rl dorp_rl.envs dorp_rl.trainers 2>&1) \
		&& [ -z "$$out" ] || { echo "$$out"; echo "make docs: pdoc failed or warned" >&2; exit 1; }
	@echo "API reference: docs/api/index.html"

lint: $(STAMP)
	$(VENV)/bin/ruff check --fix .
	$(VENV)/bin/ruff format .

clean:
	rm -rf $(VENV) outputs runs docs/api .pytest_cache .ruff_cache
