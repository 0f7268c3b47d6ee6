# Likeness: the two set-up commands are `make demo` and `make test`; both create .venv if needed.
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
PIP    := $(PY) -m pip
EXTRAS ?= offline,test

.PHONY: install demo test lint bench clean

$(VENV)/.installed: pyproject.toml constraints.txt
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PIP) install -q --upgrade pip
	$(PIP) install -q -c constraints.txt -e '.[$(EXTRAS)]'
	$(PY) -m models.kernels  # compile the in-cycle kernels into numba's cache once
	touch $@

install: $(VENV)/.installed

demo: install
	$(VENV)/bin/likeness demo

test: install
	$(PY) -m pytest -q

lint: install
	$(VENV)/bin/ruff check .

bench: install
	$(PIP) install -q -c constraints.txt -e '.[$(EXTRAS),solvers,bench]'
	$(PY) -m benchmarks

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache .ruff_cache
