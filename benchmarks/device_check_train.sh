#!/usr/bin/env bash
# GPU check of DON training, for a machine with a CUDA GPU and don_gym installed (pip install -e ".[test]"),
# run from anywhere: bash benchmarks/device_check_train.sh
#  1. the CUDA tests of tests/test_train.py (mixed precision against fp32; skipped without a GPU);
#  2. bench_train.py's gpu part: training images/s of resnet-lite and resnet34 on whole 640x480 frames,
#     fp32 vs mixed precision, one process, and the share of step time spent waiting for data
#     (target < 10%), recorded in the "train-gpu" section of benchmarks/RESULTS.md.
# About 3-5 minutes on one H200 (most of it building the 640x480 dataset and cuDNN autotuning).
# Where $OUT is set (the device runner), RESULTS.md is copied there so the figures come back.
set -euo pipefail
cd "$(dirname "$0")/.."
python -c 'import torch, sys; sys.exit(0 if torch.cuda.is_available() else "no CUDA GPU visible to torch")'
OMP_NUM_THREADS=1 python -m pytest -q -rs tests/test_train.py -k cuda
python benchmarks/bench_train.py --parts gpu "$@"
if [ -n "${OUT:-}" ]; then cp benchmarks/RESULTS.md "$OUT/RESULTS.md"; fi
