# Likeness: the two set-up commands are `make demo` and `make test`; both create .venv if needed.
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
PIP    := $(PY) -m pip
EXTRAS ?= offline,test
# Blender as a Python module for tests/blender, where a wheel exists (Linux, Python 3.11). bpy declares numpy<2 against
# the pinned numpy 2 (under 2 only its audio fails to start; the add-on needs none), so it installs with --no-deps.
BLENDER_ON := python_version == "3.11" and platform_system == "Linux"
BLENDER := 'bpy==5.0.1; $(BLENDER_ON)' 'requests; $(BLENDER_ON)' 'zstandard; $(BLENDER_ON)'

.PHONY: install demo test lint bench clean

$(VENV)/.installed: pyproject.toml constraints.txt
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PIP) install -q --upgrade pip
	$(PIP) install -q -c constraints.txt -e '.[$(EXTRAS)]'
	$(PIP) install -q -c constraints.txt --no-deps $(BLENDER)
	$(PY) -m models.kernels  # compile the in-cycle kernels into numba's cache once
	$(PY) -m offline.fem.warmup  # and the FEM's kernels
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
