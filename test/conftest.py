"""Shared test helpers."""
import importlib
import os

import pytest


def in_ci() -> bool:
    """True on a CI runner (``CI=true``, as GitHub Actions, GitLab CI and most others set it)."""
    return os.environ.get("CI", "").strip().lower() in ("true", "1", "yes")


def import_or_skip(name: str, reason: str):
    """``pytest.importorskip``, except in CI, where a missing module fails the run.

    Locally a missing optional dependency (e.g. the ROS 2 wheels of the ``ros`` extra) skips the tests
    that need it; in CI it is an installation failure and must not pass as a row of skips.
    """
    if not in_ci():
        return pytest.importorskip(name, reason=reason)
    try:
        return importlib.import_module(name)
    except ImportError as exc:
        raise ImportError(f"CI=true but {name} cannot be imported ({reason}): {exc}") from exc


#: Tests of other files that took 20 s or more in a full run on the loaded 2-core machine (2026-11-25,
#: seconds; the whole run: 20.7 min), marked ``slow`` here; the node-graph and ros2-tool tests carry the
#: mark in their own files. ``pytest -m "not slow" test`` leaves them all out.
SLOW = {
    "test_diagnose.py::test_names_the_concealed_effect": 319,       # its module fixture, set up by the first
    "test_diagnose.py::test_forward_scatter_is_named_beside_dense_marine_snow": 98,
    "test_backward.py::test_cmaes_recovers_parameters": 69,
    "test_fieldbags.py::test_fit_field_bag_recovers_the_parameters": 32,
    "test_backward.py::test_cmaes_from_the_centre_must_move_and_improves_on_its_start": 23,
    "test_campaign.py::test_dask_gives_the_same_table_and_a_rerun_skips": 20,
    "test_workers.py::test_a_diagnosis_is_the_same_with_one_process_or_two": 37,   # (quiet machine)
}


def pytest_collection_modifyitems(config, items):
    for item in items:
        if f"{item.path.name}::{getattr(item, 'originalname', item.name)}" in SLOW:
            item.add_marker(pytest.mark.slow)


@pytest.fixture(autouse=True)
def _ros_domains():
    """The ROS domain ids a test reserved (rosproc.domain_id) are given back when it ends."""
    yield
    from rosproc import release_domains

    release_domains()


def pytest_sessionfinish(session):
    """Fast DDS shared-memory segments of node processes a test had to SIGKILL (they outlive their owner and
    fill /dev/shm, which is RAM) are removed; segments of live processes (other runs) are left alone."""
    try:
        from rosproc import clean_shm

        clean_shm()
    except Exception:       # uw_sil not importable: nothing of ours ran
        pass


@pytest.fixture
def ros(monkeypatch):
    """A fresh rclpy Context on its own ROS domain with loopback discovery; shut down afterwards."""
    rclpy = import_or_skip("rclpy", reason="ROS 2 Python packages (the `ros` extra) are not installed")
    from rclpy.context import Context

    from rosproc import domain_id

    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    ctx = Context()
    rclpy.init(context=ctx, domain_id=domain_id())
    yield ctx
    ctx.try_shutdown()
