#!/usr/bin/env bash
# Set up a virtualenv with the project, then run the main job: stream rbs480a (or a
# generated matrix when the data file is absent) into a local zarr store and report.
set -euo pipefail
cd "$(dirname "$0")/.."
. scripts/venv.sh
venv_install fem
exec .venv/bin/python scripts/demo.py "$@"
