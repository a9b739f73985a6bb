#!/usr/bin/env bash
# Set up (idempotent) and run the whole test suite. `.ci/run` calls exactly this.
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$here/scripts/setup.sh"
cd "$here"
source "$here/scripts/pytest_args.sh"
exec .venv/bin/python -m pytest test "${UW_SIL_PYTEST_ARGS[@]}" "$@"
