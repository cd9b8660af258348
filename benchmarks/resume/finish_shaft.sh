#!/usr/bin/env bash
# Finishes the shaft's 256 x 6 retraining (shaft_256x6.md) and reruns what the new networks and the renewed
# test seeds (6101-6103) change, one step after another so that each has both cores. Removed with this folder
# in the commit that ships the networks. Run from the repository root: bash benchmarks/resume/finish_shaft.sh
set -euo pipefail
step() { echo "=== $(date -u +%H:%M) $*"; "$@"; }
for method in supervised-edge supervised-mask self-supervised; do
  run=runs/shipped/run_shaft_$method
  if [ ! -e "$run/train_state.pt" ]; then mkdir -p "$run" && cp benchmarks/resume/shaft_$method/* "$run/"; fi
done
step python benchmarks/train_shipped.py --objects shaft --methods supervised-edge supervised-mask self-supervised \
  --checkpoint-every 500
step python benchmarks/make_keypoint_noise.py shaft/supervised-edge shaft/supervised-mask shaft/self-supervised
step python benchmarks/check_shipped.py
step python benchmarks/bench_grasp.py --work runs/bench_grasp --only tracking
step python benchmarks/bench_grasp.py --work runs/bench_grasp --only grasp --objects shaft
step python benchmarks/bench_pose.py --work runs/bench_pose --objects shaft
echo "=== $(date -u +%H:%M) done"
