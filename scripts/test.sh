#!/usr/bin/env bash
# Set up with the test extras (see setup.sh) and run the whole test suite. GUI tests run under
# a virtual X server started by pytest-xvfb (platform xcb: Qt's offscreen platform cannot
# render the OpenGL views).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh --test
export QT_QPA_PLATFORM=xcb
exec .venv/bin/python -m pytest -q "$@"
