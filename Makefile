# Two commands on a fresh machine (Python >= 3.11 and make): `make demo` and `make test`.
# Each creates the virtual environment in .venv and installs jaxhead on first use.
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.jaxhead-installed
PYTEST_ARGS ?=

.PHONY: demo test test-slow bench install clean

# constraints.txt: the versions the tests and the README's figures were run with (pyproject.toml keeps
# the supported ranges), so that a fresh clone installs what was tested.
$(STAMP): pyproject.toml constraints.txt
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -c constraints.txt -e '.[test,gmsh]'
	touch $(STAMP)

install: $(STAMP)

demo: $(STAMP)
	$(BIN)/jaxhead run configs/demo.toml

test: $(STAMP)
	$(BIN)/python -m pytest -q -n 2 $(PYTEST_ARGS)

test-slow: $(STAMP)
	$(BIN)/python -m pytest -q -m slow $(PYTEST_ARGS)

bench: $(STAMP)
	OPENBLAS_NUM_THREADS=1 $(BIN)/python benchmarks/forward.py
	$(BIN)/python benchmarks/mesh.py

clean:
	rm -rf runs .pytest_cache
