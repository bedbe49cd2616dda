#!/usr/bin/env bash
# Build the docs site into site/ with warnings as errors (mkdocs build --strict).
# Installs the project with its [docs] extra into .venv when mkdocs is missing there.
set -euo pipefail
cd "$(dirname "$0")/.."
. scripts/venv.sh
if ! .venv/bin/python -c "import mkdocs, material, mkdocstrings_handlers.python" 2>/dev/null; then
    venv_install docs
fi
export NO_MKDOCS_2_WARNING=1  # the theme's notice about its successor, not about this site
exec .venv/bin/python -m mkdocs build --strict --site-dir site "$@"
