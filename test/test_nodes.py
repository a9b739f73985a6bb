"""The ROS 2 nodes: sim_camera and bag_play in-process (one rclpy Context per test), the backward graph
end to end as `uw-sil launch` subprocesses on a tiny synthetic bag.

Every test that touches DDS uses its own ROS_DOMAIN_ID and ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST.
"""
import importlib.util
import signal
import struct
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from conftest import import_or_skip  # noqa: E402  (skips locally, fails in CI when rclpy is missing)

rclpy = import_or_skip("rclpy", reason="ROS 2 Python packages (the `ros` extra) are not installed")

# rclpy's parameter machinery imports lark, which imports deprecated sre_* modules
pytestmark = pytest.mark.filterwarnings("ignore:module 'sre_:DeprecationWarning")

from geometry_msgs.msg import PoseStamped  # noqa: E402
from rcl_interfaces.msg import ParameterType  # noqa: E402
from rclpy.context import Context  # noqa: E402
from rclpy.duration import Duration  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.parameter_client import AsyncParameterClient  # noqa: E402
from rclpy.qos import DurabilityPolicy, QoSProfile, qos_profile_sensor_data  # noqa: E402
from sensor_msgs.msg import CameraInfo, Image  # noqa: E402
from std_msgs.msg import String  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402

from uw_sil.fit.backward import fit_bag  # noqa: E402
from uw_sil.bags import iter_raw, open_bag  # noqa: E402
from uw_sil.sim.camera import CameraModel  # noqa: E402
from uw_sil.bags.imgmsg import depth_to_image_fields, image_to_rgb  # noqa: E402
from uw_sil.sim.params import RGB_NAMES, UnderwaterParams  # noqa: E402
from uw_sil.sim.scene import facing_pose  # noqa: E402
from uw_sil.sim.simcam import SimCamera  # noqa: E402
from uw_sil.bags.synth import synthesize_trial  # noqa: E402
from uw_sil.sim.transforms import matrix_to_pose  # noqa: E402

from rosproc import Proc, domain_id, logs_on_failure, ros_env, spin_until, wait_future  # noqa: E402

SMALL = CameraModel.from_fov(160, 120, 70.0)
TRUTH = UnderwaterParams(a=(0.40, 0.12, 0.08), b=(0.07, 0.33, 0.43), rho_f=0.10)
TIMEOUT = 30.0        # discovery of a peer, a service answer: normally well under a second
START = 120.0         # a graph of node processes starting, fitting, ending: 10-60 s on a loaded 2-core machine
STOP = 30.0           # the graph ending after Ctrl-C (test_node_faults holds the nodes to 5 s)
MAX_ITER = 30


def _stamp_ns(msg) -> int:
    return msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec


# ------------------------------------------------------------------------------------------ imgmsg


def test_depth_to_image_fields_is_rep118_little_endian():
    d = np.array([[1.5, np.inf], [0.25, np.nan]], dtype=np.float64)
    f = depth_to_image_fields(d)
    assert (f["height"], f["width"], f["encoding"], f["is_bigendian"], f["step"]) == (2, 2, "32FC1", 0, 8)
    back = np.frombuffer(f["data"], dtype="<f4").reshape(2, 2)
    np.testing.assert_array_equal(back, d.astype(np.float32))   # inf and NaN survive
    assert f["data"][:8] == struct.pack("<ff", 1.5, np.inf)
    img = Image(**f)
    assert bytes(img.data) == f["data"]
    with pytest.raises(ValueError, match="H, W"):
        depth_to_image_fields(np.zeros((2, 2, 1)))
    with pytest.raises(ValueError, match="floating"):
        depth_to_image_fields(np.zeros((2, 2), np.uint16))


# ------------------------------------------------------------------------------------------ sim_camera


