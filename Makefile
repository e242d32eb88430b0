# Quickstart: `make demo` (set up + main job) and `make test` (set up + tests).
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
WOMD ?= ../shared/data/womd/motion_data_one_example.tfrecord
DEMO_OUT ?= runs/demo
PYTEST_WORKERS ?= 2
# Byte-code caching on even where the environment turns it off: the install skips byte-compiling
# (below), so without it every process (each test worker, the notebook's kernel) would compile
# TensorFlow's and JAX's sources again on import.
export PYTHONDONTWRITEBYTECODE :=

.PHONY: install lock demo test notebook bench data train clean wosac-env

# Installs the exact versions of requirements.lock (the ones docs/ numbers were measured with),
# then the package itself without resolving anything again. --no-compile: byte-compiling every
# module of TensorFlow, JAX and SciPy took 23 of the install's 54 s on 2 cores; Python compiles
# the few it imports on first use.
$(VENV)/.installed: pyproject.toml requirements.lock
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q --no-compile -r requirements.lock
	$(PY) -m pip install -q --no-deps -e .
	touch $@

# Re-resolves requirements.lock from pyproject.toml in a clean venv (commit the result).
lock:
	rm -rf .lockenv && $(PYTHON) -m venv .lockenv
	.lockenv/bin/pip install -q --upgrade pip && .lockenv/bin/pip install -q '.[dev]'
	.lockenv/bin/pip freeze --exclude-editable | grep -v '^pcdiff_jax' > requirements.lock
	rm -rf .lockenv

install: $(VENV)/.installed

demo: install   # scenes -> both training stages -> closed-loop table of ours and the baselines
	$(PY) -m experiments.demo --out $(DEMO_OUT)

# `make test`: every test not marked slow (the end-to-end runs), for a fast local loop; with CI=true or 1
# (CI's .ci/run calls make test) and in `make test-all`, the whole suite (docs/DEVELOPING.md).
# PYTEST_ARGS: extra pytest arguments, e.g. PYTEST_ARGS="--durations=30" or "-k policy".
PYTEST_ARGS ?=
PYTEST = $(PY) -m pytest -q -n $(PYTEST_WORKERS) --dist loadfile --no-loadscope-reorder $(PYTEST_ARGS)
.PHONY: test-all
test: install
	$(PYTEST) $(if $(filter true 1,$(CI)),,-m "not slow")

test-all: install
	$(PYTEST)

data: install   # the built-in dataset (docs/DATA.md): 2000 train + 200 val scenes in data/synth
	$(PY) -m experiments.make_data --out data/synth --num-train 2000 --num-val 200 --seed 0

TRAIN_DIR ?= runs/train
FINETUNE_ARGS ?= --rounds 7 --scenes 300 --steps 600
LANE_ARGS ?= --lane-inputs --rounds 3 --scenes 300 --first-scene 3300 --steps 1000
MORE_ARGS ?= --rounds 4 --scenes 300 --first-scene 4000 --steps 1000
SIMPL_AR_ARGS ?= --lane-inputs --rounds 1 --scenes 150 --first-scene 6000 --encoder-steps 1500 \
	--encoder-learning-rate 5e-4 --mix 0.3
