# Two commands from a fresh clone:
#
#   make demo    # track the bundled CMU walk (torchmocap-track; ARGS="..." adds overrides)
#   make test    # the test suite (OMP_NUM_THREADS=1 python -m pytest -q -n auto --maxprocesses 4:
#                # pytest-xdist, one single-threaded worker per core up to 4; TEST_WORKERS=0
#                # runs it in one process; PYTEST_ARGS="..." adds options)
#
# Both first prepare $(VENV): create it with $(PYTHON) -m venv when missing, install the pinned
# CPU torch, then the project with its dev extras (pip install -e ".[dev]"; they include the
# detector and the Anny body, whose cache is built once per machine, ~1-2 min, in
# $TORCHMOCAP_CACHE_DIR or ~/.cache/torchmocap). Stamp files in
# $(VENV) remember what was installed: a re-run with nothing changed starts at once; a changed
# pyproject.toml (or TORCH_VERSION) reinstalls only what depends on it.
#
# Variables: PYTHON (3.10+, default python3), VENV (default .venv), TORCH_VERSION (2.13.0),
# TORCH_PIP_ARGS (extra pip arguments for torch, e.g. --index-url
# https://download.pytorch.org/whl/cpu to get the CPU build on x86-64 Linux), CI (set: print the
# 25 slowest tests; the test suite also derandomizes hypothesis and fails on missing test data).

PYTHON ?= python3
VENV ?= .venv
TORCH_VERSION ?= 2.13.0
TORCH_PIP_ARGS ?=
ARGS ?=
PYTEST_ARGS ?=
TEST_WORKERS ?= auto

PY := $(VENV)/bin/python
PIP := $(PY) -m pip
STAMP_TORCH := $(VENV)/.stamp-torch-$(TORCH_VERSION)
STAMP_DEV := $(VENV)/.stamp-dev

.PHONY: demo test prepare clean-venv

demo: prepare
	$(VENV)/bin/torchmocap-track $(ARGS)

test: prepare
	@rc=0; OMP_NUM_THREADS=1 MKL_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 \
	  $(PY) -m pytest -q -n $(TEST_WORKERS) --maxprocesses 4 $(if $(CI),--durations=25) \
	  $(PYTEST_ARGS) || rc=$$?; \
	if [ $$rc -eq 5 ]; then echo "make test: no tests collected (a failure)"; exit 1; fi; \
	exit $$rc

prepare: $(STAMP_DEV)

$(PY):
	@$(PYTHON) -c 'import sys; sys.exit(0 if sys.version_info >= (3, 10) else \
	"torchmocap needs Python 3.10 or newer; found " + sys.version.split()[0] + \
	" (make PYTHON=python3.1x ...)")'
	$(PYTHON) -m venv $(VENV)
	$(PIP) install -q --upgrade pip

$(STAMP_TORCH): | $(PY)
	$(PIP) install -q $(TORCH_PIP_ARGS) "torch==$(TORCH_VERSION)"
	rm -f $(VENV)/.stamp-torch-* $(STAMP_DEV)
	touch $@

$(STAMP_DEV): pyproject.toml $(STAMP_TORCH)
	$(PIP) install -q -e ".[dev]"
	touch $@

clean-venv:
	rm -rf $(VENV)