class Probe(Node):
    """Publishes poses; collects everything sim_camera publishes, by stamp.

    Its subscriptions have sim_camera's best-effort sensor QoS; no frame is lost by design here: the nodes
    share the test's participant (one rclpy Context), so Fast DDS delivers in-process without a transport,
    and one pose at a time makes one frame per topic (a history of 5 cannot overflow)."""

    TOPICS = {"sim/image_raw": Image, "sim/image_clean": Image, "sim/depth": Image, "sim/mask": Image,
              "sim/camera_info": CameraInfo}

    def __init__(self, context):
        super().__init__("probe", context=context)
        self.pub_pose = self.create_publisher(PoseStamped, "panel/pose", 10)
        self.got = {t: {} for t in self.TOPICS}
        self.subs = [self.create_subscription(cls, t, lambda m, t=t: self.got[t].__setitem__(_stamp_ns(m), m),
                                              qos_profile_sensor_data) for t, cls in self.TOPICS.items()]
        self.params = AsyncParameterClient(self, "sim_camera")

    def publish_pose(self, T, stamp_ns: int, frame_id="cam_optical"):
        msg = PoseStamped()
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp_ns, 1_000_000_000)
        msg.header.frame_id = frame_id
        pos, quat = matrix_to_pose(T)
        msg.pose.position.x, msg.pose.position.y, msg.pose.position.z = (float(v) for v in pos)
        (msg.pose.orientation.x, msg.pose.orientation.y, msg.pose.orientation.z,
         msg.pose.orientation.w) = (float(v) for v in quat)
        self.pub_pose.publish(msg)

    def frame(self, stamp_ns: int):
        if all(stamp_ns in g for g in self.got.values()):
            return {t: g[stamp_ns] for t, g in self.got.items()}
        return None


