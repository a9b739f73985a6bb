"""The ROS 2 node graphs of uw_sil, described once for both ways of starting them.

``launch/*.launch.py`` turns these descriptions into ``launch_ros`` ``Node`` actions (ROS 2 installs);
``uw-sil launch`` turns them into processes (``python -m uw_sil.nodes.<module> --ros-args ...``) for
pip installs, where ``launch``/``launch_ros`` do not exist. Nothing here imports ROS.
"""
from __future__ import annotations

import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

__all__ = ["NodeSpec", "BACKWARD_INPUTS", "backward_graph", "forward_graph", "sil_graph", "ros_args", "command_line",
           "share_file", "GRAPHS"]


@dataclass
class NodeSpec:
    """One node: the console script / module to run, its name, parameter files, parameters, remappings."""

    executable: str                                      # console script (== module under uw_sil.nodes)
    name: str
    param_files: list = field(default_factory=list)
    parameters: dict = field(default_factory=dict)
    remappings: list = field(default_factory=list)       # (from, to)
    arguments: list = field(default_factory=list)        # plain arguments before --ros-args
    required: bool = False                               # the graph ends when this node exits

    @property
    def module(self) -> str:
        return f"uw_sil.nodes.{self.executable}"


def share_file(*parts: str) -> Path:
    """A file of this package's share directory (config/, launch/), installed or in the source tree."""
    source_tree = Path(__file__).resolve().parents[2]          # uw_sil/nodes/graph.py -> repository
    candidates = [source_tree.joinpath(*parts), Path(sys.prefix, "share", "uw_sil", *parts)]
    try:
        from ament_index_python.packages import get_package_share_directory

        candidates.insert(0, Path(get_package_share_directory("uw_sil"), *parts))
    except Exception:  # not in an ament index: the other candidates remain
        pass
    for c in candidates:
        if c.exists():
            return c
    raise FileNotFoundError(f"{'/'.join(parts)} not found in: " + ", ".join(str(c) for c in candidates))


#: Topics ``backward_fit`` subscribes to (as resolved in the root namespace): a replayed bag must have them.
BACKWARD_INPUTS = ("/camera/image_raw", "/camera/camera_info", "/panel/pose")


#: Seconds without a new frame after which ``backward_fit`` fits the frames it has (replayed bags).
IDLE_TIMEOUT = 3.0


def backward_graph(sim_params: Optional[str] = None, bag: Optional[str] = None, output_yaml: str = "",
                   frames: int = 3, optimizer: str = "pso", rate: float = 1.0, loop: bool = False,
                   max_iter: Optional[int] = None, stride: Optional[int] = None,
                   keep_running: bool = False) -> list:
    """sim_camera + backward_fit (+ bag_play replaying a field trial when ``bag`` is given).

    With a bag the graph is an offline replay: ``backward_fit`` exits once the fit is done (or has
    failed) and, being ``required``, ends the graph, unless ``keep_running`` (then, as with a live
    camera, everything runs until Ctrl-C and ``sim_camera`` keeps serving the fitted parameters).
    ``bag_play`` starts once ``backward_fit`` subscribes, so no frame is lost to start-up; its end
    does not end the graph. If the bag has fewer usable frames than ``frames``, ``backward_fit``
    fits those it has ``IDLE_TIMEOUT`` s after the last one.
    """
    sim_params = sim_params or str(share_file("config", "sim_camera.yaml"))
    exit_when_done = bool(bag) and not keep_running
    fit = {"frames": int(frames), "optimizer": optimizer, "output_yaml": output_yaml, "sim_node": "sim_camera",
           "exit_when_done": exit_when_done}
    if bag:
        # the bag may hold fewer usable frames than asked for: fit those once it has ended
        fit["idle_timeout"] = IDLE_TIMEOUT
    if max_iter is not None:
        fit["max_iter"] = int(max_iter)
    if stride is not None:
        fit["stride"] = int(stride)
    nodes = [
        NodeSpec("sim_camera", "sim_camera", param_files=[sim_params]),
        NodeSpec("backward_fit", "backward_fit", parameters=fit, required=exit_when_done),
    ]
    if bag:
        nodes.append(NodeSpec("bag_play", "bag_play", parameters={
            "bag": str(bag), "rate": float(rate), "loop": bool(loop),
            "wait_for_topics": [BACKWARD_INPUTS[0], BACKWARD_INPUTS[2]], "wait_for_nodes": ["backward_fit"],
            "delay": 0.5}))
    return nodes


#: sim_camera when a bag is replayed into the forward half: render every pose (a live camera keeps the
#: default queue of 1, the newest pose, for latency).
REPLAY_SIM_CAMERA = {"queue_size": 100}

#: Topic the enhancer subscribes to once sim_camera listens for poses: a replayed bag waits for it.
FORWARD_INPUT = "/camera/image_raw"


