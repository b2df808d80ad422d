#!/usr/bin/env bash
# Lint and import order (ruff) over the repository and type checks of the engine (mypy on
# core/), both configured in pyproject.toml; run by CI after the test suite.
set -euo pipefail
cd "$(dirname "$0")/.."
.venv/bin/python -m ruff check .
.venv/bin/python -m mypy core
