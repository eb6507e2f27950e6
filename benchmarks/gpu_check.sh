#!/usr/bin/env bash
# One prepared run on a lent GPU machine (docs/training.md, item 25), in one device call:
# the wheels it lacks, then benchmarks/throughput.py (the batched pipeline and detect on the
# GPU), tests/test_gpu.py (the GPU against the CPU) and a 3-minute training check
# (configs/gpu_check.yaml). What they print and write comes back under $OUT;
# docs/benchmarks.md's new section is in $OUT/benchmarks.md.
#
# Here first (it needs the package index): make gpu-wheels. Then, with the device tool:
#   run(command="bash benchmarks/gpu_check.sh", carry=[".whl"], timeout_s=600)
# At most 9 1/2 minutes of the machine's 10 a call (each part has its own time limit).
# A dry run on a CPU (the flow, not the figures): PYTHON=.venv/bin/python WHEELS=<wheels for
# its Python> THROUGHPUT_ARGS="--images 8 --batches 4 --detect-images 0"
# TRAIN_ARGS="--trainer.accelerator cpu --trainer.max_steps 4 ..." bash benchmarks/gpu_check.sh
set -uo pipefail
OUT=${OUT:-/tmp/gpu_check}
PYTHON=${PYTHON:-python3}
mkdir -p "$OUT"
"$PYTHON" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
    --target /tmp/site "${WHEELS:-.whl}"/*.whl || exit 1
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1
{
    nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv
    "$PYTHON" -c "import torch; print('torch', torch.__version__, torch.cuda.is_available()
        and torch.cuda.get_device_name())"
    nproc
} 2>&1 | tee "$OUT/device.txt"

# shellcheck disable=SC2086  # the optional arguments split into words
timeout 240 "$PYTHON" -m benchmarks.throughput --precision fp32 bf16 --threads 8 \
    ${THROUGHPUT_ARGS:-} > "$OUT/throughput.txt" 2>&1
echo "throughput: exit $?" | tee -a "$OUT/throughput.txt"
cp docs/benchmarks.md "$OUT/benchmarks.md"

timeout 100 "$PYTHON" -m pytest -q -p no:cacheprovider tests/test_gpu.py > "$OUT/tests.txt" 2>&1
echo "tests: exit $?" | tee -a "$OUT/tests.txt"

start=$(date +%s)
# shellcheck disable=SC2086
timeout 230 "$PYTHON" -m train fit -c configs/gpu.yaml -c configs/gpu_check.yaml \
    ${TRAIN_ARGS:-} > "$OUT/train.txt" 2>&1
echo "train: exit $?, $(( $(date +%s) - start )) s with start-up" | tee -a "$OUT/train.txt"
cp runs/gpu_check/csv/version_0/metrics.csv "$OUT/train_metrics.csv" 2>/dev/null
ls -la runs/gpu_check >> "$OUT/train.txt" 2>&1
tail -n 5 "$OUT/throughput.txt" "$OUT/tests.txt" "$OUT/train.txt"
