"""The ROS 2 room: thin rclpy adapters around the core library (parameters, topics, services, message
conversion), the node graphs (:mod:`.graph`) that feed both the launch files and ``uw-sil launch``
(:mod:`.launcher`).

Import rules: the only room that imports rclpy and ROS message packages (inside the node modules;
this ``__init__``, :mod:`.graph` and :mod:`.launcher` import no rclpy at module level). No algorithm
lives here: nodes call :mod:`uw_sil.sim`, :mod:`uw_sil.fit`, :mod:`uw_sil.bags`.
"""
from __future__ import annotations

import sys
from typing import Callable, Optional


def help_requested(args=None) -> bool:
    """``-h``/``--help`` among the node's own arguments (those before ``--ros-args``)."""
    argv = list(sys.argv[1:] if args is None else args)
    own = argv[:argv.index("--ros-args")] if "--ros-args" in argv else argv
    return "-h" in own or "--help" in own


def run_node(make_node: Callable, spin: Optional[Callable] = None, args=None, name: str = "",
             user_errors: tuple = (), doc: str = "") -> int:
    """The ``main()`` every node shares: init, build, spin, clean shutdown; returns the exit code.

    With ``-h``/``--help`` it prints ``doc`` (the node module's docstring: topics, parameters) and
    returns 0 without starting ROS.

    ``spin(node)`` returns an exit code (default: ``rclpy.spin``, code 0). Ctrl-C / SIGTERM are a clean
    stop, also during start-up (then the context is already shut down under the constructor).
    Exceptions in ``user_errors`` (bad parameters such as a missing bag) are logged, exit code 1.
    """
    if help_requested(args):
        print(f"usage: ros2 run uw_sil {name or 'NODE'} [--ros-args -p NAME:=VALUE | --params-file FILE | "
              f"-r FROM:=TO ...]\n\n{doc.strip()}")
        return 0
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