@pytest.mark.parametrize("workers", [0, 2])
def test_sim_camera_renders_poses_and_takes_parameters_live(ros, workers):
    """The same frames whether made in the pose's callback or by model threads (``workers``: uw_sil.sim.stream)."""
    from uw_sil.nodes.sim_camera import SimCameraNode

    start = UnderwaterParams(a=(0.3, 0.1, 0.05), b=(0.1, 0.3, 0.4), rho_f=0.05)
    overrides = [Parameter(n, value=v) for n, v in start.as_dict().items()]
    overrides += [Parameter("width", value=SMALL.width), Parameter("height", value=SMALL.height),
                  Parameter("hfov_deg", value=70.0), Parameter("workers", value=workers)]
    sim = SimCameraNode(context=ros, parameter_overrides=overrides)
    probe = Probe(ros)
    ex = SingleThreadedExecutor(context=ros)
    ex.add_node(sim)
    ex.add_node(probe)
    try:
        # matched from both ends: sim_camera publishes an image only to a subscription it has matched
        sim_pubs = (sim.pub_image, sim.pub_clean, sim.pub_depth, sim.pub_mask, sim.pub_info)
        sim_pose = [s for s in sim.subscriptions if s.topic_name == "/panel/pose"]
        spin_until(ex, lambda: probe.pub_pose.get_subscription_count() > 0
                   and all(s.get_publisher_count() > 0 for s in probe.subs + sim_pose)
                   and all(p.get_subscription_count() > 0 for p in sim_pubs), what="topic matching",
                   detail=lambda: f"probe: pose subscribers {probe.pub_pose.get_subscription_count()}, publishers "
                                  f"{[s.get_publisher_count() for s in probe.subs]}; sim_camera: subscribers "
                                  f"{[p.get_subscription_count() for p in sim_pubs]}")
        T = facing_pose(1.8, yaw=0.1)
        probe.publish_pose(T, 1_000_000_123)
        spin_until(ex, lambda: probe.frame(1_000_000_123) is not None, what="sim topics for the first pose")
        f1 = probe.frame(1_000_000_123)
        for m in f1.values():
            assert m.header.frame_id == "cam_optical"
        with SimCamera(start, camera=SMALL) as ref:    # an independent renderer with the same parameters
            want = ref.render(T)
        img = image_to_rgb(f1["sim/image_raw"])
        np.testing.assert_array_equal(img, want.image_uint8())
        d = f1["sim/depth"]
        assert d.encoding == "32FC1" and (d.width, d.height) == (SMALL.width, SMALL.height)
        depth = np.frombuffer(bytes(d.data), "<f4").reshape(d.height, d.width)
        hit = np.isfinite(want.render.depth)
        assert 0.05 < hit.mean() < 1.0
        np.testing.assert_array_equal(np.isfinite(depth), hit)
        np.testing.assert_allclose(depth[hit], want.render.depth[hit], atol=1e-5)
        assert depth[hit].min() > 1.0 and depth[hit].max() < 3.0   # panel ~1.8 m ahead, seafloor behind
        mask = f1["sim/mask"]
        assert mask.encoding == "mono8"
        np.testing.assert_array_equal(np.frombuffer(bytes(mask.data), np.uint8).reshape(d.height, d.width),
                                      want.render.labels)
        info = f1["sim/camera_info"]
        np.testing.assert_allclose(np.asarray(info.k), SMALL.K.ravel())
        assert (info.width, info.height) == (SMALL.width, SMALL.height)

        # live re-parameterization through the parameter services
        assert probe.params.wait_for_services(timeout_sec=TIMEOUT)
        new = UnderwaterParams(a=(0.8, 0.2, 0.1), b=(0.3, 0.2, 0.1), rho_f=0.2)
        res = wait_future(ex, probe.params.set_parameters(
            [Parameter(n, value=v) for n, v in new.as_dict().items()] + [Parameter("fog_mode", value="exp")]))
        assert all(r.successful for r in res.results), [r.reason for r in res.results]
        probe.publish_pose(T, 2_000_000_000)
        spin_until(ex, lambda: probe.frame(2_000_000_000) is not None, what="sim topics for the second pose")
        img2 = image_to_rgb(probe.frame(2_000_000_000)["sim/image_raw"])
        assert np.abs(img2.astype(int) - img.astype(int)).mean() > 10
        with SimCamera(new, camera=SMALL, fog="exp") as ref:
            np.testing.assert_array_equal(img2, ref.render(T).image_uint8())

        # invalid values are rejected with a reason and change nothing
        for bad, why in ((Parameter("b_r", value=1.5), "b_r"), (Parameter("fog_mode", value="bogus"), "bogus"),
                         (Parameter("a_g", value=1), "type")):
            r = wait_future(ex, probe.params.set_parameters([bad])).results[0]
            assert not r.successful and why in r.reason, r.reason
        r = wait_future(ex, probe.params.set_parameters([Parameter("width", value=320)])).results[0]
        assert not r.successful and "read-only" in r.reason
        values = wait_future(ex, probe.params.get_parameters(["b_r", "a_g", "fog_mode"])).values
        assert [values[0].double_value, values[1].double_value, values[2].string_value] == [0.3, 0.2, "exp"]
        assert sim.sim.params == new and sim.sim.fog == "exp"
    finally:
        ex.shutdown()
        sim.destroy_node()
        probe.destroy_node()


# ------------------------------------------------------------------------------------------ bag_play


@pytest.fixture(scope="module")
def trial(tmp_path_factory):
    out = tmp_path_factory.mktemp("trial") / "trial.mcap"
    synthesize_trial(out, n_frames=12, seed=3, params=TRUTH, camera=SMALL, start_m=3.5, end_m=1.2)
    return out


class TimedPublisher:
    """Stands in for a publisher of bag_play: records when each message is handed to it (then publishes), and
    which topic, in ``topics``."""

    def __init__(self, pub, log, topic=None, topics=None):
        self._pub, self._log, self._topic, self._topics = pub, log, topic, topics

    def publish(self, data):
        self._log.append(time.monotonic())
        if self._topics is not None:
            self._topics.append(self._topic)
        self._pub.publish(data)

    def __getattr__(self, name):
        return getattr(self._pub, name)


