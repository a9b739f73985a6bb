"""A graph of :mod:`uw_sil.nodes.graph` as a ROS 2 launch description (``launch``/``launch_ros``).

``launch/<graph>.launch.py`` is :func:`generate` of its graph: one ``DeclareLaunchArgument`` per graph
argument (with its description, default and choices), then the nodes, built when the arguments are known.

Behaviour (beyond upstream ``ros2 launch``'s)
---------------------------------------------
* Arguments are checked by the graph (:meth:`uw_sil.nodes.graph.Graph.parse`): ``frames:=abc`` ends the
  launch before any node starts, with "argument frames:='abc' is not valid: expected an integer >= 1",
  and ``ros2 launch`` exits 1.
* A node that exits with a non-zero status while the launch is not shutting down ends the launch with
  its reason (the last ``[ERROR]``/``[FATAL]`` line or exception it printed), and ``ros2 launch`` exits 1
  (upstream it would keep running the others and exit 0). A ``required`` node that ends normally shuts
  the launch down (exit 0).
* Nodes set the Fast DDS profile themselves (:func:`uw_sil.nodes.use_fastdds_profile`).
"""
from __future__ import annotations

from functools import partial

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction, RegisterEventHandler, Shutdown
from launch.event_handlers import OnProcessIO
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

from .graph import GRAPHS, Graph, NodeSpec, failure_reason

__all__ = ["generate", "NodeFailed"]

PACKAGE = "uw_sil"


class NodeFailed(RuntimeError):
    """A node of the graph exited with an error (raised in launch's event loop: it ends the launch with
    status 1 and this message)."""


def generate(graph_name: str) -> LaunchDescription:
    """The launch description of graph ``graph_name`` (a key of :data:`uw_sil.nodes.graph.GRAPHS`)."""
    graph = GRAPHS[graph_name]
    actions = [DeclareLaunchArgument(a.name, default_value=a.default_text, description=a.help,
                                     choices=list(a.choices) if a.choices else None) for a in graph.arguments]
    actions.append(OpaqueFunction(function=_nodes, args=[graph]))
    return LaunchDescription(actions)


def _nodes(context, graph: Graph) -> list:
    texts = {a.name: LaunchConfiguration(a.name).perform(context) for a in graph.arguments}
    actions = []
    for spec in graph.nodes(texts):       # ValueError naming the argument: the launch ends with it
        output: list = []
        node = Node(package=PACKAGE, executable=spec.executable, name=spec.name, output="screen",
                    parameters=[*spec.param_files, spec.parameters], remappings=spec.remappings,
                    arguments=spec.arguments, on_exit=partial(_on_exit, spec, output))
        keep = partial(_keep_output, output)
        actions += [node, RegisterEventHandler(OnProcessIO(target_action=node, on_stdout=keep, on_stderr=keep))]
    return actions


def _keep_output(output: list, event) -> None:
    """Remember a node's last output lines (for the reason of a failure)."""
    output.extend(event.text.decode(errors="replace").splitlines())
    del output[:-50]


def _on_exit(spec: NodeSpec, output: list, event, context):
    if context.is_shutdown:            # stopping anyway (Ctrl-C, another node's end)
        return None
    if event.returncode != 0:
        reason = failure_reason(output)
        raise NodeFailed(f"{spec.name} failed (exit code {event.returncode})" + (f": {reason}" if reason else ""))
    if spec.required:
        return [Shutdown(reason=f"required node {spec.name} ended")]
    return None
