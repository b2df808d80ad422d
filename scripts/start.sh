#!/usr/bin/env bash
# Set up (see setup.sh) and start SSM Studio on the demo data. Without a display, render the
# main window to ssm-studio-demo.png under a virtual X server instead, and say where it is.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
if [ -z "${DISPLAY:-}" ] && [ -z "${WAYLAND_DISPLAY:-}" ]; then
  .venv/bin/ssm-studio --screenshot ssm-studio-demo.png
  echo "No display here: rendered the demo window to $(pwd)/ssm-studio-demo.png"
else
  exec .venv/bin/ssm-studio "$@"
fi
