# Two entry points for a fresh machine: `make demo` (main job) and `make test`.
PYTHON ?= python3.11
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: install demo test lint bench train-hour gpu-wheels clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	$(BIN)/pip install -q -e '.[dev]'
	touch $(STAMP)

install: $(STAMP)

demo: $(STAMP)
	$(BIN)/cupnet demo

test: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/python -m pytest

bench: $(STAMP)
	$(BIN)/python -m benchmarks.numsim
	$(BIN)/python -m benchmarks.solver_speed
	$(BIN)/python -m benchmarks.synth
	$(BIN)/python -m benchmarks.model
	$(BIN)/python -m benchmarks.predict

# The one-hour CPU recipe (docs/training.md, item 36): four stages, each from the weights the
# one before exported, 59 min on this 2-core machine; the model ends in
# runs/hour_locator/cupnet.safetensors, with the shipped inference settings beside it (they
# were tuned on the shipped weights, items 6-35).
TRAIN := $(BIN)/python -m train fit -c configs/cpu.yaml
train-hour: $(STAMP)
	$(TRAIN) -c configs/hour_unet.yaml
	$(TRAIN) -c configs/cpu_rim.yaml -c configs/hour_rim.yaml
	$(TRAIN) -c configs/cpu_rim.yaml -c configs/cpu_coarse.yaml -c configs/hour_coarse.yaml
	$(TRAIN) -c configs/cpu_locator2.yaml -c configs/hour_locator.yaml
	cp cupnet/assets/cupnet_default.json runs/hour_locator/cupnet.json

# A lent GPU machine reaches no package index and lacks these (docs/training.md, item 25):
# their wheels, for its Python 3.12, go into .whl/ for benchmarks/gpu_check.sh to install.
GPU_WHEELS := kornia==0.9.0 kornia_rs==0.2.0 segmentation_models_pytorch==0.6.0 \
	pydicom==3.0.2 jsonargparse==4.53.0 docstring_parser==0.18.0 typeshed_client==2.15.0 \
	timm==1.0.31
gpu-wheels: $(STAMP)
	$(BIN)/pip download -q --no-deps --only-binary=:all: --python-version 3.12 \
		--implementation cp --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 \
		--platform manylinux2014_x86_64 -d .whl $(GPU_WHEELS)

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache
