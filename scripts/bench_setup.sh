#!/usr/bin/env bash
# Install the optional benchmark dependencies (benchmarks/README.md):
#   - Mitsuba 3 into .venv through the project's `bench` extra (pyproject.toml);
#   - Debian's libllvm19 for Mitsuba's fast `llvm_ad_rgb` variant (Debian 12's LLVM 15 aborts
#     in Dr.Jit with "Cannot select ... fminimum"), where apt-get and root are available.
# Prints the DRJIT_LIBLLVM_PATH to export. Idempotent: a second run only checks.
# Needs scripts/setup.sh to have created .venv first.
set -euo pipefail
cd "$(dirname "$0")/.."

if [ ! -x .venv/bin/python ]; then
  echo "bench_setup: .venv is missing; run scripts/setup.sh first" >&2
  exit 1
fi

if ! .venv/bin/python -c "import mitsuba" >/dev/null 2>&1; then
  echo "bench_setup: installing the bench extra (mitsuba) into .venv"
  .venv/bin/python -m pip install -q -e '.[bench]'
fi
.venv/bin/python -c "import mitsuba, drjit; print('bench_setup: mitsuba', mitsuba.__version__, 'drjit', drjit.__version__)"

find_llvm() {
  local p
  for p in /usr/lib/llvm-19/lib/libLLVM-19.so /usr/lib/llvm-19/lib/libLLVM.so.1 \
           /usr/lib/x86_64-linux-gnu/libLLVM-19.so /usr/lib/x86_64-linux-gnu/libLLVM-19.so.1 \
           /usr/lib/aarch64-linux-gnu/libLLVM-19.so /usr/lib/aarch64-linux-gnu/libLLVM-19.so.1; do
    [ -e "$p" ] && { echo "$p"; return 0; }
  done
  if command -v dpkg >/dev/null 2>&1 && dpkg -s libllvm19 >/dev/null 2>&1; then
    dpkg -L libllvm19 | grep -E '/libLLVM(-19)?\.so(\.[0-9.]+)?$' | head -n 1
    return 0
  fi
  return 1
}

llvm="$(find_llvm || true)"
if [ -z "$llvm" ]; then
  sudo_cmd=""
  [ "$(id -u)" -eq 0 ] || sudo_cmd="sudo -n"
  if command -v apt-get >/dev/null 2>&1 && { [ -z "$sudo_cmd" ] || sudo -n true 2>/dev/null; }; then
    echo "bench_setup: installing Debian's libllvm19"
    $sudo_cmd apt-get install -y -q libllvm19 >/dev/null 2>&1 \
      || { $sudo_cmd apt-get update -q >/dev/null && $sudo_cmd apt-get install -y -q libllvm19 >/dev/null; }
    llvm="$(find_llvm || true)"
  else
    echo "bench_setup: cannot install libllvm19 (no apt-get or no root): only Mitsuba's" \
         "scalar_rgb variant will run (5-6x slower; benchmarks/render_vs_mitsuba.py --variant scalar_rgb)" >&2
  fi
fi

if [ -n "$llvm" ]; then
  echo "bench_setup: libLLVM 19 at $llvm"
  if DRJIT_LIBLLVM_PATH="$llvm" .venv/bin/python -c "import mitsuba as mi; mi.set_variant('llvm_ad_rgb')" >/dev/null 2>&1; then
    echo "bench_setup: llvm_ad_rgb works"
  else
    echo "bench_setup: llvm_ad_rgb does not load with $llvm" >&2
  fi
  echo "export DRJIT_LIBLLVM_PATH=$llvm"
fi