def test_bag_play_waits_for_a_node_on_one_topic_only(ros, trial):
    """``wait_for_nodes`` entries ``NODE:TOPIC`` wait for that node on that topic alone (the graphs wait for
    sim_camera on the camera_info, which it reads, not on the camera, which it does not); plain entries wait
    on every topic of ``wait_for_topics``, as before; such a topic the bag does not play is an error."""
    from uw_sil.nodes.bag_play import BagPlayNode

    def player_for(nodes):
        return BagPlayNode(context=ros, parameter_overrides=[
            Parameter("bag", value=str(trial)), Parameter("wait_for_topics", value=["/camera/image_raw"]),
            Parameter("wait_for_nodes", value=nodes), Parameter("wait_timeout", value=1.0)])

    player = player_for(["fitter", "probe:/camera/camera_info"])
    fitter, probe = Node("fitter", context=ros), Node("probe", context=ros)
    ex = SingleThreadedExecutor(context=ros)
    for n in (player, fitter, probe):
        ex.add_node(n)
    try:
        fitter.create_subscription(Image, "/camera/image_raw", lambda m: None, qos_profile_sensor_data)
        assert not player.wait_for_readers(ex)                # the fitter alone: probe has not subscribed
        probe.create_subscription(CameraInfo, "/camera/camera_info", lambda m: None, qos_profile_sensor_data)
        assert player.wait_for_readers(ex)                    # probe on camera_info only, the fitter on the camera
        missing = player_for(["probe:/sonar/image"])
        ex.add_node(missing)
        with pytest.raises(ValueError, match="/sonar/image is not played"):
            missing.wait_for_readers(ex)
        missing.destroy_node()
    finally:
        ex.shutdown()
        for n in (player, fitter, probe):
            n.destroy_node()


