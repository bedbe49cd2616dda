#!/usr/bin/env bash
# Set up a virtualenv with the project and its test extras, then run a tier of the tests:
#   bash scripts/test.sh          the fast tier (-m "not slow"; hypothesis profile "fast")
#   bash scripts/test.sh --slow   the slow tier (-m slow): tests/slow/ and the tests marked slow
#                                 (profile "ci"; with the bench extra's peers)
#   bash scripts/test.sh --all    both tiers (profile "ci"), on two processes (pytest-xdist)
# Further arguments pass through to pytest.
set -euo pipefail
cd "$(dirname "$0")/.."
. scripts/venv.sh
tier=fast
case "${1:-}" in
    --slow) tier=slow; shift ;;
    --all) tier=all; shift ;;
esac
# the slow tier also runs the side-by-side benchmarks' smoke tests: their peers come
# with the bench extra
if [ "$tier" = fast ]; then venv_install test,fem; else venv_install test,fem,bench; fi
case "$tier" in
    fast) export HYPOTHESIS_PROFILE=${HYPOTHESIS_PROFILE:-fast}; set -- -m "not slow" "$@" ;;
    slow) export HYPOTHESIS_PROFILE=${HYPOTHESIS_PROFILE:-ci}; set -- -m slow "$@" ;;
    all) export HYPOTHESIS_PROFILE=${HYPOTHESIS_PROFILE:-ci}; set -- -n 2 "$@" ;;
esac
exec .venv/bin/python -m pytest "$@"
