# Two entry points that do all set-up on a fresh machine:
#   make demo   creates .venv, installs softrtc with every extra, runs the main job
#   make test   creates .venv, installs, runs the whole test suite
PYTHON ?= python3.11
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: demo test venv clean

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	# The CPU build of torch first, so that the torch extra (torch>=2.2) is already met and pip fetches no CUDA build.
	$(PY) -m pip install --quiet "torch==2.13.0"
	$(PY) -m pip install --quiet -e ".[all]"
	touch $(STAMP)

venv: $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/softrtc demo

test: $(STAMP)
	SOFTRTC_REQUIRE_ALL=1 $(PY) -m pytest -q

clean:
	rm -rf $(VENV)