def test_bag_play_replays_with_recorded_timing(ros, trial):
    from uw_sil.nodes.bag_play import BagPlayNode

    rate = 2.0
    player = BagPlayNode(context=ros, parameter_overrides=[
        Parameter("bag", value=str(trial)), Parameter("rate", value=rate), Parameter("start_paused", value=True),
        Parameter("topics", value=["/camera/image_raw", "/panel/pose"])])
    listener = Node("listener", context=ros)
    got = []
    # images read best effort, as sim_camera/backward_fit read a camera: none is lost here (one participant,
    # in-process delivery; the player spins the executor between messages, so a history of 5 does not overflow)
    for topic, cls, qos in (("/camera/image_raw", Image, qos_profile_sensor_data), ("/panel/pose", PoseStamped, 10)):
        listener.create_subscription(cls, topic, lambda m, t=topic: got.append((t, _stamp_ns(m), time.monotonic())),
                                     qos)
    info_sub = listener.create_subscription(CameraInfo, "/camera/camera_info", lambda m: got.append("info"), 10)
    resume = listener.create_client(Trigger, "/bag_play/resume")
    published = []
    handed = []
    player.publishers_ = {t: TimedPublisher(p, published, t, handed) for t, p in player.publishers_.items()}
    ex = SingleThreadedExecutor(context=ros)
    ex.add_node(player)
    ex.add_node(listener)
    try:
        assert player.topics == ["/camera/image_raw", "/panel/pose"]
        assert info_sub.get_publisher_count() == 0            # not selected: no publisher
        spin_until(ex, lambda: all(p.get_subscription_count() > 0 for p in player.publishers_.values()),
                   what="subscriptions")
        assert resume.wait_for_service(timeout_sec=TIMEOUT)
        t_resume = []

        def do_resume():  # from a timer of the listener, while play() serves the executor
            t_resume.append(time.monotonic())
            resume.call_async(Trigger.Request())
            timer.cancel()
        timer = listener.create_timer(0.4, do_resume)
        t0 = time.monotonic()
        assert player.play(ex)
        spin_until(ex, lambda: len(got) >= 24, what="all 24 messages (12 images, 12 poses)",
                   detail=lambda: f"got {len(got)}: {[t for t, *_ in got]}")
    finally:
        ex.shutdown()
        player.destroy_node()
        listener.destroy_node()
    recorded = [(m.topic, m.log_time_ns) for m in iter_raw(trial, ["/camera/image_raw", "/panel/pose"])]
    # all, stamps as recorded, handed over in the recorded order; delivered in order on each topic (between two
    # topics the executor may take either callback first when both are ready: at load 8 an image came before
    # the pose recorded 0.1 s earlier)
    assert handed == [t for t, _ in recorded]
    for topic in ("/camera/image_raw", "/panel/pose"):
        assert [s for t, s, _ in got if t == topic] == [s for t, s in recorded if t == topic], topic
    assert player.played == 24
    first = got[0][2]
    assert first >= t_resume[0] >= t0 + 0.35                  # nothing before ~/resume
    # Paced by the recorded receive times at rate 2 (12 frames 0.1 s apart: 0.55 s), checked on the times the
    # player handed each message over, not on delivery (which a busy machine delays at random):
    # never early -- message i no sooner than (its recorded offset) / rate after the resume request -- ...
    assert len(published) == 24
    due = [(t - recorded[0][1]) / 1e9 / rate for _, t in recorded]
    assert all(p - t_resume[0] >= d - 1e-3 for p, d in zip(published, due)), list(zip(published, due))
    # ... and on time: the schedule is absolute (a late message does not delay the next ones), so the median
    # lateness stays small under load, while playing at rate 1 instead of 2 would make it 0.28 s
    lateness = sorted(p - published[0] - d for p, d in zip(published, due))
    assert lateness[len(lateness) // 2] < 0.1, lateness


def test_bag_play_loops_and_publishes_the_bag_clock(ros, trial):
    from rosgraph_msgs.msg import Clock

    from uw_sil.nodes.bag_play import BagPlayNode

    info = open_bag(trial)
    player = BagPlayNode(context=ros, parameter_overrides=[
        Parameter("bag", value=str(trial)), Parameter("rate", value=10.0), Parameter("loop", value=True),
        Parameter("topics", value=["/panel/pose"]), Parameter("clock_hz", value=50.0)])
    listener = Node("listener", context=ros)
    poses, clock = [], []

    def on_pose(m):
        poses.append(_stamp_ns(m))
        if len(poses) == 30:      # two and a half passes through the bag: stop like Ctrl-C would
            ros.try_shutdown()
    pose_sub = listener.create_subscription(PoseStamped, "/panel/pose", on_pose, 100)
    listener.create_subscription(Clock, "/clock", lambda m: clock.append(m.clock.sec * 10**9 + m.clock.nanosec), 100)
    ex = SingleThreadedExecutor(context=ros)
    ex.add_node(player)
    ex.add_node(listener)
    try:
        spin_until(ex, lambda: pose_sub.get_publisher_count() > 0, what="matching")
        assert not player.play(ex)                              # interrupted, never ended by itself
    finally:
        ex.shutdown()
        player.destroy_node()
        listener.destroy_node()
    stamps = [m.log_time_ns for m in iter_raw(trial, "/panel/pose")]
    assert poses[:30] == (stamps * 3)[:30]
    # the bag time: within the bag (it stands at the end until the loop restarts, however late that is: an
    # allowance of 100 ms of bag time, 10 ms of wall time at rate 10, failed once beside a CPU hog)
    assert len(clock) >= 5 and all(info.start_ns <= c <= info.end_ns for c in clock), clock


def test_bag_play_rejects_missing_topics_and_types(ros, trial, tmp_path):
    from uw_sil.nodes.bag_play import BagPlayNode, message_class

    assert message_class("sensor_msgs/msg/Image") is Image
    with pytest.raises(ImportError):
        message_class("no_such_pkg/msg/Thing")
    with pytest.raises(ImportError):
        message_class("sensor_msgs/msg/NoSuchMessage")
    with pytest.raises(ValueError, match="not in bag"):
        BagPlayNode(context=ros, parameter_overrides=[Parameter("bag", value=str(trial)),
                                                      Parameter("topics", value=["/nope"])])
    with pytest.raises(ValueError, match="required"):
        BagPlayNode(context=ros)
    with pytest.raises(FileNotFoundError):
        BagPlayNode(context=ros, parameter_overrides=[Parameter("bag", value=str(tmp_path / "missing.mcap"))])


def test_backward_fit_keeps_every_frame_of_a_replay_through_a_stall(ros, trial):
    """backward_fit is single-threaded and renders in its callbacks: its first frame (a new OpenGL context at
    the camera's size, the model uploaded) took 0.95-1.2 s on a loaded machine and over 3 s beside a CPU hog,
    while the replay went on at 10 frames/s. What arrives meanwhile waits in the subscriptions' queues:
    a pose queue of 10 lost pose #1 (11 poses arrived), image #1 found no pose within max_dt and was dropped,
    and the node fitted other frames than `uw-sil fit` (test_backward_graph_refits_... failed 1 run in 8, and
    10 of 10 beside a busy loop per core); and a stall longer than idle_timeout made the node fit the one frame
    it had, the replay's frames still queued, taking its own stall for the end of the bag.

    Here the node's first frame lasts as long as the rest of the replay (frames 1-11, each acknowledged by the
    node's readers) plus more than idle_timeout (the graphs' 3 s: a shorter one would make the test fail when
    the loaded machine leaves the node without CPU for that long between two callbacks, which is not the
    fault tested here); the time.sleep below stands for that slow render, it is not a wait for anything.
    Then every frame must be paired, and the collection still be running. The input is read reliably, so
    what could be lost is only what the node's queues cannot hold.
    """
    from uw_sil.nodes.backward_fit import BackwardFitNode
    from uw_sil.nodes.bag_play import BagPlayNode
    from uw_sil.nodes.graph import IDLE_TIMEOUT as idle

    topics = ["/camera/image_raw", "/camera/camera_info", "/panel/pose"]
    fit = BackwardFitNode(context=ros, parameter_overrides=[
        Parameter("frames", value=13), Parameter("stride", value=1), Parameter("reliable_input", value=True),
        Parameter("idle_timeout", value=idle)])
    player = BagPlayNode(context=ros, parameter_overrides=[
        Parameter("bag", value=str(trial)), Parameter("topics", value=topics)])
    ex_play, ex_fit = SingleThreadedExecutor(context=ros), SingleThreadedExecutor(context=ros)
    ex_play.add_node(player)
    ex_fit.add_node(fit)
    messages = [(m.topic, bytes(m.data)) for m in iter_raw(trial, topics)]
    assert len(messages) == 36
    sel, st = fit.selector, fit.sync.stats
    real_offer, stalls = sel.offer, []

    def publish(msgs):
        for topic, data in msgs:
            player.publishers_[topic].publish(data)
        for pub in player.publishers_.values():
            assert pub.wait_for_all_acked(Duration(seconds=TIMEOUT)), f"{pub.topic_name} not acked"

    def slow_offer(sample):
        if not stalls:
            t0 = time.monotonic()
            publish(messages[3:])             # frames 1-11 arrive while the node is busy with frame 0
            time.sleep(idle + 0.5)            # the rest of the slow first render (no wait for anything)
            stalls.append(time.monotonic() - t0)
        return real_offer(sample)
    sel.offer = slow_offer
    try:
        # matched on both sides (the player's writers and the node's readers) before the first message
        spin_until(ex_play, lambda: all(p.get_subscription_count() > 0 for p in player.publishers_.values())
                   and all(s.get_publisher_count() > 0 for s in fit.subs), what="the replay's topics matched")
        publish(messages[:3])                 # frame 0: image, camera_info, pose
        spin_until(ex_fit, lambda: fit.selector is not sel or sel.scanned + st.dropped >= 12,
                   what="backward_fit to decide all 12 images (paired or dropped)",
                   detail=lambda: f"received {st.received}, {st.matched} matched, dropped {st.dropped_no_partner}")
    finally:
        ex_play.shutdown()
        ex_fit.shutdown()
        player.destroy_node()
        fit.destroy_node()
    assert stalls and stalls[0] > idle
    assert st.received == [12, 12, 12] and st.dropped == 0, (st.received, st.dropped_no_partner)
    assert fit.selector is sel and fit.fit_thread is None, "fitted before the queued frames were taken"
    assert sel.scanned == 12 and [f.index for f in sel.frames] == list(range(12))


# ------------------------------------------------------------------------------------------ the graph


@pytest.mark.slow
def test_backward_graph_refits_sim_camera_and_stops_on_ctrl_c(trial, tmp_path, monkeypatch):
    """bag_play -> backward_fit -> sim_camera re-parameterized; then SIGINT ends everything cleanly."""
    domain = domain_id()
    fit_yaml = tmp_path / "fit.yaml"
    cmd = [sys.executable, "-m", "uw_sil.cli", "launch", "backward", "--bag", str(trial), "--frames", "3",
           "--stride", "4", "--optimizer", "cmaes", "--max-iter", str(MAX_ITER), "--output-yaml", str(fit_yaml),
           "--keep-running"]
    launch = Proc(cmd, ros_env(domain), name="uw-sil launch backward")
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    ctx = Context()
    rclpy.init(context=ctx, domain_id=domain)
    node = Node("test_watcher", context=ctx)
    status = []
    node.create_subscription(String, "/backward_fit/status", lambda m: status.append(m.data),
                             QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL))
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    try:
        with logs_on_failure(launch):
            spin_until(ex, lambda: any(s.startswith(("done", "failed")) for s in status)
                       or launch.popen.poll() is not None, timeout=START,
                       what="backward_fit's final status (done/failed) on /backward_fit/status",
                       detail=lambda: f"statuses received: {status}")
            assert status and status[-1].startswith("done"), status
            assert "re-parameterized" in status[-1]
            fitted = yaml.safe_load(fit_yaml.read_text())["/**"]["ros__parameters"]
            client = AsyncParameterClient(node, "sim_camera")
            assert client.wait_for_services(timeout_sec=TIMEOUT), "sim_camera's parameter services"
            values = wait_future(ex, client.get_parameters(list(RGB_NAMES) + ["fog_mode", "noise_sigma"]),
                                 what="sim_camera's parameters").values
            live = {n: v.double_value for n, v in zip(RGB_NAMES, values)
                    if v.type == ParameterType.PARAMETER_DOUBLE}
            assert live == {n: fitted[n] for n in RGB_NAMES}        # sim_camera runs with exactly the fit
            assert values[-2].string_value == fitted["fog_mode"] == "exp2"
            assert values[-1].double_value == fitted["noise_sigma"] > 0
            # The node fits exactly what `uw-sil fit` fits offline on the same frames (how close that comes to
            # the truth is test_backward's subject); and it improved θ over the start of the search.
            offline = fit_bag(trial, k=3, stride=4, method="cmaes", max_iter=MAX_ITER, seed=0)
            fitting = next(s for s in status if s.startswith("fitting"))
            for f in offline.frames:
                assert f"#{f.index} ({f.range_median:.2f} m" in fitting, fitting
            np.testing.assert_array_equal(UnderwaterParams.from_dict(live).as_vector(),
                                          offline.params.as_vector(), err_msg="the node's fit differs from the offline fit")
            theta = status[-1].split("theta ")[1].split(" in ")[0].split(" -> ")
            assert float(theta[1]) == pytest.approx(offline.theta_best, abs=5e-5)     # printed with 4 decimals
            assert offline.theta_best >= offline.theta_x0           # never worse than the optimizer's start point
            # Ctrl-C: the launcher forwards SIGINT and every node ends cleanly
            assert launch.popen.poll() is None, "the graph ended although --keep-running was given"
            launch.popen.send_signal(signal.SIGINT)
            launch.wait_group(STOP)
            text = launch.text
            assert launch.popen.returncode == 0
            assert "SIGINT received" in text and "all nodes ended cleanly" in text
            pids = [int(line.split("(pid ")[1].split(")")[0]) for line in text.splitlines() if "(pid " in line]
            assert len(pids) == 3
            for pid in pids:
                assert not Path(f"/proc/{pid}").exists(), f"node process {pid} outlived the launcher"
            assert "bag_play exited with status 0" in text     # the bag ended before the graph did
    finally:
        launch.stop()
        ex.shutdown()
        node.destroy_node()
        ctx.try_shutdown()


