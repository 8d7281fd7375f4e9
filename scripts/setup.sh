#!/usr/bin/env bash
# Install softbody and what it needs, then run one job.
#
#   bash scripts/setup.sh demo [ARGS...]   # install, then `softbody demo ARGS...`
#   bash scripts/setup.sh test [ARGS...]   # install with test extras, then `pytest -n CORES ARGS...`
#   bash scripts/setup.sh install          # install only
#
# Idempotent: system packages are installed only when missing (apt-get, as root or
# through sudo), the virtual environment `.venv` is created once and the package is
# reinstalled only when pyproject.toml changes. Works on a bare Debian 12 with
# Python 3.11 and nothing else.
set -euo pipefail
cd "$(dirname "$0")/.."
job=${1:-install}
[ $# -gt 0 ] && shift

PYTHON=${PYTHON:-python3}
VENV=${VENV:-.venv}

# System libraries. gmsh's wheel links libGLU/libGL and X libraries; pyvista's offscreen
# rendering needs an EGL or OSMesa GL (with libgl1 alone VTK segfaults); the browser
# tests need Debian's chromium. python3-venv gives a bare Debian `python3 -m venv`. g++
# builds softbody's native sparse solves on first use (softbody/native; without it the
# slower callback solver is used).
pkgs=(libglu1-mesa libgl1 libegl1 libosmesa6 libxrender1 libxcursor1 libxfixes3 libxext6
      libxft2 libfontconfig1 libxinerama1 libx11-6 libgomp1 ca-certificates g++)
[ "$job" = test ] && pkgs+=(chromium fonts-dejavu-core)
if ! "$PYTHON" -c 'import ensurepip, venv' >/dev/null 2>&1; then
    pkgs+=(python3-venv)
fi
missing=()
for p in "${pkgs[@]}"; do
    dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if [ ${#missing[@]} -gt 0 ]; then
    echo "softbody setup: installing system packages: ${missing[*]}"
    sudo=""
    [ "$(id -u)" -ne 0 ] && sudo="sudo"
    $sudo apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
fi

# Python environment.
[ -x "$VENV/bin/python" ] || "$PYTHON" -m venv "$VENV"
extras=""
stamp="$VENV/.softbody-installed"
if [ "$job" = test ]; then extras="[test]"; stamp="$VENV/.softbody-installed-test"; fi
if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ]; then
    echo "softbody setup: installing the package into $VENV"
    "$VENV/bin/python" -m pip install -q --upgrade pip
    "$VENV/bin/python" -m pip install -q -e ".$extras"
    touch "$stamp"
fi

# One BLAS thread: OpenBLAS's Cholesky runs ~15x slower with 2 threads on 2 cores.
export OPENBLAS_NUM_THREADS=${OPENBLAS_NUM_THREADS:-1}
case "$job" in
    demo) exec "$VENV/bin/softbody" demo "$@" ;;
    # Tests run in parallel, one test file per worker (module fixtures are built once): a
    # worker per core, at most 4 (each holds its compiled programs, ~2-3 GB). Pass `-n 0`
    # to run in one process.
    test) workers=$(nproc 2>/dev/null || echo 2); [ "$workers" -gt 4 ] && workers=4
          exec "$VENV/bin/python" -m pytest -n "$workers" --dist loadfile "$@" ;;
    install) echo "softbody installed in $VENV; activate with: source $VENV/bin/activate" ;;
    *) echo "unknown job '$job': use demo, test or install" >&2; exit 2 ;;
esac
