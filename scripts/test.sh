#!/usr/bin/env bash
# Set up (scripts/setup.sh), check the import layers, lint (ruff) and types (mypy), and run the
# whole test suite. Extra arguments go to pytest (`-m "not slow"` for the fast tier).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
.venv/bin/lint-imports pyproject.toml
.venv/bin/ruff check .
.venv/bin/mypy drivers sim station fakes
exec .venv/bin/python -m pytest "$@"
