"""``bag_play`` node: replay a ROS 2 bag with its recorded timing (what ``ros2 bag play`` does; rosbag2
is not on PyPI).

Messages are republished as recorded, serialized CDR bytes (no deserialization), paced by their bag
receive times divided by ``rate``. Every topic gets a reliable, volatile, keep-last(10) publisher:
reliable writers also serve best-effort readers, so ``sim_camera``/``backward_fit`` (sensor-data
QoS for images) and reliable subscribers (poses) both receive them. Topics whose message type has
no Python package installed (e.g. ``tf2_msgs`` from PyPI) are skipped with a warning, unless they
are named in ``topics``, which is then an error.

Parameters (read at start)
    ``bag`` (str, required): bag directory, ``metadata.yaml``, or ``.mcap``/``.db3`` file.
    ``rate`` (1.0): playback speed factor. ``loop`` (false): start over at the end.
    ``topics`` (string array, empty = all). ``start_paused`` (false).
    ``wait_for_topics`` (string array): start only once each of these has a subscriber -- one of each
    node named in ``wait_for_nodes`` (string array) when given, else any (``wait_timeout`` s, default
    30; then exit with an error); an entry ``NODE:TOPIC`` of ``wait_for_nodes`` waits for that node on that
    topic only (e.g. ``sim_camera:/camera/camera_info``: a camera_info published before sim_camera listens
    is lost to it, and after a short bag none comes again).
    ``delay`` (0.0 s): extra wait before the first message (gives the
    readers time to match the publishers too).
    ``clock_hz`` (0.0 = off): publish the bag time on ``/clock`` at this rate.
Services
    ``~/pause``, ``~/resume`` (std_srvs/Trigger).

The node exits (status 0) after the last message has been acknowledged by the reliable readers,
unless ``loop`` is set.
"""
from __future__ import annotations

import importlib
import sys
import time

import rclpy
from rcl_interfaces.msg import FloatingPointRange, ParameterDescriptor
from rclpy.duration import Duration
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock
from std_srvs.srv import Trigger

from ..bags import iter_raw, open_bag
from . import declare_string_array, executor_for, run_node


def _float_range(lo: float, hi: float) -> list:
    return [FloatingPointRange(from_value=lo, to_value=hi, step=0.0)]

PLAYBACK_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10, reliability=ReliabilityPolicy.RELIABLE,
                          durability=DurabilityPolicy.VOLATILE)


def message_class(msgtype: str):
    """rclpy message class of a ROS type name such as ``'sensor_msgs/msg/Image'`` (ImportError if missing)."""
    try:
        from rosidl_runtime_py.utilities import get_message
    except ImportError:  # not on PyPI: import the generated module directly
        pkg, kind, name = msgtype.split("/") if msgtype.count("/") == 2 else (None, None, None)
        if kind != "msg":
            raise ImportError(f"not a ROS message type name: {msgtype!r}") from None
        module = importlib.import_module(f"{pkg}.msg")
        try:
            return getattr(module, name)
        except AttributeError:
            raise ImportError(f"package {pkg} has no message {name}") from None
    try:
        return get_message(msgtype)
    except (AttributeError, ValueError, ModuleNotFoundError) as e:
        raise ImportError(str(e)) from None