@pytest.mark.slow
def test_backward_graph_with_a_bag_ends_by_itself(trial, tmp_path):
    """Asked for more frames than the bag has: the frames there are fitted once the bag has ended, then
    backward_fit exits, which ends the graph (status 0, parameters file written)."""
    fit_yaml = tmp_path / "fit.yaml"
    cmd = [sys.executable, "-m", "uw_sil.cli", "launch", "backward", "--bag", str(trial), "--frames", "10",
           "--stride", "4", "--optimizer", "cmaes", "--max-iter", "3", "--output-yaml", str(fit_yaml), "--rate", "2"]
    launch = Proc(cmd, ros_env(domain_id()), name="uw-sil launch backward")
    try:
        with logs_on_failure(launch):
            launch.wait_group(START)
            text = launch.text
            assert launch.popen.returncode == 0
            assert "fitting the 3 of 10 frames taken so far" in text
            assert "required node backward_fit ended: stopping sim_camera" in text
            assert "all nodes ended cleanly" in text
    finally:
        launch.stop()
    params = yaml.safe_load(fit_yaml.read_text())["/**"]["ros__parameters"]
    assert set(params) == set(RGB_NAMES) | {"fog_mode", "noise_sigma"}
    assert 0.5 < params["noise_sigma"] < 5.0      # the trial's camera noise, estimated on the water


