#!/usr/bin/env bash
# Set up (idempotent) and run the whole test suite. `.ci/run` calls exactly this.
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$here/scripts/setup.sh"
cd "$here"
# DDS isolation for the tests that start ROS 2 nodes (each test picks its own ROS_DOMAIN_ID).
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
export PYOPENGL_PLATFORM="${PYOPENGL_PLATFORM:-osmesa}"
# Two test processes (pytest-xdist), one file each at a time (a module's fixtures are built once): the
# suite is half waiting for node graphs, so two share the 2-core machine well. UW_SIL_TEST_WORKERS=0 runs
# it in one process.
exec .venv/bin/python -m pytest test -q -n "${UW_SIL_TEST_WORKERS:-2}" --dist loadfile "$@"