LANE_ENCODER_ARGS ?= --rounds 2 --scenes 300 --first-scene 5200 --steps 1000
V10_ARGS ?= --rounds 2 --scenes 150 --steps 800
V11_ARGS ?= --rounds 3 --scenes 150 --steps 800
# The shipped model's recipe from scratch (checkpoints/*/MODEL_CARD.md): 10k scenes, both stages,
# on-policy fine-tuning rounds, lane-input rounds (v6), four more rounds (v7), the SIMPL-AR baseline's own
# encoder (lane inputs + rounds on its own closed loop), ours re-trained on that encoder (v8), two
# rounds on 600 other scenes (v10), the proposal head refit on queued traffic and v8's denoiser
# re-trained on it (v11), export. Each command resumes where it stopped when re-run.
train: install
	$(PY) -m experiments.make_data --out data/synth10k --num-train 10000 --num-val 200 --seed 0 --shard-size 500
	$(PY) -m experiments.train --stage encoder --config cpu --data 'data/synth10k/train-*' --workdir $(TRAIN_DIR) --steps 1800
	$(PY) -m experiments.train --stage diffusion --config cpu --data 'data/synth10k/train-*' --workdir $(TRAIN_DIR)
	$(PY) -m experiments.finetune --from $(TRAIN_DIR) --data 'data/synth10k/train-*' --workdir $(TRAIN_DIR)-onpolicy \
	  --cache-dir $(TRAIN_DIR)/cache $(FINETUNE_ARGS)
	$(PY) -m experiments.finetune --from $(TRAIN_DIR)-onpolicy --data 'data/synth10k/train-*' --workdir $(TRAIN_DIR)-lanes \
	  --cache-dir $(TRAIN_DIR)/cache $(LANE_ARGS)
	$(PY) -m experiments.finetune --from $(TRAIN_DIR)-lanes --data 'data/synth10k/train-*' --workdir $(TRAIN_DIR)-more \
	  --cache-dir $(TRAIN_DIR)/cache $(MORE_ARGS)
	$(PY) -m experiments.finetune --policy simpl-ar --from $(TRAIN_DIR)-more --data 'data/synth10k/train-*' \
	  --workdir $(TRAIN_DIR)-simpl-ar --cache-dir $(TRAIN_DIR)/cache $(SIMPL_AR_ARGS)
	$(PY) -m experiments.finetune --from $(TRAIN_DIR)-simpl-ar --encoder-from $(TRAIN_DIR)-simpl-ar \
	  --data 'data/synth10k/train-*' --workdir $(TRAIN_DIR)-v8 --cache-dir $(TRAIN_DIR)/cache $(LANE_ENCODER_ARGS)
	$(PY) -m experiments.make_data --out data/synth600 --num-train 600 --num-val 0 --seed 0
	$(PY) -m experiments.finetune --from $(TRAIN_DIR)-v8 --data 'data/synth600/train-*' --workdir $(TRAIN_DIR)-v10 \
	  --cache-dir $(TRAIN_DIR)/cache600 $(V10_ARGS)
	$(PY) -m experiments.make_data --out data/synthq --num-train 1200 --num-val 200 --seed 0 --warmup-seconds 30
	$(PY) -m experiments.refit_head --from $(TRAIN_DIR)-v10 --data 'data/synthq/train-*' 'data/synth600/train-*' \
	  --steps 8000 --workdir $(TRAIN_DIR)-v11-head
	$(PY) -m experiments.finetune --from $(TRAIN_DIR)-v8 --encoder-from $(TRAIN_DIR)-v11-head \
	  --data 'data/synthq/train-*' 'data/synth600/train-*' --workdir $(TRAIN_DIR)-v11 --cache-dir $(TRAIN_DIR)/cacheq $(V11_ARGS)
	$(PY) -m experiments.export --workdir $(TRAIN_DIR)-v11 --out $(TRAIN_DIR)-model --simpl-ar-from $(TRAIN_DIR)-v10

# Re-executes notebooks/quickstart.ipynb in place on the shipped model (commit the outputs).
notebook: install
	$(VENV)/bin/jupyter-execute --inplace notebooks/quickstart.ipynb

bench: install
	$(PY) -m experiments.bench --scenarios $(WOMD)

# Waymo's official sim agents evaluator (`python -m experiments.wosac --score`) in its own venv:
# it pins Python 3.10 and TensorFlow 2.12, which cannot share ours. PYTHON310= names another
# interpreter; WOSAC_LOCK= another lock (wosac-requirements.lock: pip freeze of the first install).
PYTHON310 ?= $(firstword $(wildcard $(shell pyenv root 2>/dev/null)/versions/3.10*/bin/python3.10) $(shell command -v python3.10 2>/dev/null))
WOSAC_VENV ?= .wosac-venv
WOSAC_LOCK ?= wosac-requirements.lock
$(WOSAC_VENV)/.installed: $(WOSAC_LOCK)
	@test -n "$(PYTHON310)" && test -x "$(PYTHON310)" || { echo "make wosac-env: no Python 3.10 found (looked for \
	$$(pyenv root)/versions/3.10*/bin/python3.10 and python3.10 on PATH); install one (pyenv install 3.10) or pass \
	PYTHON310=/path/to/python3.10" >&2; exit 2; }
	rm -rf $(WOSAC_VENV) && $(PYTHON310) -m venv $(WOSAC_VENV)
	$(WOSAC_VENV)/bin/python -m pip install -q --upgrade pip
	$(WOSAC_VENV)/bin/python -m pip install -q --no-compile -r $(WOSAC_LOCK)
	$(WOSAC_VENV)/bin/python -c "from waymo_open_dataset.wdl_limited.sim_agents_metrics import metrics"
	touch $@

wosac-env: $(WOSAC_VENV)/.installed

clean:
	rm -rf $(VENV) .cache runs
