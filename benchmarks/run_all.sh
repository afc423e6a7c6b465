#!/usr/bin/env bash
# Every benchmark whose table of record docs/benchmarks.md keeps, one after the other (never two at once: each run needs the whole
# machine), from a fresh clone: scene generation, the nerfstudio peer, error against run time with the seven
# configurations and the peer, the samples-per-ray and prior-noise sweeps, and the voxnerf run at the peer's
# number of rays seen.
#
#   make bench OUT=DIR        # or: benchmarks/run_all.sh [--quick] DIR [BUDGET] [SWEEP_BUDGET]
#
# --quick: every script's CI-sized smoke mode on the tiny room (the peer, if installed, trains 30 s): checks
# this script end to end in a few minutes, not quality.
# BUDGET (default 300) is the wall-clock budget of each error-against-run-time configuration, of the peer and
# of each prior-noise setting; SWEEP_BUDGET (default 120) that of each samples-per-ray pair. The peer needs its
# own venv (about 8 GB): benchmarks/peer/install_nerfstudio.sh; without it the peer steps are skipped, and the script says so.
# PEER_VENV overrides its place (default /work/peer/venv).
set -euo pipefail
QUICK=()
if [ "${1:-}" = "--quick" ]; then
    QUICK=(--quick)
    shift
fi
OUT=${1:?usage: benchmarks/run_all.sh OUT [BUDGET] [SWEEP_BUDGET]}
BUDGET=${2:-$([ ${#QUICK[@]} -gt 0 ] && echo 30 || echo 300)}
SWEEP_BUDGET=${3:-$([ ${#QUICK[@]} -gt 0 ] && echo 30 || echo 120)}
PEER_VENV=${PEER_VENV:-/work/peer/venv}
ROOT=$(cd "$(dirname "$0")/.." && pwd)
PY="$ROOT/.venv/bin/python"
mkdir -p "$OUT"
OUT=$(cd "$OUT" && pwd)
SCENE="$OUT/evr/scene"
cd "$ROOT"
log() { echo "$(date -u +%H:%M:%S) $*"; }

log "scene: $SCENE"
(cd benchmarks && "$PY" -c "import sys; from pathlib import Path; from error_vs_runtime import make_scene; \
make_scene('room', Path(sys.argv[1]), sys.argv[2] == 'quick')" "$OUT/evr" "${QUICK[0]:+quick}")

PEER=()
if [ -x "$PEER_VENV/bin/python" ] && "$PEER_VENV/bin/python" -c "import nerfstudio" 2>/dev/null; then
    log "peer: nerfacto, budget $BUDGET s (log: $OUT/nerfacto.log)"
    "$PEER_VENV/bin/python" benchmarks/peer/nerfacto_run.py "$SCENE" --budget "$BUDGET" --eval-at "$BUDGET" \
        --out "$OUT/nerfacto" > "$OUT/nerfacto.log" 2>&1
    "$PY" benchmarks/peer/score_renders.py "$SCENE" --out "$OUT/nerfacto"
    PEER=(--peer "nerfacto=$OUT/nerfacto")
else
    log "peer skipped: no nerfstudio in $PEER_VENV (run benchmarks/peer/install_nerfstudio.sh)"
fi

log "error against run time, budget $BUDGET s per configuration"
EVAL_AT=$("$PY" -c "import sys; b = float(sys.argv[1]); print(','.join(f'{t:g}' for t in (60, 120, b) if t <= b))" \
    "$BUDGET")
"$PY" benchmarks/error_vs_runtime.py --scene room --budget "$BUDGET" --eval-at "$EVAL_AT" "${PEER[@]}" \
    "${QUICK[@]}" --out "$OUT/evr"

log "samples per ray, budget $SWEEP_BUDGET s per pair"
"$PY" benchmarks/samples_sweep.py --scene "$SCENE" --budget "$SWEEP_BUDGET" "${QUICK[@]}" --out "$OUT/samples"

log "prior noise, budget $BUDGET s per setting"
"$PY" benchmarks/prior_noise_sweep.py --scene "$SCENE" --budget "$BUDGET" "${QUICK[@]}" --out "$OUT/noise"

if [ ${#PEER[@]} -gt 0 ]; then
    # Rays per voxnerf step (random rays + smoothness patches) as the voxnerf configuration's run reported them.
    REPORT="$OUT/evr/runs/voxnerf/report.json"
    [ -f "$REPORT" ] || { echo "run_all.sh: $REPORT: missing (the voxnerf run did not finish)" >&2; exit 1; }
    STEP_RAYS=$("$PY" -c "import json, sys; print(json.load(open(sys.argv[1]))['throughput']['rays_per_step'])" \
        "$REPORT")
    ITERS=$("$PY" -c "import csv, math, sys; row = list(csv.DictReader(open(sys.argv[1])))[-1]; \
print(math.ceil(int(row['rays_seen']) / int(sys.argv[2])))" "$OUT/nerfacto/timeline.csv" "$STEP_RAYS")
    log "voxnerf at the peer's rays seen: $ITERS steps of $STEP_RAYS rays"
    "$PY" -m voxnerf train "$SCENE" --out "$OUT/equal_rays" --max-iters "$ITERS" --restart \
        $([ ${#QUICK[@]} -gt 0 ] && echo --no-compile)
fi
REDKITCHEN=${REDKITCHEN:-$ROOT/../shared/data/redkitchen}
RK=()
[ -f "$REDKITCHEN/transforms.json" ] && [ ${#QUICK[@]} -eq 0 ] && RK=(--redkitchen "$REDKITCHEN")
# The suite's baseline rows only (every configuration of benchmarks/suite.py on every scene is hours more);
# SUITE_CONFIGS overrides the list.
SUITE_CONFIGS=${SUITE_CONFIGS:-defaults,previous-defaults,occgrid-seeded,occgrid-density}
log "tuning suite ($SUITE_CONFIGS), budget $SWEEP_BUDGET s per run (${RK[*]:-no redkitchen})"
if [ ${#QUICK[@]} -gt 0 ]; then
    "$PY" benchmarks/suite.py --quick --out "$OUT/suite"
else
    "$PY" benchmarks/suite.py --budget "$SWEEP_BUDGET" "${RK[@]}" --configs "$SUITE_CONFIGS" --out "$OUT/suite"
fi
log "done: tables in $OUT/evr/table.md, $OUT/samples/samples.md, $OUT/noise/prior_noise.md, $OUT/suite/table.md"
