#!/usr/bin/env bash
# Set up everything the project needs on a fresh Debian-like machine: the Debian packages for
# the display tests (Xvfb, Mesa's EGL/GL) and GenICam cameras (Aravis), a virtual environment in
# .venv, and the project with its test extra (PyGObject built from PyPI).
# Idempotent: a second run only checks.
set -euo pipefail
cd "$(dirname "$0")/.."

PY=${PYTHON:-python3}
need_debs=()
command -v Xvfb >/dev/null 2>&1 || need_debs+=(xvfb)
for lib in libEGL_mesa.so.0 libGL.so.1 libEGL.so.1; do
  ldconfig -p 2>/dev/null | grep -q "$lib" || need_debs+=(libegl1 libegl-mesa0 libgl1 libgl1-mesa-dri)
done
# GenICam cameras (drivers/genicam.py): Aravis 0.8 and its GObject introspection data, plus what
# pip needs to build PyGObject (the 'genicam' extra) against Debian's GLib: the
# gobject-introspection-1.0 and cairo development files, pkg-config and a C compiler.
# aravis-tools-cli is arv-tool-0.8 for looking at real cameras (aravis-tools would pull in GTK).
typelib_dirs=(/usr/lib/*/girepository-1.0 /usr/lib/girepository-1.0)
ls "${typelib_dirs[@]}" 2>/dev/null | grep -q '^Aravis-0\.8\.typelib$' || need_debs+=(gir1.2-aravis-0.8)
command -v arv-tool-0.8 >/dev/null 2>&1 || need_debs+=(aravis-tools-cli)
command -v pkg-config >/dev/null 2>&1 || need_debs+=(pkg-config)
command -v cc >/dev/null 2>&1 || need_debs+=(gcc libc6-dev)
if command -v pkg-config >/dev/null 2>&1; then
  pkg-config --exists gobject-introspection-1.0 || need_debs+=(libgirepository1.0-dev)
  pkg-config --exists cairo || need_debs+=(libcairo2-dev)
else
  need_debs+=(libgirepository1.0-dev libcairo2-dev)
fi
# PyGObject and pycairo compile against the venv interpreter's headers (Debian's python3-dev when
# that interpreter is Debian's /usr/bin/python3; a pyenv or python.org build brings its own).
"$PY" -c 'import os, sys, sysconfig; sys.exit(not os.path.exists(os.path.join(sysconfig.get_path("include"), "Python.h")))' \
  || need_debs+=(python3-dev)
if [ ${#need_debs[@]} -gt 0 ]; then
  mapfile -t need_debs < <(printf '%s\n' "${need_debs[@]}" | sort -u)
  sudo_cmd=""
  [ "$(id -u)" -eq 0 ] || sudo_cmd="sudo -n"
  if command -v apt-get >/dev/null 2>&1 && { [ -z "$sudo_cmd" ] || sudo -n true 2>/dev/null; }; then
    echo "setup: installing Debian packages: ${need_debs[*]}"
    apt=($sudo_cmd apt-get -o DPkg::Lock::Timeout=300)
    "${apt[@]}" install -y -q "${need_debs[@]}" >/dev/null 2>&1 \
      || { "${apt[@]}" update -q >/dev/null && "${apt[@]}" install -y -q "${need_debs[@]}" >/dev/null; }
  else
    echo "setup: cannot install ${need_debs[*]} (no apt-get or no root); display and GenICam tests will fail" >&2
  fi
fi

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
