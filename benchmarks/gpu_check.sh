#!/usr/bin/env bash
# One prepared run on a lent GPU machine (docs/training.md, items 25 and 40), in one device
# call: the wheels it lacks, then benchmarks/throughput.py (the batched pipelines and detect
# on the GPU), benchmarks/stages.py (the batched pipelines stage by stage),
# tests/test_gpu.py (the GPU against the CPU) and, with TRAIN_CHECK=1, a 3-minute training
# check (configs/gpu_check.yaml). What they print and write comes back under $OUT;
# docs/benchmarks.md's new sections are in $OUT/benchmarks.md.
#
# Here first (it needs the package index): make gpu-wheels. Then, with the device tool:
#   run(command="bash benchmarks/gpu_check.sh", carry=[".whl"], timeout_s=600)
# At most 9 minutes of the machine's 10 a call (each part has its own time limit; the
# training check adds 4). A dry run on a CPU (the flow, not the figures):
# PYTHON=.venv/bin/python WHEELS=<wheels for its Python> THROUGHPUT_ARGS="--images 8
# --batches 1 4 --detect-images 0" STAGES_ARGS="--batch 4 --images 4" TRAIN_CHECK=1
# TRAIN_ARGS="--trainer.accelerator cpu --trainer.max_steps 4 ..." bash benchmarks/gpu_check.sh
# (it rewrites docs/benchmarks.md's cpu sections: git checkout docs/benchmarks.md after)
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
timeout 330 "$PYTHON" -m benchmarks.throughput --precision fp32 --threads 8 \
    --batches 1 256 1024 2048 ${THROUGHPUT_ARGS:-} > "$OUT/throughput.txt" 2>&1
echo "throughput: exit $?" | tee -a "$OUT/throughput.txt"
# shellcheck disable=SC2086
timeout 100 "$PYTHON" -m benchmarks.stages --threads 8 ${STAGES_ARGS:-} > "$OUT/stages.txt" 2>&1
echo "stages: exit $?" | tee -a "$OUT/stages.txt"
cp docs/benchmarks.md "$OUT/benchmarks.md"

timeout 100 "$PYTHON" -m pytest -q -p no:cacheprovider tests/test_gpu.py > "$OUT/tests.txt" 2>&1
echo "tests: exit $?" | tee -a "$OUT/tests.txt"

if [ -n "${TRAIN_CHECK:-}" ]; then
    start=$(date +%s)
    # shellcheck disable=SC2086
    timeout 230 "$PYTHON" -m train fit -c configs/gpu.yaml -c configs/gpu_check.yaml \
        ${TRAIN_ARGS:-} > "$OUT/train.txt" 2>&1
    echo "train: exit $?, $(( $(date +%s) - start )) s with start-up" | tee -a "$OUT/train.txt"
    cp runs/gpu_check/csv/version_0/metrics.csv "$OUT/train_metrics.csv" 2>/dev/null
    ls -la runs/gpu_check >> "$OUT/train.txt" 2>&1
fi
tail -n 5 "$OUT"/*.txt
