# Two entry points for a fresh machine: `make demo` (main job) and `make test`.
PYTHON ?= python3.11
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: install demo test lint bench train-hour train-hardware gpu-wheels clean

$(STAMP): pyproject.toml constraints.txt
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	$(BIN)/pip install -q -c constraints.txt -e '.[dev]'
	touch $(STAMP)

install: $(STAMP)

demo: $(STAMP)
	$(BIN)/cupnet demo

lint: $(STAMP)
	$(BIN)/ruff check .

test: lint
	$(BIN)/python -m pytest

bench: $(STAMP)
	$(BIN)/python -m benchmarks.numsim
	$(BIN)/python -m benchmarks.solver_speed
	$(BIN)/python -m benchmarks.synth
	$(BIN)/python -m benchmarks.model
	$(BIN)/python -m benchmarks.predict

# The one-hour CPU recipe (docs/training.md, items 46-47), 58-59 min on this 2-core machine:
# two chains of one-thread processes side by side (make -j2), A the U-Nets then the locator,
# B the fine then the coarse rim network; the merge puts B's rim networks into A's export, and
# the locator trains on alone for the rest of the hour. The model ends in
# runs/hour/cupnet.safetensors, with the shipped inference settings beside it (they were tuned
# on the shipped weights, items 6-35). Each stage's whole output is printed when it ends (-O).
# HOUR_ARGS goes to every stage, e.g. HOUR_ARGS="--seed_everything 1 --data.train_seed 100".
TRAIN := $(BIN)/python -m train fit -c configs/cpu.yaml
HOUR_ARGS ?=
train-hour: $(STAMP)
	@echo "train-hour: chain A (U-Nets, then locator) beside chain B (fine rim, then coarse" \
		"rim), about 44 min, each stage's output printed when it ends; then the locator alone"
	$(MAKE) -j2 -O hour-merged
	$(TRAIN) -c configs/cpu_locator2.yaml -c configs/hour_final.yaml $(HOUR_ARGS)
	cp cupnet/assets/cupnet_default.json runs/hour/cupnet.json

.PHONY: hour-unet hour-rim hour-locator hour-coarse hour-merged
hour-unet: $(STAMP)
	$(TRAIN) -c configs/hour_unet.yaml $(HOUR_ARGS)
hour-rim: $(STAMP)
	$(TRAIN) -c configs/cpu_rim.yaml -c configs/hour_rim.yaml $(HOUR_ARGS)
hour-locator: hour-unet
	$(TRAIN) -c configs/cpu_locator2.yaml -c configs/hour_locator.yaml $(HOUR_ARGS)
# After hour-rim too, though it takes none of its weights: one chain a core.
hour-coarse: hour-unet hour-rim
	$(TRAIN) -c configs/cpu_rim.yaml -c configs/cpu_coarse.yaml -c configs/hour_coarse.yaml \
		$(HOUR_ARGS)
hour-merged: hour-locator hour-coarse
	$(BIN)/python -m train.merge runs/hour_locator/cupnet.safetensors \
		--take rim=runs/hour_rim/cupnet.safetensors \
		--take coarse_rim=runs/hour_coarse/cupnet.safetensors \
		--out runs/hour_merged/cupnet.safetensors

# Surgical hardware (docs/training.md, items 63-64), the shipped weights' last stage: the
# locator and fine rim network shipped before it fine-tuned side by side, about 30 min, on
# images with screws and the cup's inserter, merged into runs/hardware/cupnet.safetensors with
# the shipped settings beside it (the weights now in cupnet/assets/). The weights it starts
# from are taken out of git, as shipped at d89edca (a shallow clone lacks them), with their
# settings beside them: without those, load_model builds the default architecture, which
# refuses the rim networks' weights.
PRE_HARDWARE := runs/pre_hardware/cupnet.safetensors
train-hardware: $(STAMP) $(PRE_HARDWARE)
	$(MAKE) -j2 -O hardware-locator hardware-rim
	$(BIN)/python -m train.merge runs/hardware_locator/cupnet.safetensors \
		--take rim=runs/hardware_rim/cupnet.safetensors --out runs/hardware/cupnet.safetensors
	cp cupnet/assets/cupnet_default.json runs/hardware/cupnet.json

$(PRE_HARDWARE):
	mkdir -p $(@D)
	git show d89edca:cupnet/assets/cupnet_default.json > $(basename $@).json
	git show d89edca:cupnet/assets/cupnet_default.safetensors > $@.part
	mv $@.part $@

.PHONY: hardware-locator hardware-rim
hardware-locator: $(STAMP) $(PRE_HARDWARE)
	$(TRAIN) -c configs/cpu_locator2.yaml -c configs/hardware_locator.yaml $(HOUR_ARGS)
hardware-rim: $(STAMP) $(PRE_HARDWARE)
	$(TRAIN) -c configs/cpu_rim.yaml -c configs/hardware_rim.yaml $(HOUR_ARGS)

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
