#!/usr/bin/env bash
# Install nerfstudio 1.1.5 (the peer for the error-against-run-time benchmark) into its own venv, outside the
# project: it pulls its own torch (CUDA build, runs on CPU here) and torchvision, about 8 GB.
# Usage: benchmarks/peer/install_nerfstudio.sh [VENV_DIR]   (default /work/peer/venv; skipped when present)
set -euo pipefail
VENV="${1:-/work/peer/venv}"
if [ -x "$VENV/bin/python" ] && "$VENV/bin/python" -c "import nerfstudio" 2>/dev/null; then
    echo "nerfstudio already installed in $VENV"
    exit 0
fi
python3 -m venv "$VENV"
"$VENV/bin/pip" install -q nerfstudio==1.1.5
"$VENV/bin/python" -c "import importlib.metadata as m; print('nerfstudio', m.version('nerfstudio'), 'torch', m.version('torch'))"
