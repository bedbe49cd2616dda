#!/usr/bin/env bash
# Static checks on the project's virtualenv: ruff, the import contracts of the layers
# (import-linter) and mypy on the library, each configured in pyproject.toml. The s3 extra
# is installed too: mypy checks the calls into obstore against its own types.
set -euo pipefail
cd "$(dirname "$0")/.."
. scripts/venv.sh
venv_install dev,s3
.venv/bin/python -m ruff check .
.venv/bin/lint-imports
.venv/bin/python -m mypy
