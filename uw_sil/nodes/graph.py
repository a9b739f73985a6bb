"""The ROS 2 node graphs of uw_sil, described once for both ways of starting them.

A graph (:class:`Graph`, registered in :data:`GRAPHS`) is its arguments (:class:`GraphArg`: type,
default, range, description) and a function from their values to a list of :class:`NodeSpec`.
``launch/<graph>.launch.py`` turns it into launch arguments and ``launch_ros`` ``Node`` actions
(:func:`uw_sil.nodes.launchgen.generate`, for ``ros2 launch``); ``uw-sil launch <graph>`` turns the same
arguments into command-line options and the nodes into processes (:mod:`uw_sil.nodes.launcher`, for pip
installs, where ``launch``/``launch_ros`` do not exist). Both check the arguments here, with messages
naming the argument. Adding a graph: a builder returning NodeSpecs, a tuple of GraphArgs, an entry in
:data:`GRAPHS`, and a three-line ``launch/<graph>.launch.py``. Nothing here imports ROS.
"""
from __future__ import annotations

import re
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterable, Mapping, Optional

__all__ = ["NodeSpec", "GraphArg", "Graph", "BACKWARD_INPUTS", "BACKWARD_ARGS", "FORWARD_ARGS", "SIL_ARGS",
           "backward_graph", "forward_graph", "sil_graph", "ros_args", "command_line", "share_file", "failure_reason",
           "GRAPHS"]


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

#: The camera topic of each ``image_transport`` (image_transport's naming).
IMAGE_TOPICS = {"raw": "/camera/image_raw", "compressed": "/camera/image_raw/compressed"}


def _camera_input(image_transport: str, pose_source: str, camera_info_file: str) -> tuple:
    """The parameters every camera-reading node takes, and the panel_pose node when the pose comes from the
    panel's markers (None otherwise)."""
    if image_transport not in IMAGE_TOPICS:
        raise ValueError(f"image_transport must be one of {', '.join(IMAGE_TOPICS)}, got {image_transport!r}")
    if pose_source not in ("topic", "markers"):
        raise ValueError(f"pose_source must be topic or markers, got {pose_source!r}")
    params = {}
    if image_transport != "raw":
        params["image_transport"] = image_transport
    if camera_info_file:
        params["camera_info_file"] = str(camera_info_file)
    marker_node = NodeSpec("panel_pose", "panel_pose", parameters=dict(params)) if pose_source == "markers" else None
    return params, marker_node


#: The enhancer's queue of paired frames in a replay (a live camera keeps the default 2, for latency): on the
#: loaded 2-core machine a replay at rate 2 delivered every frame, reliably, and the queue of 2 dropped 2 of 12
#: while the worker was behind. At 640x480 a paired frame holds ~2.4 MB (image, depth, mask).
REPLAY_ENHANCER_QUEUE = 50


def _replayed(marker_node: Optional[NodeSpec], sim_camera: Optional[NodeSpec] = None,
              enhancer: Optional[NodeSpec] = None) -> None:
    """A bag is replayed: nothing may be lost between the nodes. panel_pose and the enhancer read the camera
    reliably (bag_play publishes reliably), sim_camera publishes its renders reliably and the enhancer reads
    them so, and queues what it cannot enhance at once instead of dropping it."""
    for node in (marker_node, enhancer):
        if node is not None:
            node.parameters["reliable_input"] = True
    if sim_camera is not None and enhancer is not None:
        sim_camera.parameters["reliable_output"] = True
        enhancer.parameters["queue_size"] = REPLAY_ENHANCER_QUEUE


#: Seconds without a new frame after which ``backward_fit`` fits the frames it has (replayed bags).
IDLE_TIMEOUT = 3.0

#: With a bag: seconds after which ``backward_fit`` reports that no frames arrived at all. Longer than
#: ``bag_play`` may wait for its readers (its ``wait_timeout``, 30 s), so a slow start is not a failure.
FIRST_FRAME_TIMEOUT = 40.0


