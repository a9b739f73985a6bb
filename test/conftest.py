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
