#!/bin/bash
# Issue #45's GPU check (docs/cuda.md, "The GPU check"): from the repository root of a bare GPU machine that has
# Python 3.12 with CUDA PyTorch and the bundle of scripts/gpu_bundle.py carried as .gpu, install the bundled wheels
# (no package index) and run benchmarks/gpu_check.py on redkitchen: the step profile with the voxnerf sampler's
# octree misses gathered and masked, training throughput of the cpu and paper presets, render latency per
# 320x240 and 640x480 view. Sized for under 9 minutes from a bare machine (an estimate: not yet timed on a GPU); the
# Python part is cut at CHECK_TIMEOUT seconds and keeps what it finished.
#
#   bash scripts/gpu_check.sh [OUT_DIR]        # OUT_DIR defaults to $OUT
#
# Environment (defaults): PYTHON (python3), BUNDLE (.gpu), SCENE ($BUNDLE/redkitchen), DEVICE (auto),
# DOWNSCALE (2), STEPS (30), WARM (8), SYNC_STEPS (4), TRAIN_SECONDS (30), RENDERS (8), PRESETS (cpu,paper),
# OVERRIDES ({}: TrainConfig fields for every run, e.g. {"compile": false} in a quick dry run), CHECK_TIMEOUT (480).
# Writes OUT_DIR/gpu_check.json, OUT_DIR/gpu_check.md (the tables) and OUT_DIR/log.
set -u
out=${1:-${OUT:?usage: scripts/gpu_check.sh OUT_DIR (or set OUT)}}
python=${PYTHON:-python3}
bundle=${BUNDLE:-.gpu}
scene=${SCENE:-$bundle/redkitchen}
overrides=${OVERRIDES-}
[ -n "$overrides" ] || overrides='{}'
start=$(date +%s)
mkdir -p "$out"
for needed in "$bundle/whl" "$bundle/lpips" "$scene/transforms.json"; do
  if [ ! -e "$needed" ]; then
    echo "scripts/gpu_check.sh: $needed is missing (make the bundle: .venv/bin/python scripts/gpu_bundle.py" \
      "../shared/data/redkitchen $bundle)" >&2
    exit 2
  fi
done
site=$(mktemp -d /tmp/gpu_check_site.XXXXXX)
"$python" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target "$site" "$bundle"/whl/*.whl \
  2>&1 | tail -3
export PYTHONPATH=$site:$PWD/$bundle/lpips:$PWD PYTHONUNBUFFERED=1
nvidia-smi -L 2>/dev/null || echo "no nvidia-smi"
echo "cpus: $(nproc)"
"$python" -c "import torch, voxnerf; print('torch', torch.__version__, 'cuda', torch.cuda.is_available())"
echo "set-up took $(( $(date +%s) - start )) s"
timeout "${CHECK_TIMEOUT:-480}" "$python" benchmarks/gpu_check.py "$scene" --out "$out" --device "${DEVICE:-auto}" \
  --downscale "${DOWNSCALE:-2}" --steps "${STEPS:-30}" --warm "${WARM:-8}" --count-syncs "${SYNC_STEPS:-4}" \
  --train-seconds "${TRAIN_SECONDS:-30}" --renders "${RENDERS:-8}" --presets "${PRESETS:-cpu,paper}" \
  --overrides "$overrides" 2>&1 \
  | tee "$out/log"
rc=${PIPESTATUS[0]}
echo "rc=$rc total $(( $(date +%s) - start )) s"
nvidia-smi --query-gpu=name,memory.used --format=csv 2>/dev/null || true
exit "$rc"
