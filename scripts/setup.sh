#!/usr/bin/env bash
# Set up everything the project needs on a fresh Debian-like machine: the Debian packages for
# the display tests (Xvfb, Mesa's EGL/GL), a virtual environment in .venv, and the project.
# Idempotent: a second run only checks.
set -euo pipefail
cd "$(dirname "$0")/.."

need_debs=()
command -v Xvfb >/dev/null 2>&1 || need_debs+=(xvfb)
for lib in libEGL_mesa.so.0 libGL.so.1 libEGL.so.1; do
  ldconfig -p 2>/dev/null | grep -q "$lib" || need_debs+=(libegl1 libegl-mesa0 libgl1 libgl1-mesa-dri)
done
if [ ${#need_debs[@]} -gt 0 ]; then
  mapfile -t need_debs < <(printf '%s\n' "${need_debs[@]}" | sort -u)
  sudo_cmd=""
  [ "$(id -u)" -eq 0 ] || sudo_cmd="sudo -n"
  if command -v apt-get >/dev/null 2>&1 && { [ -z "$sudo_cmd" ] || sudo -n true 2>/dev/null; }; then
    echo "setup: installing Debian packages: ${need_debs[*]}"
    $sudo_cmd apt-get install -y -q "${need_debs[@]}" >/dev/null 2>&1 \
      || { $sudo_cmd apt-get update -q >/dev/null && $sudo_cmd apt-get install -y -q "${need_debs[@]}" >/dev/null; }
  else
    echo "setup: cannot install ${need_debs[*]} (no apt-get or no root); display tests will fail" >&2
  fi
fi

PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  echo "setup: creating .venv with $($PY --version)"
  "$PY" -m venv .venv
fi
stamp=.venv/.installed
if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ]; then
  echo "setup: installing the project and its dependencies into .venv"
  .venv/bin/python -m pip install -q --upgrade pip
  .venv/bin/python -m pip install -q -e '.[test]'
  touch "$stamp"
fi