def _enhancer(method: str, b_from_frame: bool, idle_exit: bool) -> NodeSpec:
    params = {"method": method, "b_from_frame": bool(b_from_frame), "sim_node": "sim_camera"}
    if idle_exit:
        params["idle_timeout"] = IDLE_TIMEOUT
    return NodeSpec("enhancer", "enhancer", parameters=params, required=idle_exit)


def _bag_play(bag, rate, loop, wait_for_topics, wait_for_nodes=()) -> NodeSpec:
    params = {"bag": str(bag), "rate": float(rate), "loop": bool(loop), "wait_for_topics": list(wait_for_topics),
              "delay": 0.5}
    if wait_for_nodes:
        params["wait_for_nodes"] = list(wait_for_nodes)
    return NodeSpec("bag_play", "bag_play", parameters=params)


def forward_graph(sim_params: Optional[str] = None, bag: Optional[str] = None, rate: float = 1.0, loop: bool = False,
                  keep_running: bool = False, method: str = "sil", b_from_frame: bool = False) -> list:
    """sim_camera + enhancer (+ bag_play replaying a field trial when ``bag`` is given): the forward half.

    ``sim_params`` is the fitted parameters file (``uw-sil fit --out fit.yaml``; default
    ``config/sim_camera.yaml``); the enhancer follows ``sim_camera``'s parameters. With a bag (and not
    ``keep_running`` or ``loop``) the enhancer exits ``IDLE_TIMEOUT`` s after the last frame and, being
    ``required``, ends the graph. ``bag_play`` starts once its camera and pose publishers have matched the
    enhancer and sim_camera (the enhancer subscribes once it has sim_camera's parameters), so no frame is
    lost to start-up.
    """
    sim_params = sim_params or str(share_file("config", "sim_camera.yaml"))
    idle_exit = bool(bag) and not keep_running and not loop
    nodes = [NodeSpec("sim_camera", "sim_camera", param_files=[sim_params],
                      parameters=dict(REPLAY_SIM_CAMERA) if bag else {}),
             _enhancer(method, b_from_frame, idle_exit)]
    if bag:
        # without wait_for_nodes bag_play waits for a *matched* reader on each topic: the enhancer on the
        # camera, sim_camera on the poses (both are the only readers in this graph)
        nodes.append(_bag_play(bag, rate, loop, [FORWARD_INPUT, BACKWARD_INPUTS[2]]))
    return nodes


def sil_graph(sim_params: Optional[str] = None, bag: Optional[str] = None, output_yaml: str = "", frames: int = 3,
              optimizer: str = "pso", rate: float = 1.0, loop: bool = False, max_iter: Optional[int] = None,
              stride: Optional[int] = None, keep_running: bool = False, method: str = "sil",
              b_from_frame: bool = False) -> list:
    """Both halves: sim_camera + backward_fit + enhancer (+ bag_play): the fit re-parameterizes sim_camera,
    and through its parameter events the enhancer.

    With a bag the graph ends when the fit is done (as the backward graph), unless ``keep_running``; frames
    enhanced before then use ``sim_params``. ``bag_play`` starts once both backward_fit and the enhancer
    subscribe to the camera.
    """
    nodes = [n for n in backward_graph(sim_params=sim_params, bag=bag, output_yaml=output_yaml, frames=frames,
                                       optimizer=optimizer, rate=rate, loop=loop, max_iter=max_iter, stride=stride,
                                       keep_running=keep_running) if n.name != "bag_play"]
    nodes.append(_enhancer(method, b_from_frame, idle_exit=False))
    if bag:
        nodes[0].parameters.update(REPLAY_SIM_CAMERA)
        nodes.append(_bag_play(bag, rate, loop, [FORWARD_INPUT], ["backward_fit", "enhancer"]))
    return nodes


GRAPHS = {"backward": backward_graph, "forward": forward_graph, "sil": sil_graph}


def _param_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return _quote(v)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_quote(x) if isinstance(x, str) else _param_value(x) for x in v) + "]"
    return repr(v)


def _quote(text: str) -> str:
    """A string as a YAML scalar that stays a string (``-p k:=v`` values are parsed as YAML)."""
    import json

    return json.dumps(text)


def ros_args(spec: NodeSpec) -> list:
    """``--ros-args`` part of the command line for ``spec``."""
    args = ["--ros-args", "-r", f"__node:={spec.name}"]
    for f in spec.param_files:
        args += ["--params-file", str(f)]
    for k, v in spec.parameters.items():
        args += ["-p", f"{k}:={_param_value(v)}"]
    for a, b in spec.remappings:
        args += ["-r", f"{a}:={b}"]
    return args


def command_line(spec: NodeSpec, python: str = sys.executable) -> list:
    """The process that runs ``spec`` without ``ros2 launch``."""
    return [python, "-m", spec.module, *spec.arguments, *ros_args(spec)]
