#!/usr/bin/env bash
# Set up (scripts/setup.sh), then run the main job on the built-in fake bench: check the bench,
# acquire Fourier single-pixel frames at every depth, reconstruct every pixel's LTC, and derive
# the measured lens (principal rays, optical centre, aperture samples) with figures.
# Each run writes into a new folder out/demo-<time>; nothing earlier is overwritten.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
ltc=.venv/bin/ltc
out="out/demo-$(date +%Y%m%d-%H%M%S)"
mkdir -p "$out"
$ltc config --example fake > "$out/fake.toml"
echo "== 1/4 check the bench"
$ltc check "$out/fake.toml" --out "$out/check"
echo "== 2/4 acquire"
$ltc acquire "$out/fake.toml" --out "$out/run.zarr"
echo "== 3/4 reconstruct the LTC"
$ltc reconstruct "$out/run.zarr" --out "$out/ltc.zarr"
echo "== 4/4 derive the lens"
$ltc lens "$out/ltc.zarr" --out "$out/lens.npz" --figures "$out/figures" "$@"
echo "== done: results in $out (contact sheet, run store, LTC store, lens model, figures)"
