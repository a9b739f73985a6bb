#!/usr/bin/env bash
# Set up (idempotent) and run the whole test suite. `.ci/run` calls exactly this.
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$here/scripts/setup.sh"
cd "$here"
# DDS isolation for the tests that start ROS 2 nodes (each test picks its own ROS_DOMAIN_ID).
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
export PYOPENGL_PLATFORM="${PYOPENGL_PLATFORM:-osmesa}"
source "$here/scripts/pytest_args.sh"
exec .venv/bin/python -m pytest test "${UW_SIL_PYTEST_ARGS[@]}" "$@"
