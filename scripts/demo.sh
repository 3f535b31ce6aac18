#!/usr/bin/env bash
# Set up (scripts/setup.sh), then run the project's main job on the built-in fake benches
# (`ltc demo`): for each of the rig's two cameras a bench check, acquisition of Fourier
# single-pixel frames at six depths, LTC reconstruction and the measured lens; then the
# experiment (real, measured-LTC, Gaussian and pinhole scanners on spheres, ball bars and a
# CAD part) and its report. Each run writes into a new folder out/demo-<time>; nothing earlier
# is overwritten. Extra arguments go to `ltc demo` (e.g. --json).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
exec .venv/bin/ltc demo "$@"