def backward_graph(sim_params: Optional[str] = None, bag: Optional[str] = None, output_yaml: str = "",
                   frames: int = 3, optimizer: str = "pso", rate: float = 1.0, loop: bool = False,
                   max_iter: Optional[int] = None, stride: Optional[int] = None,
                   keep_running: bool = False, start_paused: bool = False, diagnose: bool = False,
                   diagnose_frames: Optional[int] = None, diagnose_max_effects: Optional[int] = None,
                   diagnose_effects: str = "", output_json: str = "", image_transport: str = "raw",
                   pose_source: str = "topic", camera_info_file: str = "") -> list:
    """sim_camera + backward_fit (+ bag_play replaying a field trial when ``bag`` is given).

    With a bag the graph is an offline replay: ``backward_fit`` exits once the fit is done (or has
    failed) and, being ``required``, ends the graph, unless ``keep_running`` (then, as with a live
    camera, everything runs until Ctrl-C and ``sim_camera`` keeps serving the fitted parameters).
    ``bag_play`` starts once ``backward_fit`` subscribes, so no frame is lost to start-up; its end
    does not end the graph. If the bag has fewer usable frames than ``frames``, ``backward_fit``
    fits those it has ``IDLE_TIMEOUT`` s after the last one. With ``start_paused`` the replay waits for
    ``bag_play``'s ``~/resume`` (and ``backward_fit`` waits as long as that takes for its first frame).

    With ``diagnose`` backward_fit diagnoses instead (``diagnose_frames`` spread over the frames received,
    see :mod:`uw_sil.nodes.backward_fit`) and sends the extended model; sim_camera is then started with
    ``extensible_effects: all``, so that it takes the accepted effects live. ``image_transport`` (raw |
    compressed) chooses the camera topic, ``pose_source: markers`` adds ``panel_pose`` (the pose from the
    panel's markers on ``panel/pose``), ``camera_info_file`` replaces ``camera/camera_info``.
    """
    sim_params = sim_params or str(share_file("config", "sim_camera.yaml"))
    exit_when_done = bool(bag) and not keep_running
    camera, marker_node = _camera_input(image_transport, pose_source, camera_info_file)
    fit = {"frames": int(frames), "optimizer": optimizer, "output_yaml": output_yaml, "sim_node": "sim_camera",
           "exit_when_done": exit_when_done, **camera}
    if diagnose:
        fit["diagnose"] = True
        for name, value in (("diagnose_frames", diagnose_frames), ("diagnose_max_effects", diagnose_max_effects)):
            if value is not None:
                fit[name] = int(value)
        if diagnose_effects:
            fit["diagnose_effects"] = str(diagnose_effects)
        if output_json:
            fit["output_json"] = str(output_json)
    if bag:
        # the bag may hold fewer usable frames than asked for: fit those once it has ended; and say so
        # when none arrive at all
        fit["idle_timeout"] = IDLE_TIMEOUT
        fit["first_frame_timeout"] = 0.0 if start_paused else FIRST_FRAME_TIMEOUT
        fit["reliable_input"] = True          # bag_play publishes reliably: a replay loses no frame
        _replayed(marker_node)
    if max_iter is not None:
        fit["max_iter"] = int(max_iter)
    if stride is not None:
        fit["stride"] = int(stride)
    sim = {"extensible_effects": "all"} if diagnose else {}
    if camera_info_file:
        sim["camera_info_file"] = str(camera_info_file)
    nodes = [
        NodeSpec("sim_camera", "sim_camera", param_files=[sim_params], parameters=sim),
        NodeSpec("backward_fit", "backward_fit", parameters=fit, required=exit_when_done),
    ]
    if marker_node is not None:
        nodes.append(marker_node)
    if bag:
        waits = [IMAGE_TOPICS[image_transport]] + ([BACKWARD_INPUTS[2]] if marker_node is None else [])
        readers = ["backward_fit"] + (["panel_pose"] if marker_node is not None else [])
        nodes.append(_bag_play(bag, rate, loop, waits, readers + _camera_info_reader(camera_info_file), start_paused))
    return nodes


#: sim_camera when a bag is replayed into the forward half: render every pose (a live camera keeps the
#: default queue of 1, the newest pose, for latency).
REPLAY_SIM_CAMERA = {"queue_size": 100}


#: With poses from the markers, seconds without input after which the enhancer of a replay ends: panel_pose sends
#: the poses later than the images arrive (its first frame took 4.3 s on the loaded 2-core machine: the renderer
#: of its refinement starts), so IDLE_TIMEOUT after the last image ended the graph before any frame was paired.
MARKER_IDLE_TIMEOUT = 15.0


