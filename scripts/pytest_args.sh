# How the suite runs (sourced by scripts/test.sh and scripts/flake_check.sh, so both run it alike).
# DDS isolation for the tests that start ROS 2 nodes (each test picks its own ROS_DOMAIN_ID); headless GL.
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
export PYOPENGL_PLATFORM="${PYOPENGL_PLATFORM:-osmesa}"
# Two test processes (pytest-xdist), one file each at a time (a module's fixtures are built once): the
# suite is half waiting for node graphs, so two share the 2-core machine well. UW_SIL_TEST_WORKERS=0 runs
# it in one process.
UW_SIL_PYTEST_ARGS=(-q -n "${UW_SIL_TEST_WORKERS:-2}" --dist loadfile)
