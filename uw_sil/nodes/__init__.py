"""Thin rclpy adapters around the core library: parameters, topics, services, message conversion."""
from __future__ import annotations

from typing import Callable, Optional


def run_node(make_node: Callable, spin: Optional[Callable] = None, args=None, name: str = "",
             user_errors: tuple = ()) -> int:
    """The ``main()`` every node shares: init, build, spin, clean shutdown; returns the exit code.

    ``spin(node)`` returns an exit code (default: ``rclpy.spin``, code 0). Ctrl-C / SIGTERM are a clean
    stop, also during start-up (then the context is already shut down under the constructor).
    Exceptions in ``user_errors`` (bad parameters such as a missing bag) are logged, exit code 1.
    """
    import rclpy
    from rclpy.executors import ExternalShutdownException
    from rclpy.logging import get_logger

    rclpy.init(args=args)
    node = None
    code = 0
    try:
        node = make_node()
        if spin is None:
            rclpy.spin(node)
        else:
            code = spin(node) or 0
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except user_errors as e:
        get_logger(name or "uw_sil").error(str(e))
        code = 1
    except Exception:
        if rclpy.ok():
            raise
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return code