def _enhancer(method: str, b_from_frame: bool, idle_exit: bool, image_transport: str = "raw",
              idle_timeout: float = IDLE_TIMEOUT) -> NodeSpec:
    params = {"method": method, "b_from_frame": bool(b_from_frame), "sim_node": "sim_camera"}
    if image_transport != "raw":
        params["image_transport"] = image_transport
    if idle_exit:
        params["idle_timeout"] = idle_timeout
    return NodeSpec("enhancer", "enhancer", parameters=params, required=idle_exit)


def _camera_info_reader(camera_info_file: str) -> list:
    """bag_play's wait for sim_camera on the camera_info topic (a ``wait_for_nodes`` entry of one topic), unless a
    ``camera_info_file`` gives sim_camera its camera. sim_camera takes the camera size from the first camera_info
    it hears; started late on a loaded machine (its imports: 3-10 s) it heard none of a short bag's and rendered
    the diagnosed model at its default 640x480 for a 160x120 recording (a loaded test run)."""
    return [] if camera_info_file else [f"sim_camera:{BACKWARD_INPUTS[1]}"]


def _bag_play(bag, rate, loop, wait_for_topics, wait_for_nodes=(), start_paused=False) -> NodeSpec:
    params = {"bag": str(bag), "rate": float(rate), "loop": bool(loop), "wait_for_topics": list(wait_for_topics),
              "delay": 0.5}
    if wait_for_nodes:
        params["wait_for_nodes"] = list(wait_for_nodes)
    if start_paused:
        params["start_paused"] = True
    return NodeSpec("bag_play", "bag_play", parameters=params)


def forward_graph(sim_params: Optional[str] = None, bag: Optional[str] = None, rate: float = 1.0, loop: bool = False,
                  keep_running: bool = False, method: str = "sil", b_from_frame: bool = False,
                  start_paused: bool = False, image_transport: str = "raw", pose_source: str = "topic",
                  camera_info_file: str = "") -> list:
    """sim_camera + enhancer (+ bag_play replaying a field trial when ``bag`` is given): the forward half.

    ``sim_params`` is the fitted parameters file (``uw-sil fit --out fit.yaml``; default
    ``config/sim_camera.yaml``); the enhancer follows ``sim_camera``'s parameters. With a bag (and not
    ``keep_running`` or ``loop``) the enhancer exits ``IDLE_TIMEOUT`` s after the last frame and, being
    ``required``, ends the graph. ``bag_play`` starts once its camera and pose publishers have matched the
    enhancer and sim_camera (the enhancer subscribes once it has sim_camera's parameters), so no frame is
    lost to start-up. With ``start_paused`` the replay waits for ``bag_play``'s ``~/resume``: time for a
    recorder or viewer of ``camera/image_enhanced`` to match the enhancer, which the graph cannot wait for.

    ``image_transport``, ``pose_source`` and ``camera_info_file`` as in :func:`backward_graph`: the enhancer reads
    ``camera/image_raw/compressed``, ``panel_pose`` publishes the pose from the panel's markers, sim_camera takes
    its intrinsics from the calibration file.
    """
    sim_params = sim_params or str(share_file("config", "sim_camera.yaml"))
    idle_exit = bool(bag) and not keep_running and not loop
    camera, marker_node = _camera_input(image_transport, pose_source, camera_info_file)
    sim = dict(REPLAY_SIM_CAMERA) if bag else {}
    if camera_info_file:
        sim["camera_info_file"] = str(camera_info_file)
    nodes = [NodeSpec("sim_camera", "sim_camera", param_files=[sim_params], parameters=sim),
             _enhancer(method, b_from_frame, idle_exit, image_transport=image_transport,
                       idle_timeout=MARKER_IDLE_TIMEOUT if marker_node is not None else IDLE_TIMEOUT)]
    if marker_node is not None:
        nodes.append(marker_node)
    if bag:
        _replayed(marker_node, *nodes[:2])
        if marker_node is None:
            # without wait_for_nodes bag_play waits for a *matched* reader on each topic: the enhancer on the
            # camera, sim_camera on the poses (both are the only readers in this graph)
            nodes.append(_bag_play(bag, rate, loop, [IMAGE_TOPICS[image_transport], BACKWARD_INPUTS[2]],
                                   start_paused=start_paused))
        else:
            # no pose topic in such a bag: the camera, read by the enhancer (subscribed once sim_camera listens
            # for poses) and by panel_pose
            nodes.append(_bag_play(bag, rate, loop, [IMAGE_TOPICS[image_transport]], ["enhancer", "panel_pose"],
                                   start_paused))
    return nodes


