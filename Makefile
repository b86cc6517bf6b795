# Two entry points that do all set-up on a fresh machine:
#   make demo   creates .venv, installs softrtc with every extra, runs the main job
#   make test   creates .venv, installs (LeRobot's RTC modules too), runs the whole test suite on two workers
#   make docs   builds the documentation site into site/
PYTHON ?= python3.11
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: demo test venv clean lerobot-envs

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	# The CPU build of torch first, so that the torch extra (torch>=2.2) is already met and pip fetches no CUDA build.
	$(PY) -m pip install --quiet "torch==2.13.0"
	# setuptools notes on every editable install of a flat layout that a folder named like the package (here
	# softrtc/, the package itself) may shadow it; the notice is about editable installs, not this project.
	PYTHONWARNINGS="ignore:Editable installation" $(PY) -m pip install --quiet -e ".[all]"
	touch $(STAMP)

# LeRobot's RTC modules for its conformance adapter (spec/41-thirdparty.md [TP-6], [TP-7]): without its declared
# dependencies, which pin torch<2.11 and bring its dataset and vision stack; its RTC code imports only torch.
# 0.4.4 goes into .venv (Python 3.11); 0.6.1 needs Python 3.12 and gets a venv of its own with torch (PyPI's
# only Linux build of torch for 3.12 is the CUDA one, about 4.7 GB with its nvidia packages; it runs on the CPU),
# numpy and softrtc without dependencies. Measured set-up times are in spec/41-thirdparty.md [TP-7].
LEROBOT_STAMP := $(VENV)/.lerobot-0.4.4
PYTHON312 ?= $(firstword $(wildcard $(HOME)/.pyenv/versions/3.12*/bin/python3.12 /root/.pyenv/versions/3.12*/bin/python3.12) python3.12)
LEROBOT_NEW_VENV := .venv-lerobot-0.6.1
LEROBOT_NEW_STAMP := $(LEROBOT_NEW_VENV)/.installed

$(LEROBOT_STAMP): $(STAMP)
	$(PY) -m pip install --quiet --no-deps "lerobot==0.4.4"
	touch $(LEROBOT_STAMP)

$(LEROBOT_NEW_STAMP): pyproject.toml
	test -x $(LEROBOT_NEW_VENV)/bin/python || $(PYTHON312) -m venv $(LEROBOT_NEW_VENV)
	$(LEROBOT_NEW_VENV)/bin/python -m pip install --quiet "torch==2.13.0" "numpy>=1.26"
	$(LEROBOT_NEW_VENV)/bin/python -m pip install --quiet --no-deps "lerobot==0.6.1"
	PYTHONWARNINGS="ignore:Editable installation" $(LEROBOT_NEW_VENV)/bin/python -m pip install --quiet --no-deps -e .
	touch $(LEROBOT_NEW_STAMP)

lerobot-envs: $(LEROBOT_STAMP) $(LEROBOT_NEW_STAMP)

venv: $(STAMP)

# The documentation site (mkdocs.yml, sources under docs/ and spec/) into site/; `make test` builds it again
# with warnings as errors and opens it in headless Chromium (tests/docs/). A fresh Debian machine lacks
# Chromium: it is installed here with apt-get, which needs root (elsewhere, install the package `chromium`).
.PHONY: docs
CHROMIUM := /usr/bin/chromium

$(CHROMIUM):
	apt-get update && apt-get install -y chromium

docs: $(STAMP)
	NO_MKDOCS_2_WARNING=1 $(VENV)/bin/mkdocs build --site-dir site

test: $(CHROMIUM)

demo: $(STAMP)
	$(VENV)/bin/softrtc demo

# Two pytest-xdist workers, one per core of the 2-core machines the suite is sized for; whole files go to one
# worker (module fixtures are built once) and conftest.py hands out the files with slow tests first.
test: $(STAMP) $(LEROBOT_STAMP) $(LEROBOT_NEW_STAMP)
	SOFTRTC_REQUIRE_ALL=1 $(PY) -m pytest -q -n 2 --dist loadfile --no-loadscope-reorder

clean:
	rm -rf $(VENV) $(LEROBOT_NEW_VENV)
