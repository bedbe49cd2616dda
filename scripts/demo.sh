#!/usr/bin/env bash
# Set up a virtualenv with the project, then run the main job: stream rbs480a (or a
# generated matrix when the data file is absent) into a local zarr store and report.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
    "$PY" -m venv .venv
fi
.venv/bin/python -m pip install --quiet --upgrade pip
.venv/bin/python -m pip install --quiet -e ".[fem]"
exec .venv/bin/python scripts/demo.py "$@"
