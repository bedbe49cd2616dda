#!/usr/bin/env bash
# Build the docs site into site/ with warnings as errors (mkdocs build --strict).
# Installs the project with its [docs] extra into .venv when mkdocs is missing there.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
    "$PY" -m venv .venv
fi
if ! .venv/bin/python -c "import mkdocs, material, mkdocstrings_handlers.python" 2>/dev/null; then
    .venv/bin/python -m pip install --quiet --upgrade pip
    .venv/bin/python -m pip install --quiet -e ".[docs]"
fi
exec .venv/bin/python -m mkdocs build --strict --site-dir site "$@"
