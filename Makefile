# Setup is idempotent: each target installs what is missing, then runs.
#   make quickstart   record demos, train and evaluate a small act_modified, print stage tables
#   make test         lint (ruff), then the test suite (default run, no GPU, 11-25 minutes on 2 cores)
SHELL := /bin/bash
VENV := .venv
STAMP := $(VENV)/.installed
export MUJOCO_GL ?= egl
export HF_HUB_OFFLINE ?= 1
export TOKENIZERS_PARALLELISM ?= false

# Python 3.12: from PATH, else pyenv's.
PYTHON312 := $(shell for p in python3.12 $$HOME/.pyenv/versions/3.12*/bin/python3.12 /usr/local/bin/python3.12 /usr/bin/python3.12; do \
	$$p -c 'import sys; assert sys.version_info[:2] == (3, 12)' >/dev/null 2>&1 && { echo $$p; break; }; done)

.PHONY: setup system-deps quickstart lint test test-slow bench

setup: system-deps $(STAMP)

# Headless MuJoCo rendering needs EGL with Mesa's software driver; torchcodec (LeRobot's video
# decoder) needs FFmpeg's shared libraries, else LeRobot falls back to slower PyAV with a traceback.
# The report test opens the HTML report in Debian's headless Chromium through its ChromeDriver.
SYSTEM_LIBS := libEGL_mesa.so.0 libavdevice.so.59 libavfilter.so.8
SYSTEM_BINS := chromium chromedriver
SYSTEM_PKGS := libegl1 libegl-mesa0 libgl1-mesa-dri libgl1 libavutil57 libavcodec59 libavformat59 libavdevice59 libavfilter8 libswscale6 libswresample4 chromium chromium-driver
system-deps:
	@missing=0; for lib in $(SYSTEM_LIBS); do ldconfig -p | grep -q "$$lib" || missing=1; done; \
	for bin in $(SYSTEM_BINS); do command -v $$bin >/dev/null || missing=1; done; \
	if [ $$missing = 1 ]; then \
		echo "Installing system libraries: $(SYSTEM_PKGS)"; \
		apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $(SYSTEM_PKGS) >/dev/null; \
	fi

$(STAMP): pyproject.toml
	@test -n "$(PYTHON312)" || { echo "Python 3.12 not found (looked on PATH and in ~/.pyenv/versions)"; exit 1; }
	test -x $(VENV)/bin/python || $(PYTHON312) -m venv $(VENV)
	$(VENV)/bin/python -m pip install -q --upgrade pip
	$(VENV)/bin/python -m pip install -q -e ".[test]"
	touch $(STAMP)

quickstart: setup
	$(VENV)/bin/condground quickstart

# Lint first: it takes a second and fails CI on a new violation before the long test run.
lint: setup
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .

# One pytest worker per logical CPU (at most 4), a test file per worker: the suite keeps one core busy on its
# own, and a file's module fixtures (datasets, checkpoints) are built once. Wall-clock rate checks (marked
# realtime: the real-time twin, streams across processes) run afterwards on a quiet machine: beside a
# training they measure the load.
test: lint
	$(VENV)/bin/python -m pytest -q --numprocesses=logical --maxprocesses=4 --dist=loadfile --durations=25 \
		-m "not slow and not realtime"
	$(VENV)/bin/python -m pytest -q -m "realtime and not slow"

test-slow: setup
	$(VENV)/bin/python -m pytest -q -m slow

bench: setup
	$(VENV)/bin/condground bench
