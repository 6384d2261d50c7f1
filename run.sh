#!/usr/bin/env bash
# Set up (or reuse) the virtual environment and run the demo or the tests.
#   bash run.sh demo   -- flow past a cylinder with snapping (main demo)
#   bash run.sh test   -- the whole test suite (serial and mpiexec -n 2/3)
set -euo pipefail
cd "$(dirname "$0")"
VENV=${NAGATA_SNAP_VENV:-.venv}

find_python() {
  # A pyenv shim answers `command -v` even when its version is not active, so
  # every candidate is run, not merely looked up.
  for cand in python3.12 python3.13; do
    if "$cand" -c 'import sys; assert sys.version_info >= (3, 12)' >/dev/null 2>&1; then
      echo "$cand"; return
    fi
  done
  # pyenv-installed interpreters, whether or not pyenv is active in this shell
  for exe in "${PYENV_ROOT:-$HOME/.pyenv}"/versions/3.1[2-9]*/bin/python3; do
    if [ -x "$exe" ] && "$exe" -c 'import sys; assert sys.version_info >= (3, 12)' >/dev/null 2>&1; then
      echo "$exe"; return
    fi
  done
  if python3 -c 'import sys; assert sys.version_info >= (3, 12)' 2>/dev/null; then echo python3; return; fi
  echo "error: CPython >= 3.12 is needed (DOLFINx wheel dolfinx-solver-real); none found" >&2
  exit 1
}

if [ ! -x "$VENV/bin/python" ] || ! "$VENV/bin/python" -c 'import nagata_snap, dolfinx, gmsh, OCP, pytest, hypothesis, matplotlib' 2>/dev/null; then
  PY=$(find_python)
  echo "setting up $VENV with $($PY --version)" >&2
  $PY -m venv "$VENV"
  "$VENV/bin/python" -m pip install -q --upgrade pip
  "$VENV/bin/python" -m pip install -q -e ".[test,demo]"
fi
case "$VENV" in /*) ;; *) VENV="$PWD/$VENV" ;; esac
export PATH="$VENV/bin:$PATH"
export OMP_NUM_THREADS=1

case "${1:-test}" in
  demo) shift; exec "$VENV/bin/python" demos/flow_past_cylinder.py "$@" ;;
  test) shift; exec "$VENV/bin/python" -m pytest -q tests "$@" ;;
  *) echo "usage: bash run.sh {demo|test} [args...]" >&2; exit 2 ;;
esac