class BagPlayNode(Node):
    def __init__(self, **kwargs):
        super().__init__("bag_play", **kwargs)
        for name, default, description, ranges in (
                ("bag", "", "bag directory, metadata.yaml, or .mcap/.db3 file (required)", {}),
                ("rate", 1.0, "playback speed factor", {"floating_point_range": _float_range(0.01, 100.0)}),
                ("loop", False, "start over at the end of the bag", {}),
                ("start_paused", False, "wait for ~/resume before playing", {}),
                ("delay", 0.0, "extra wait before the first message [s]", {"floating_point_range": _float_range(0.0, 3600.0)}),
                ("wait_timeout", 30.0, "how long to wait for wait_for_topics' subscribers [s]",
                 {"floating_point_range": _float_range(0.0, 3600.0)}),
                ("clock_hz", 0.0, "publish the bag time on /clock at this rate (0: off) [Hz]",
                 {"floating_point_range": _float_range(0.0, 1000.0)})):
            self.declare_parameter(name, default, ParameterDescriptor(
                description=f"{description}; read at start", read_only=True, **ranges))
        for name, description in (("topics", "topics to play (empty: all)"),
                                  ("wait_for_topics", "start only once each of these topics has a subscriber"),
                                  ("wait_for_nodes", "... a subscriber of each of these nodes (empty: any)")):
            declare_string_array(self, name, ParameterDescriptor(description=f"{description}; read at start",
                                                                 read_only=True))
        g = self._param
        self.bag, self.rate, self.loop = g("bag"), float(g("rate")), bool(g("loop"))
        if not self.bag:
            raise ValueError("parameter 'bag' is required (a bag directory, .mcap or .db3 file)")
        if not self.rate > 0:
            raise ValueError(f"rate must be > 0, got {self.rate}")
        info = open_bag(self.bag)
        wanted = list(g("topics") or [])
        missing = [t for t in wanted if t not in info.topics]
        if missing:
            raise ValueError(f"topics not in bag {info.path}: {missing}; it has {sorted(info.topics)}")
        self.publishers_ = {}
        for name in wanted or sorted(info.topics):
            msgtype = info.topics[name].msgtype
            try:
                cls = message_class(msgtype)
            except ImportError as e:
                if wanted:
                    raise ValueError(f"cannot play {name}: message type {msgtype} is not installed ({e})") from None
                self.get_logger().warning(f"skipping {name}: message type {msgtype} is not installed ({e})")
                continue
            self.publishers_[name] = self.create_publisher(cls, name, PLAYBACK_QOS)
        if not self.publishers_:
            raise ValueError(f"nothing to play in {info.path}")
        self.topics = list(self.publishers_)
        self.total = sum(info.topics[t].count or 0 for t in self.topics)
        self.start_ns = info.start_ns
        self.end_ns = info.end_ns
        self.get_logger().info(f"{info.path}: {self.total} messages on {len(self.topics)} topics over "
                               f"{info.duration_s:.2f} s, playing at rate {self.rate:g}")
        self.paused = bool(g("start_paused"))
        self._paused_since = time.monotonic() if self.paused else None
        self.create_service(Trigger, "~/pause", self._on_pause)
        self.create_service(Trigger, "~/resume", self._on_resume)
        if self.paused:
            self.get_logger().info(f"paused: ros2 service call {self.get_fully_qualified_name()}/resume "
                                   "std_srvs/srv/Trigger starts the replay")
        self.played = 0
        self._t0_wall = None   # wall time (monotonic) at which bag time start_ns is played
        if g("clock_hz") > 0:
            self.pub_clock = self.create_publisher(Clock, "/clock", 10)
            self.create_timer(1.0 / g("clock_hz"), self._publish_clock)

    def _param(self, name: str):
        return self.get_parameter(name).value

    # ------------------------------------------------------------------ pause / resume
    def _set_paused(self, paused: bool) -> bool:
        if paused == self.paused:
            return False
        now = time.monotonic()
        if paused:
            self._paused_since = now
        else:
            if self._t0_wall is not None:
                self._t0_wall += now - self._paused_since
            self._paused_since = None
        self.paused = paused
        self.get_logger().info("paused" if paused else "resumed")
        return True

    def _on_pause(self, _req, resp):
        resp.success = self._set_paused(True)
        resp.message = "paused" if resp.success else "already paused"
        return resp

    def _on_resume(self, _req, resp):
        resp.success = self._set_paused(False)
        resp.message = "resumed" if resp.success else "not paused"
        return resp

    # ------------------------------------------------------------------ timing
    def bag_time_now(self) -> int:
        """The bag time (ns) being played now: it stands at the bag's end after the last message until a loop
        starts again (a bag has no time after its end; a late restart on a busy machine must not show one)."""
        if self._t0_wall is None:
            return self.start_ns
        now = self._paused_since if self.paused else time.monotonic()
        return min(self.start_ns + int((now - self._t0_wall) * self.rate * 1e9), self.end_ns)

    def _publish_clock(self):
        t = self.bag_time_now()
        msg = Clock()
        msg.clock.sec, msg.clock.nanosec = divmod(t, 1_000_000_000)
        self.pub_clock.publish(msg)

    def _wait(self, executor, until, seconds: float) -> bool:
        """Serve callbacks until ``until()`` is true (or ``seconds`` passed); True if it became true."""
        deadline = time.monotonic() + seconds
        while not until():
            left = deadline - time.monotonic()
            if left <= 0 or not self.context.ok():
                return False
            executor.spin_once(timeout_sec=min(left, 0.05))
        return True

    # ------------------------------------------------------------------ playing
    def wait_for_readers(self, executor) -> bool:
        g = self._param
        everywhere, only = set(), {}
        for entry in g("wait_for_nodes") or []:
            node, on_one, topic = entry.partition(":")
            if on_one:
                only.setdefault(topic, set()).add(node)
            else:
                everywhere.add(node)
        topics = list(g("wait_for_topics") or [])
        for topic in topics + [t for t in only if t not in topics]:
            pub = self.publishers_.get(topic)
            if pub is None:
                raise ValueError(f"wait_for_topics: {topic} is not played")
            nodes = (everywhere if topic in topics else set()) | only.get(topic, set())

            def subscribed():
                if not nodes:
                    return pub.get_subscription_count() > 0
                return nodes <= {i.node_name for i in self.get_subscriptions_info_by_topic(pub.topic_name)}
            if not self._wait(executor, subscribed, g("wait_timeout")):
                if self.context.ok():
                    there = {i.node_name for i in self.get_subscriptions_info_by_topic(pub.topic_name)}
                    who = (f"{', '.join(sorted(nodes - there))} not subscribed to" if nodes
                           else "no subscriber on")
                    self.get_logger().error(f"{who} {topic} after {g('wait_timeout'):g} s")
                return False
        self._wait(executor, lambda: False, g("delay"))
        return self.context.ok()

    def play(self, executor) -> bool:
        """Play the bag once (or forever with ``loop``); False if interrupted."""
        last_log = time.monotonic()
        while True:
            self._t0_wall = time.monotonic()
            if self.paused:
                self._paused_since = self._t0_wall
            with iter_raw(self.bag, self.topics) as stream:
                for m in stream:
                    while self.paused or self.bag_time_now() < m.log_time_ns:
                        if not self.context.ok():
                            return False
                        wait = 0.05 if self.paused else (m.log_time_ns - self.bag_time_now()) / self.rate / 1e9
                        executor.spin_once(timeout_sec=min(max(wait, 0.0), 0.05))
                    if not self.context.ok():   # shut down by a callback of the last spin (the message was due)
                        return False
                    self.publishers_[m.topic].publish(bytes(m.data))
                    self.played += 1
                    if time.monotonic() - last_log >= 2.0:
                        last_log = time.monotonic()
                        self.get_logger().info(f"played {self.played} messages, bag time "
                                               f"{(m.log_time_ns - self.start_ns) / 1e9:.2f} s")
                    executor.spin_once(timeout_sec=0.0)
                for err in stream.report.errors:
                    self.get_logger().warning(f"bag: {err}")
            if not self.loop:
                break
            self.get_logger().info(f"end of bag after {self.played} messages: looping")
        for pub in self.publishers_.values():
            if not pub.wait_for_all_acked(Duration(seconds=5)):
                self.get_logger().warning(f"{pub.topic_name}: not every reliable reader acknowledged the last "
                                          "messages within 5 s")
        self.get_logger().info(f"done: played {self.played} messages")
        return True


def _spin(node) -> int:
    with executor_for(node) as executor:
        if not node.wait_for_readers(executor) or not node.play(executor):
            return 1 if rclpy.ok() else 0   # interrupted (Ctrl-C) is not an error
    return 0


def main(args=None):
    return run_node(BagPlayNode, _spin, args=args, name="bag_play", user_errors=(ValueError, FileNotFoundError),
                    doc=__doc__)


if __name__ == "__main__":
    sys.exit(main())
