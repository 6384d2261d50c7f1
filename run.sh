#!/usr/bin/env bash
# Set up (or reuse) the virtual environment and run the demo, the tests or the checks.
#   bash run.sh demo         -- flow past a cylinder with snapping (main demo)
#   bash run.sh test [ARGS]  -- the whole test suite (serial and mpiexec -n 2/3), or the pytest
#                               ARGS given (files, -k ...)
#   bash run.sh check        -- ruff, mypy, documentation site build (with the API reference),
#                               README and package-map layout (fails on any problem)
#   bash run.sh docs [DIR]   -- the documentation site (mkdocs, strict) with the pdoc API reference
#                               in DIR/api, into DIR (out/site)
#   bash run.sh results [ARGS] -- rerun the benchmarks named on the results pages and write their
#                               output into docs/pages/results (slow; ARGS: docs/results.py --help)
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

if [ ! -x "$VENV/bin/python" ] || ! "$VENV/bin/python" -c 'import nagata_snap, dolfinx, gmsh, OCP, pytest, hypothesis, matplotlib, ruff, mypy, pdoc, mkdocs' 2>/dev/null; then
  PY=$(find_python)
  echo "setting up $VENV with $($PY --version)" >&2
  $PY -m venv "$VENV"
  "$VENV/bin/python" -m pip install -q --upgrade pip
  "$VENV/bin/python" -m pip install -q -e ".[wheel,cad,test,demo,dev]"
fi
case "$VENV" in /*) ;; *) VENV="$PWD/$VENV" ;; esac
export PATH="$VENV/bin:$PATH"
export OMP_NUM_THREADS=1

check() {
  # Every tool runs (all problems are listed); the step fails if any of them failed.
  local failed=() api
  echo "== ruff check nagata_snap tests benchmarks demos meshes docs"
  "$VENV/bin/ruff" check nagata_snap tests benchmarks demos meshes docs || failed+=(ruff)
  echo "== mypy (files and options: [tool.mypy] in pyproject.toml)"
  "$VENV/bin/python" -m mypy || failed+=(mypy)
  echo "== documentation site and API reference (mkdocs --strict, pdoc: docs/hooks.py)"
  site=$(mktemp -d)
  "$VENV/bin/python" -m mkdocs build --strict --site-dir "$site" || failed+=(docs)
  rm -rf "$site"
  echo "== README and package map (docs/layout.py)"
  "$VENV/bin/python" docs/layout.py || failed+=(layout)
  if [ ${#failed[@]} -gt 0 ]; then
    echo "check FAILED: ${failed[*]}" >&2
    return 1
  fi
  echo "check passed: ruff, mypy, documentation site, API reference, README and package map"
}

case "${1:-test}" in
  demo) shift; exec "$VENV/bin/python" demos/flow_past_cylinder.py "$@" ;;
  test) shift; exec "$VENV/bin/python" -m pytest -q "$@" ;;  # pyproject: testpaths = tests
  check) check ;;
  docs) site=${2:-out/site}
        "$VENV/bin/python" -m mkdocs build --strict --site-dir "$site"
        echo "documentation: $site/index.html (API reference: $site/api/nagata_snap.html)" ;;
  results) shift; exec "$VENV/bin/python" docs/results.py "$@" ;;
  *) echo "usage: bash run.sh {demo|test|check|docs|results} [args...]" >&2; exit 2 ;;
esac