def test_play_command_ends_with_the_bag(trial):
    """`uw-sil play` replays the bag and returns when it is done (no subscriber needed)."""
    t0 = time.monotonic()
    play = Proc([sys.executable, "-m", "uw_sil.cli", "play", str(trial), "--rate", "4"], ros_env(domain_id()),
                name="uw-sil play")
    try:
        with logs_on_failure(play):
            play.wait_group(START)
            assert play.popen.returncode == 0
            # 12 frames x (image, camera_info, pose, tf); /tf is skipped (with a warning) when tf2_msgs is missing
            tf = importlib.util.find_spec("tf2_msgs") is not None
            assert f"done: played {48 if tf else 36} messages" in play.text
            assert tf or "skipping /tf" in play.text
    finally:
        play.stop()
    assert time.monotonic() - t0 < 30


def test_a_stopped_node_waits_for_rclpys_signal_thread_before_it_is_destroyed():
    """rclpy shuts the context down in a thread of its own after SIGINT/SIGTERM; destroying publishers
    meanwhile crashed the enhancer once (SIGSEGV in destroy_publisher). The stop waits until the context
    is shut down, and gives up after its timeout when it never is."""
    from uw_sil.nodes import _await_signal_shutdown

    class FakeRclpy:
        def __init__(self, ok_calls):
            self.left, self.calls = ok_calls, 0

        def ok(self):
            self.calls += 1
            self.left -= 1
            return self.left >= 0

    shutting = FakeRclpy(3)                 # the signal thread finishes after three checks
    _await_signal_shutdown(shutting, timeout=30.0)
    assert shutting.calls == 4
    never = FakeRclpy(10**9)
    t0 = time.monotonic()
    _await_signal_shutdown(never, timeout=0.05)
    assert never.calls > 1 and time.monotonic() - t0 < 5.0
