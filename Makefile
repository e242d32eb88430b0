# Quickstart: `make demo` (set up + main job) and `make test` (set up + tests).
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
WOMD ?= ../shared/data/womd/motion_data_one_example.tfrecord
DEMO_OUT ?= runs/demo
PYTEST_WORKERS ?= 2

.PHONY: install demo test bench clean

$(VENV)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e '.[dev]'
	touch $@

install: $(VENV)/.installed

demo: install
	$(PY) -m experiments.rollout --scenarios $(WOMD) --method cv --out $(DEMO_OUT) --gifs 1

test: install
	$(PY) -m pytest -q -n $(PYTEST_WORKERS)

bench: install
	$(PY) -m experiments.bench --scenarios $(WOMD)

clean:
	rm -rf $(VENV) .cache runs
