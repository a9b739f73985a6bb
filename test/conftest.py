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