def sil_graph(sim_params: Optional[str] = None, bag: Optional[str] = None, output_yaml: str = "", frames: int = 3,
              optimizer: str = "pso", rate: float = 1.0, loop: bool = False, max_iter: Optional[int] = None,
              stride: Optional[int] = None, keep_running: bool = False, method: str = "sil",
              b_from_frame: bool = False, start_paused: bool = False, diagnose: bool = False,
              diagnose_frames: Optional[int] = None, diagnose_max_effects: Optional[int] = None,
              diagnose_effects: str = "", output_json: str = "", image_transport: str = "raw",
              pose_source: str = "topic", camera_info_file: str = "") -> list:
    """Both halves: sim_camera + backward_fit + enhancer (+ bag_play): the fit re-parameterizes sim_camera,
    and through its parameter events the enhancer.

    With a bag the graph ends when the fit is done (as the backward graph), unless ``keep_running``; frames
    enhanced before then use ``sim_params``. ``bag_play`` starts once both backward_fit and the enhancer
    subscribe to the camera.
    """
    nodes = [n for n in backward_graph(sim_params=sim_params, bag=bag, output_yaml=output_yaml, frames=frames,
                                       optimizer=optimizer, rate=rate, loop=loop, max_iter=max_iter, stride=stride,
                                       keep_running=keep_running, start_paused=start_paused, diagnose=diagnose,
                                       diagnose_frames=diagnose_frames, diagnose_max_effects=diagnose_max_effects,
                                       diagnose_effects=diagnose_effects, output_json=output_json,
                                       image_transport=image_transport, pose_source=pose_source,
                                       camera_info_file=camera_info_file)
             if n.name != "bag_play"]
    nodes.append(_enhancer(method, b_from_frame, idle_exit=False, image_transport=image_transport))
    if bag:
        nodes[0].parameters.update(REPLAY_SIM_CAMERA)
        _replayed(None, nodes[0], nodes[-1])
        readers = ["backward_fit", "enhancer"] + (["panel_pose"] if pose_source == "markers" else [])
        readers += _camera_info_reader(camera_info_file)
        nodes.append(_bag_play(bag, rate, loop, [IMAGE_TOPICS[image_transport]], readers, start_paused))
    return nodes


# ------------------------------------------------------------------------------------------ arguments

_TRUE, _FALSE = ("true", "1", "yes", "on"), ("false", "0", "no", "off")


