#!/usr/bin/env bash
# Set up with the test extras (see setup.sh) and run the whole test suite. GUI tests run under
# a virtual X server started by pytest-xvfb (platform xcb: Qt's offscreen platform cannot
# render the OpenGL views).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh --test
export QT_QPA_PLATFORM=xcb
# The suite runs in parallel, one pytest-xdist worker a core (at most 4: the correspondence
# tests start pools of their own); "worksteal" keeps every worker busy while a few long tests remain.
# SSM_TEST_WORKERS=0 runs it in this one process (for a debugger or -s).
exec .venv/bin/python -m pytest -q -n "${SSM_TEST_WORKERS:-auto}" --maxprocesses 4 \
    --dist worksteal "$@"
