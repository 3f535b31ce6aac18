#!/usr/bin/env bash
# Set up (scripts/setup.sh) and run the main job on the built-in fake bench.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
mkdir -p out
exec .venv/bin/ltc check --fake --out out/check "$@"