@dataclass(frozen=True)
class GraphArg:
    """One argument of a graph: ``name:=value`` for ``ros2 launch``, ``--name`` for ``uw-sil launch``.

    ``kind`` is ``str``, ``int``, ``float`` or ``bool`` (true/false, also 1/0, yes/no, on/off); ``default``
    None means "not given" (the builder's own default applies; an empty launch argument is the same);
    ``minimum`` bounds numbers (``strict``: the value must exceed it); ``path`` marks a file or directory
    (``uw-sil launch`` makes it absolute).
    """

    name: str
    description: str
    kind: type = str
    default: object = None
    choices: tuple = ()
    minimum: Optional[float] = None
    strict: bool = False
    path: bool = False

    @property
    def expected(self) -> str:
        """What a valid value looks like, in words."""
        if self.choices:
            return "one of " + ", ".join(self.choices)
        if self.kind is bool:
            return "true or false"
        what = {int: "an integer", float: "a number", str: "a path" if self.path else "a string"}[self.kind]
        if self.minimum is not None:
            what += f" {'>' if self.strict else '>='} {self.minimum:g}"
        return what

    @property
    def default_text(self) -> str:
        """The default as launch-argument text ('' when there is none)."""
        if self.default is None:
            return ""
        if self.kind is bool:
            return "true" if self.default else "false"
        return str(self.default)

    def parse(self, text):
        """The value of ``text`` (a string, or already a value of ``kind``); ValueError naming the argument.

        An empty string gives the default."""
        if not isinstance(text, str):
            text = self.format(text)
        text = text.strip()
        if text == "":
            return self.default
        bad = ValueError(f"argument {self.name}:={text!r} is not valid: expected {self.expected}")
        if self.choices and text not in self.choices:
            raise bad
        if self.kind is bool:
            if text.lower() not in _TRUE + _FALSE:
                raise bad
            return text.lower() in _TRUE
        try:
            value = self.kind(text)
        except ValueError:
            raise bad from None
        if self.kind is float and not abs(value) < float("inf"):   # nan, inf
            raise bad
        if self.minimum is not None and (value <= self.minimum if self.strict else value < self.minimum):
            raise bad
        return value

    def format(self, value) -> str:
        if isinstance(value, bool):
            return "true" if value else "false"
        return "" if value is None else str(value)

    @property
    def help(self) -> str:
        """The description with what is expected and the default (launch argument / option help)."""
        parts = [] if self.kind is str and not self.choices else [self.expected]
        if self.default_text:
            parts.append(f"default {self.default_text}")
        return f"{self.description} ({'; '.join(parts)})" if parts else self.description


@dataclass(frozen=True)
class Graph:
    """A node graph: its arguments and the function from their values to the nodes."""

    name: str
    description: str
    arguments: tuple
    build: Callable[..., list]           # keyword arguments named like ``arguments``; returns NodeSpecs

    def argument(self, name: str) -> GraphArg:
        for a in self.arguments:
            if a.name == name:
                return a
        raise KeyError(f"graph {self.name} has no argument {name!r}; it has "
                       + ", ".join(a.name for a in self.arguments))

    def parse(self, texts: Mapping) -> dict:
        """Every argument's value from ``texts`` (name -> text or value; missing: the default).

        ValueError names each invalid argument and what it expects."""
        unknown = set(texts) - {a.name for a in self.arguments}
        if unknown:
            raise ValueError(f"graph {self.name} has no argument(s) {', '.join(sorted(unknown))}; it has "
                             + ", ".join(a.name for a in self.arguments))
        values, errors = {}, []
        for a in self.arguments:
            try:
                values[a.name] = a.parse(texts.get(a.name, ""))
            except ValueError as e:
                errors.append(str(e))
        if errors:
            raise ValueError("; ".join(errors))
        return values

    def nodes(self, texts: Mapping = None) -> list:
        """The graph's NodeSpecs for the arguments ``texts`` (see :meth:`parse`); arguments without a value
        are left to the builder's defaults."""
        return self.build(**{k: v for k, v in self.parse(texts or {}).items() if v is not None})


BACKWARD_ARGS = (
    GraphArg("bag", "replay this field trial (rosbag2 directory, .mcap or .db3); the graph then ends after "
             "the fit", path=True),
    GraphArg("output_yaml", "write the fitted parameters here (a ROS 2 parameters file for sim_camera)", path=True),
    GraphArg("sim_params", "sim_camera's start-up parameters file (default: config/sim_camera.yaml)", path=True),
    GraphArg("frames", "K: usable frames to fit", int, 3, minimum=1),
    GraphArg("stride", "consider every n-th frame (spreads the K frames over more ranges)", int, minimum=1),
    GraphArg("optimizer", "optimizer of the backward fit", str, "pso", choices=("pso", "cmaes")),
    GraphArg("max_iter", "optimizer iterations (default: the optimizer's own)", int, minimum=1),
    GraphArg("rate", "bag replay rate (2: twice as fast as recorded)", float, 1.0, minimum=0, strict=True),
    GraphArg("loop", "replay the bag in a loop", bool, False),
    GraphArg("keep_running", "with a bag: keep the graph running after the fit, until Ctrl-C", bool, False),
    GraphArg("start_paused", "with a bag: wait for `ros2 service call /bag_play/resume std_srvs/srv/Trigger` "
             "before replaying (time to start a recorder or viewer)", bool, False),
    GraphArg("diagnose", "backward_fit diagnoses instead of fitting: finds the physics the simulation lacks "
             "(/diagnostics, /backward_fit/diagnosis) and re-parameterizes sim_camera with the extended model",
             bool, False),
    GraphArg("diagnose_frames", "with diagnose: frames diagnosed, spread over those received", int, minimum=3),
    GraphArg("diagnose_max_effects", "with diagnose: effects the greedy selection adds at most (those judged on "
             "statistics come on top)", int, minimum=1),
    GraphArg("diagnose_effects", "with diagnose: effects considered, comma-separated (default: every effect the "
             "diagnosis judges)"),
    GraphArg("output_json", "with diagnose: write the diagnosis JSON here (as uw-sil diagnose --json)", path=True),
    GraphArg("image_transport", "camera input: raw (camera/image_raw) or compressed (camera/image_raw/compressed, "
             "sensor_msgs/CompressedImage)", str, "raw", choices=("raw", "compressed")),
    GraphArg("pose_source", "panel pose: topic (panel/pose is recorded or published) or markers (the panel_pose "
             "node detects the panel's markers and publishes panel/pose)", str, "topic", choices=("topic", "markers")),
    GraphArg("camera_info_file", "camera calibration YAML (no distortion) used instead of camera/camera_info, for "
             "recordings without it", path=True),
)

