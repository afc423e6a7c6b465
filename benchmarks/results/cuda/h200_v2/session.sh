#!/bin/bash
# One device call: the suite's redkitchen comparison of the two presets on CUDA, then the step profile.
T0=$SECONDS
log() { echo "[$(date +%T) +$((SECONDS - T0))s] $*" | tee -a $OUT/session.log; }
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .gpu/whl/*.whl || exit 1
export PYTHONPATH=/tmp/site:$PWD/.gpu/lpips:$PWD PYTHONUNBUFFERED=1
log "$(nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader) torch $(python3 -c 'import torch; print(torch.__version__)')"
log suite start
timeout 380 python3 benchmarks/suite.py --out /tmp/gpu --budget 120 --eval-at 30,60,90 --scenes redkitchen \
  --redkitchen .gpu/redkitchen --configs defaults,paper-preset > $OUT/suite.txt 2>&1
log "suite rc $?"
(cd /tmp/gpu && tar czf $OUT/runs.tgz $(find . -name '*.json' -size -20M))
LEFT=$((540 - (SECONDS - T0)))
log "profile start, $LEFT s left"
timeout $LEFT python3 benchmarks/step_profile.py .gpu/redkitchen --downscale 2 --steps 30 --warm 8 --trace 4 \
  --config paper='{"preset": "paper"}' \
  --config paper-plain='{"preset": "paper", "pose_refinement": "none", "appearance": "none"}' \
  --config paper-uniform='{"preset": "paper", "sampler": "uniform", "depth_loss": false, "pose_refinement": "none", "appearance": "none"}' \
  --config cpu='{}' \
  --json $OUT/profile.json > $OUT/profile.txt 2>&1
log "profile rc $?"