_ENHANCER_ARGS = (
    GraphArg("method", "the enhancer's method: sil (the fitted model, inverted), dcp or udcp", str, "sil",
             choices=("sil", "dcp", "udcp")),
    GraphArg("b_from_frame", "the enhancer re-estimates the background on every frame from its water", bool, False),
)

FORWARD_ARGS = (
    GraphArg("bag", "replay this field trial (rosbag2 directory, .mcap or .db3); the graph then ends after its "
             "last frame", path=True),
    GraphArg("sim_params", "the fitted parameters file for sim_camera (`uw-sil fit --out fit.yaml`; default: "
             "config/sim_camera.yaml)", path=True),
    *_ENHANCER_ARGS,
    *(a for a in BACKWARD_ARGS if a.name in ("rate", "loop")),
    GraphArg("keep_running", "with a bag: keep the graph running after its last frame, until Ctrl-C", bool, False),
    *(a for a in BACKWARD_ARGS if a.name in ("start_paused", "image_transport", "pose_source", "camera_info_file")),
)

SIL_ARGS = BACKWARD_ARGS + _ENHANCER_ARGS

#: The graphs by name: ``ros2 launch uw_sil <name>.launch.py`` and ``uw-sil launch <name>``.
GRAPHS = {
    "backward": Graph("backward", "sim_camera + backward_fit (+ bag_play replaying a field trial): fit the "
                      "simulator to the first frames and re-parameterize it", BACKWARD_ARGS, backward_graph),
    "forward": Graph("forward", "sim_camera + enhancer (+ bag_play): the real frames dehazed with the "
                     "fitted model and the simulated depth", FORWARD_ARGS, forward_graph),
    "sil": Graph("sil", "sim_camera + backward_fit + enhancer (+ bag_play): both halves; the fit "
                 "re-parameterizes sim_camera and, through it, the enhancer", SIL_ARGS, sil_graph),
}


# ------------------------------------------------------------------------------------------ node output

_LOG_PROBLEM = re.compile(r"\[(?:ERROR|FATAL)\] \[[\d.]+\] \[[^\]]*\]: (.+)")
_EXCEPTION = re.compile(r"^(?:[A-Za-z_][\w.]*)(?:Error|Exception|Interrupt): .+")


def failure_reason(lines: Iterable[str]) -> str:
    """The last problem a node reported in its output: an rclpy ``[ERROR]``/``[FATAL]`` log message, or
    the last line of a Python traceback ('' when there is none)."""
    reason = ""
    for line in lines:
        line = line.strip()
        m = _LOG_PROBLEM.search(line)
        if m:
            reason = m.group(1)
        elif _EXCEPTION.match(line):
            reason = line
    return reason


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
    """The process that runs ``spec`` without ``ros2 launch``: the console script's own start
    (:mod:`uw_sil.nodes.entry`), with this interpreter."""
    return [python, "-m", "uw_sil.nodes.entry", spec.executable, *spec.arguments, *ros_args(spec)]
